// Binned splat pass 5: per output pixel, the splat sums of its bin gathered from the records of the four
// bins whose points have a tap on it (itself, left, above, above-left), in registers: the largest log weight
// t_max of the finite points first, then the 64-bit fixed-point sums of coverage, weight and weight * (r, g,
// b, z), each term exactly splat_accumulate's, so the sums are the atomic splat's bits (exact integer sums
// do not depend on the order); sky points weigh only where no finite point reached the bin. Output as
// splat_store.glsl says.
#include "splat_common.glsl"
#include "splat_store.glsl"

int64_t fixed64(float value) {
    return int64_t(packUint2x32(fixed_parts(value)));
}

// tap k (0: top-left .. 3: bottom-right) of the point of record r: its cover, depth and source index
float record_cover(uvec4 r, int k, out float z) {
    float fx = uintBitsToFloat(r.x), fy = uintBitsToFloat(r.y);
    z = uintBitsToFloat(r.z);
#ifdef FRAME
    float a = 1.0;
#else
    float a = alpha_[r.w];
#endif
    float wx = (k & 1) != 0 ? fx : 1.0 - fx;
    float wy = (k & 2) != 0 ? fy : 1.0 - fy;
    return wx * wy * a;
}

void main() {
    uint i = invocation();
    if (i >= uint(src_size.x * dst_size.x * dst_size.y)) return;
    int o = int(i);
    int bin = output_bin(o);
    int wp = dst_size.y + 2;
    ivec4 sources = ivec4(bin, bin - 1, bin - wp, bin - wp - 1);  // bins whose tap k lands on this one
    uvec4 starts, stops;
    for (int k = 0; k < 4; ++k) {
        starts[k] = bin_start(sources[k]);
        stops[k] = bin_start(sources[k] + 1);
    }
    float t_max = -INF;
    bool finite = false;
    for (int k = 0; k < 4; ++k) {
        for (uint j = starts[k]; j < stops[k]; ++j) {
            float z;
            float cover = record_cover(record_[j], k, z);
            if (cover != 0.0 && !isinf(z)) {
                t_max = max(t_max, log_splat_weight(cover, log_zbuffer(z)));
                finite = true;
            }
        }
    }
    int64_t cov = 0l, wsum = 0l;
    i64vec4 sums = i64vec4(0l);
    for (int k = 0; k < 4; ++k) {
        for (uint j = starts[k]; j < stops[k]; ++j) {
            uvec4 r = record_[j];
            float z;
            float cover = record_cover(r, k, z);
            if (cover == 0.0) continue;
            cov += fixed64(cover);
            bool sky = isinf(z);
            if (sky && finite) continue;  // a finite point landed here: sky counts for nothing
            float weight = sky ? cover : relative_weight(cover, log_zbuffer(z), t_max);
            vec3 rgb = point_color(r.w);
            wsum += fixed64(weight);
            sums += i64vec4(fixed64(weight * rgb.r), fixed64(weight * rgb.g), fixed64(weight * rgb.b),
                            sky ? 0l : fixed64(weight * z));
        }
    }
    store_pixel(o, cov, wsum, sums, finite);
}
