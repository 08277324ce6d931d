// A frame's colour sent as 8-bit sRGB codes, (H, W, CHANNELS) uint8 with CHANNELS 3 or 4 (alpha ignored), rows
// top to bottom, decoded on the GPU into the backend's frame layout, (H, W, 3) float32 linear light, by the
// 256-entry table of engine.geometry.encoding.decode8: bit for bit the CPU's decoding. The codes arrive as
// 32-bit words of the byte stream (the first byte in the low bits: little-endian hosts).
layout(std430, binding = 0) readonly buffer CodeBuf { uint codes_[]; };
layout(std430, binding = 1) readonly buffer TableBuf { float table_[]; };  // linear light of code 0..255
layout(std430, binding = 2) writeonly buffer ColorBuf { float color_[]; };

uniform uint count;     // H * W
uniform uint channels;  // bytes a pixel: 3 or 4

uint code(uint offset) {
    return (codes_[offset >> 2u] >> (8u * (offset & 3u))) & 0xffu;
}

void main() {
    uint i = invocation();
    if (i >= count) return;
    uint first = channels * i;
    color_[3u * i] = table_[code(first)];
    color_[3u * i + 1u] = table_[code(first + 1u)];
    color_[3u * i + 2u] = table_[code(first + 2u)];
}
