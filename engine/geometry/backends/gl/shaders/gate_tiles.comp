// Motion gate pass 3 (engine.predict.decomp.gate.tile_counts), per pixel of the working resolution: a changed
// pixel (gate_residual) that survives the 3 x 3 erosion (ERODE; cv2.erode's border: pixels outside the image do
// not erode) and whose surface frame n-k saw (UNSEEN: seen_common.glsl with frame n's working-resolution depth)
// adds 1 to its tile's count.
layout(std430, binding = 23) readonly buffer ChangedBuf { uint changed_[]; };   // (h, w) 0 / 1
layout(std430, binding = 21) readonly buffer LowDepthBuf { float low_depth_[]; };  // frame n (h, w)
layout(std430, binding = 24) coherent buffer CountBuf { uint counts_[]; };      // (tiles_h, tiles_w)

uniform ivec2 size;   // (h, w)
uniform int tile;
uniform int tiles_w;

#include "seen_common.glsl"

void main() {
    uint i = invocation();
    int h = size.x, w = size.y;
    if (i >= uint(h * w) || changed_[i] == 0u) return;
    int y = int(i) / w, x = int(i) % w;
#ifdef ERODE
    for (int dy = -1; dy <= 1; ++dy) {
        for (int dx = -1; dx <= 1; ++dx) {
            int yy = y + dy, xx = x + dx;
            if (yy >= 0 && yy < h && xx >= 0 && xx < w && changed_[yy * w + xx] == 0u) return;
        }
    }
#endif
#ifdef UNSEEN
    if (!seen(x, y, low_depth_[i])) return;
#endif
    atomicAdd(counts_[(y / tile) * tiles_w + x / tile], 1u);
}
