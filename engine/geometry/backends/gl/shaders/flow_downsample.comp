// Flow pass 2, per pixel of pyramid level l + 1: the mean of its 2 x 2 block of level l (H_{l+1} =
// ceil(H_l / 2); a block past an odd border repeats the last row / column), so pixel centres map as
// x_l + 0.5 = 2 (x_{l+1} + 0.5).

layout(std430, binding = 1) buffer LumaBuf { float luma_[]; };  // all levels of one pyramid

uniform ivec2 src_size;  // H, W of level l
uniform ivec2 dst_size;  // H, W of level l + 1
uniform int src_offset;
uniform int dst_offset;

float src_at(int y, int x) {
    return luma_[src_offset + min(y, src_size.x - 1) * src_size.y + min(x, src_size.y - 1)];
}

void main() {
    uint i = invocation();
    if (i >= uint(dst_size.x * dst_size.y)) return;
    int y = int(i) / dst_size.y, x = int(i) % dst_size.y;
    luma_[dst_offset + int(i)] = 0.25 * (src_at(2 * y, 2 * x) + src_at(2 * y, 2 * x + 1)
                                         + src_at(2 * y + 1, 2 * x) + src_at(2 * y + 1, 2 * x + 1));
}
