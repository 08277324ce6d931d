// Trust pass 1, per pixel of frame n: the photometric errors engine.predict.dis.confident_motion averages:
// still_ = |luma_n - target| (no object motion), moved_ = |luma_n - target sampled at the pixel moved by the
// flow u(n -> n-k)| (remap_common.glsl: OpenCV 5's remap; a sample below 0 costs 255).

layout(std430, binding = 20) readonly buffer LumaNBuf { float luma_n_[]; };   // (H, W) 8-bit levels
layout(std430, binding = 21) readonly buffer TargetBuf { float target_[]; };  // (H, W) 8-bit levels
layout(std430, binding = 22) readonly buffer FlowBuf { vec2 flow_[]; };       // (H, W) u(n -> n-k) pixels
layout(std430, binding = 23) writeonly buffer StillBuf { float still_[]; };   // (H, W)
layout(std430, binding = 24) writeonly buffer MovedBuf { float moved_[]; };   // (H, W)

uniform ivec2 size;  // H, W

#include "remap_common.glsl"

void main() {
    uint i = invocation();
    int h = size.x, w = size.y;
    if (i >= uint(h * w)) return;
    int y = int(i) / w, x = int(i) % w;
    float luma = luma_n_[i];
    still_[i] = abs(luma - target_[i]);
    moved_[i] = remap_error(luma, x, y, flow_[i], size);
}
