// Motion gate pass 1 (engine.geometry.downsample_frame), per pixel of the working resolution (low_size): the
// colour is the mean of its factor x factor block of frame pixels (summed in float32 in row-major order, then
// scaled by 1 / factor^2: OpenCV's INTER_AREA, which the CPU calls, to within an ulp), the depth the block's
// minimum (+inf only where the whole block is sky). RANGE: also the smallest and largest finite depth, as
// atomics on the bits of positive floats (which order as the floats do).
layout(std430, binding = 0) readonly buffer ColorBuf { float color_[]; };      // (H, W, 3) linear RGB
layout(std430, binding = 1) readonly buffer DepthBuf { float depth_[]; };      // (H, W) planar, +inf sky
layout(std430, binding = 20) writeonly buffer LowColorBuf { float low_color_[]; };  // (h, w, 3)
layout(std430, binding = 21) writeonly buffer LowDepthBuf { float low_depth_[]; };  // (h, w)
#ifdef RANGE
layout(std430, binding = 22) coherent buffer RangeBuf { uint range_[]; };  // bits of (min, max) finite depth
#endif

uniform int width;       // W of the frame
uniform ivec2 low_size;  // (h, w)
uniform int factor;
uniform float scale;     // float32(1 / factor^2)

void main() {
    uint i = invocation();
    if (i >= uint(low_size.x * low_size.y)) return;
    int y = int(i) / low_size.y, x = int(i) % low_size.y;
    int y0 = y * factor, x0 = x * factor;
    precise vec3 sum = vec3(0.0);
    float d = depth_[y0 * width + x0];
    for (int dy = 0; dy < factor; ++dy) {
        for (int dx = 0; dx < factor; ++dx) {
            int p = (y0 + dy) * width + x0 + dx;
            sum += vec3(color_[3 * p], color_[3 * p + 1], color_[3 * p + 2]);
            d = min(d, depth_[p]);
        }
    }
    precise vec3 mean = sum * scale;
    low_color_[3u * i] = mean.x;
    low_color_[3u * i + 1u] = mean.y;
    low_color_[3u * i + 2u] = mean.z;
    low_depth_[i] = d;
#ifdef RANGE
    if (!nonfinite_bits(d)) {
        atomicMin(range_[0], floatBitsToUint(d));
        atomicMax(range_[1], floatBitsToUint(d));
    }
#endif
}
