// A frame's colour (H, W, 3) float32 linear light, rows top to bottom (a GlImage's or a GlPrediction's buffer),
// stored into a texture as GL keeps images: texel (x, H - 1 - y) holds pixel (x, y), alpha 1. The texture is
// RGBA16F or RGBA32F (linear: the value as it is, rounded to the format), or with SRGB8 an RGBA8 texture of the
// 8-bit sRGB codes (encode8_common.glsl: the CPU's codes bit for bit; stored as code / 255, read back as code).
layout(std430, binding = 0) readonly buffer ColorBuf { float color_[]; };
#ifdef SRGB8
layout(std430, binding = 1) readonly buffer TableBuf { vec2 table_[]; };  // per bucket (step, level)
layout(rgba8, binding = 0) writeonly uniform image2D target;
#include "encode8_common.glsl"
#else
layout(IMAGE_FORMAT, binding = 0) writeonly uniform image2D target;
#endif

uniform ivec2 size;  // (H, W)

void main() {
    uint i = invocation();
    uint w = uint(size.y);
    if (i >= uint(size.x) * w) return;
    vec3 c = vec3(color_[3u * i], color_[3u * i + 1u], color_[3u * i + 2u]);
#ifdef SRGB8
    c = vec3(encode8(c.r), encode8(c.g), encode8(c.b)) / 255.0;
#endif
    imageStore(target, ivec2(int(i % w), size.x - 1 - int(i / w)), vec4(c, 1.0));
}
