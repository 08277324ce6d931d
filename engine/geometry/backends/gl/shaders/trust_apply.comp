// Trust pass 3, per pixel of frame n (engine.predict.dis.trusted_motion): keep the flow u(n -> n-k) only
// where frame n-k saw the surface (engine.geometry.seen_before: the pixel reprojected with frame n's depth
// into camera n-k lands in front of it and inside its (h, w) image) and, for motion under ``small`` pixels,
// where it explains frame n better than none: the WINDOW x WINDOW mean of moved_ below that of still_ by more
// than ``margin`` levels. Elsewhere the flow is set to 0, in place.
layout(std430, binding = 1) readonly buffer DepthBuf { float depth_[]; };    // (H, W) frame n, +inf sky
layout(std430, binding = 22) buffer FlowBuf { vec2 flow_[]; };               // (H, W)
layout(std430, binding = 25) readonly buffer RowsBuf { dvec2 rows_[]; };      // (H, W) row sums

#include "trust_common.glsl"
#include "seen_common.glsl"
uniform float small;
uniform float margin;

void main() {
    uint i = invocation();
    int h = size.x, w = size.y;
    if (i >= uint(h * w)) return;
    int y = int(i) / w, x = int(i) % w;
    vec2 f = flow_[i];
    bool keep = seen(x, y, depth_[i]);
    if (keep && length(vec2(f)) < small) {  // hypot
        dvec2 sum = dvec2(0.0);
        for (int d = -WINDOW / 2; d <= WINDOW / 2; ++d) {
            sum += rows_[reflect_index(y + d, h) * w + x];
        }
        float still = float(sum.x * (1.0LF / double(WINDOW * WINDOW)));
        float moved = float(sum.y * (1.0LF / double(WINDOW * WINDOW)));
        keep = moved < still - margin;
    }
    if (!keep) flow_[i] = vec2(0.0);
}
