// The predicted colour (H, W, 3) float32 linear light as 8-bit sRGB codes, packed 3 bytes a pixel (rows top
// to bottom, r g b), so a readback moves a quarter of the float frame's bytes. The rule is the CPU kernel's
// (engine.geometry.kernels.encode8, oracle engine.core.colorspace.encode8_reference): clip to [0, 1] (NaN and
// values <= 0 give level[0]), bucket b = floor(c * buckets) (exact: buckets is a power of two), code
// level[b] + (c >= step[b]) from colorspace.encode8_table: bit for bit the CPU's codes. One invocation writes
// one 32-bit word, four codes of the byte stream, the first in the low byte (little-endian hosts).
layout(std430, binding = 0) readonly buffer ColorBuf { float color_[]; };
layout(std430, binding = 1) readonly buffer TableBuf { uvec2 table_[]; };  // (level, bits of step) per bucket
layout(std430, binding = 2) writeonly buffer CodeBuf { uint codes_[]; };

uniform uint count;    // 3 H W values
uniform float buckets;

uint code(float c) {
    if (nan_bits(c) || c <= 0.0) return table_[0].x;  // NaN by its bits (context.py: NVIDIA folds negations)
    c = min(c, 1.0);
    uvec2 entry = table_[uint(c * buckets)];
    return c >= uintBitsToFloat(entry.y) ? entry.x + 1u : entry.x;
}

void main() {
    uint i = invocation();
    uint first = 4u * i;
    if (first >= count) return;
    uint word = 0u;
    for (uint j = 0u; j < 4u; ++j) {
        if (first + j < count) word |= code(color_[first + j]) << (8u * j);
    }
    codes_[i] = word;
}
