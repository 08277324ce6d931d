// Flow pass 5, per pixel of a finer level: the flow of a coarser level, bilinear and scaled
// (flow_upsample.glsl).

layout(std430, binding = 6) readonly buffer SrcBuf { vec2 src_[]; };   // (Hc, Wc) coarse flow
layout(std430, binding = 7) writeonly buffer DstBuf { vec2 dst_[]; };  // (Hf, Wf) fine flow

uniform ivec2 src_size;  // Hc, Wc
uniform ivec2 dst_size;  // Hf, Wf
uniform float scale;

#define FLOW_SOURCE(j) src_[j]
#include "flow_upsample.glsl"

void main() {
    uint i = invocation();
    if (i >= uint(dst_size.x * dst_size.y)) return;
    dst_[i] = upsample_at(int(i) / dst_size.y, int(i) % dst_size.y, src_size, scale);
}
