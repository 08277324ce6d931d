// Flow pass 1, per pixel: the 8-bit luma OpenCV DIS reads (engine.predict.dis.luma8) of linear RGB (H, W, 3):
// each channel display-encoded to 8 bits (encode8_common.glsl: clip to [0, 1], sRGB, round; NaN -> 0), then
// OpenCV 5's fixed-point RGB -> grey, (19596 R + 38470 G + 7470 B + 2^15) >> 16 (equal to cv2.cvtColor for all
// 2^24 colours, measured; the test holds this pass to luma8).

layout(std430, binding = 0) readonly buffer ColorBuf { float color_[]; };  // (H, W, 3) linear RGB
layout(std430, binding = 1) writeonly buffer LumaBuf { float luma_[]; };   // (H, W) level 0 of a pyramid
layout(std430, binding = 2) readonly buffer TableBuf { vec2 table_[]; };   // per bucket (step, level)

#include "encode8_common.glsl"

uniform int count;  // H * W

void main() {
    uint i = invocation();
    if (i >= uint(count)) return;
    uint r = encode8(color_[3u * i]), g = encode8(color_[3u * i + 1u]), b = encode8(color_[3u * i + 2u]);
    luma_[i] = float((19596u * r + 38470u * g + 7470u * b + 32768u) >> 16);
}
