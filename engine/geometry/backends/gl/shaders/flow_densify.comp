// Flow pass 4, per pixel of a pyramid level: DIS densification (flow_densify.glsl), the patch flows averaged
// per pixel, weighted by their photometric error.
#include "flow_common.glsl"

layout(std430, binding = 5) readonly buffer PatchBuf { vec2 patch_[]; };  // (rows, columns) patch flows
layout(std430, binding = 6) writeonly buffer DenseBuf { vec2 dense_[]; }; // (H, W) dense flow

#include "flow_densify.glsl"

void main() {
    uint i = invocation();
    if (i >= uint(size.x * size.y)) return;
    dense_[i] = densify_at(int(i) / size.y, int(i) % size.y);
}
