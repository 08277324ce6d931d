// Refinement pass 1 (decomp's network input), per pixel of a box at the network's working resolution
// (``low_size``): the block mean of the initial flow over its factor x factor pixels of frame n, in its pixels
// (engine.geometry.downsample_flow: the block's rows, then its columns, summed in float32, divided by f^2 and
// by f, each quotient rounded as numpy rounds it).

layout(std430, binding = 30) readonly buffer InitBuf { vec2 init_[]; };   // (H, W) initial u(n -> n-k)
layout(std430, binding = 26) writeonly buffer LowBuf { vec2 low_[]; };    // (h_low, w_low)

uniform ivec2 frame;     // H, W of frame n
uniform ivec2 origin;    // (y0, x0) of the box in frame n
uniform ivec2 low_size;  // (h_low, w_low)
uniform int factor;

void main() {
    uint i = invocation();
    if (i >= uint(low_size.x * low_size.y)) return;
    int y = int(i) / low_size.y, x = int(i) % low_size.y;
    int y0 = origin.x + y * factor, x0 = origin.y + x * factor;
    precise vec2 sum = init_[y0 * frame.y + x0];
    for (int dy = 0; dy < factor; ++dy) {
        for (int dx = 0; dx < factor; ++dx) {
            if (dy != 0 || dx != 0) sum += init_[(y0 + dy) * frame.y + x0 + dx];
        }
    }
    double ff = double(factor * factor), f = double(factor);
    vec2 mean = vec2(float(double(sum.x) / ff), float(double(sum.y) / ff));
    low_[i] = vec2(float(double(mean.x) / f), float(double(mean.y) / f));
}
