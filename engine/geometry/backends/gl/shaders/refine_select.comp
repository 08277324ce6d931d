// Refinement pass 4 (decomp's refinement check), per pixel of the box: the WINDOW x WINDOW means of both
// errors (column sums of trust_blur_rows' row sums, BORDER_REFLECT within the box, in double as cv2.blur); the
// pixel keeps the refined flow where its mean error plus ``margin`` is below the initial flow's, else the
// initial flow, and no motion where frame n-k did not see the surface (seen_common.glsl), written into the
// flow (which may be the initial flow's buffer: a pixel reads its own initial flow before it writes).

layout(std430, binding = 22) buffer FlowBuf { vec2 flow_[]; };                 // (H, W) written in the box
layout(std430, binding = 30) readonly buffer InitBuf { vec2 init_[]; };        // (H, W) initial flow (may alias)
layout(std430, binding = 25) readonly buffer RowsBuf { dvec2 rows_[]; };       // (h, w) row sums
layout(std430, binding = 26) readonly buffer RefinedBuf { vec2 refined_[]; };  // (h, w)
layout(std430, binding = 1) readonly buffer DepthBuf { float depth_[]; };     // (H, W) frame n, +inf sky

#include "trust_common.glsl"
#include "seen_common.glsl"
uniform ivec2 frame;      // H, W of frame n
uniform ivec2 origin;     // (y0, x0) of the box
uniform float margin;

void main() {
    uint i = invocation();
    int h = size.x, w = size.y;
    if (i >= uint(h * w)) return;
    int y = int(i) / w, x = int(i) % w;
    dvec2 sum = dvec2(0.0);
    for (int d = -WINDOW / 2; d <= WINDOW / 2; ++d) {
        sum += rows_[reflect_index(y + d, h) * w + x];
    }
    float refined_err = float(sum.x * (1.0LF / double(WINDOW * WINDOW)));
    float init_err = float(sum.y * (1.0LF / double(WINDOW * WINDOW)));
    int gx = origin.y + x, gy = origin.x + y;
    uint g = uint(gy * frame.y + gx);
    precise float lowered = refined_err + margin;
    vec2 f = lowered < init_err ? refined_[i] : init_[g];
    if (!seen(gx, gy, depth_[g])) f = vec2(0.0);
    flow_[g] = f;
}
