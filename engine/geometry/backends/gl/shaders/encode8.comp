// The predicted colour (H, W, 3) float32 linear light as 8-bit sRGB codes (encode8_common.glsl), packed 3
// bytes a pixel (rows top to bottom, r g b), so a readback moves a quarter of the float frame's bytes. One
// invocation writes one 32-bit word, four codes of the byte stream, the first in the low byte (little-endian
// hosts).
layout(std430, binding = 0) readonly buffer ColorBuf { float color_[]; };
layout(std430, binding = 1) readonly buffer TableBuf { vec2 table_[]; };  // per bucket (step, level)
layout(std430, binding = 2) writeonly buffer CodeBuf { uint codes_[]; };

#include "encode8_common.glsl"

uniform uint count;  // 3 H W values

void main() {
    uint i = invocation();
    uint first = 4u * i;
    if (first >= count) return;
    uint word = 0u;
    for (uint j = 0u; j < 4u; ++j) {
        if (first + j < count) word |= encode8(color_[first + j]) << (8u * j);
    }
    codes_[i] = word;
}
