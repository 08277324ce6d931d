// Binned splat pass 5: per output pixel, the splat sums of its bin gathered from the records of the four
// bins whose points have a tap on it (itself, left, above, above-left), in registers: the largest log weight
// t_max of the finite points first, then the 64-bit fixed-point sums of coverage, weight and weight * (r, g,
// b, z), each term exactly splat_accumulate's, so the sums are the atomic splat's bits (exact integer sums
// do not depend on the order); sky points weigh only where no finite point reached the bin. The records of
// the left and own bins are one run (bins are consecutive), split where the own bin's start; so are those of
// the above-left and above bins. Output as splat_store.glsl says.
#include "splat_common.glsl"
#include "splat_store.glsl"

int64_t fixed64(float value) {
    return int64_t(packUint2x32(fixed_parts(value)));
}

// the cover of record r's tap on this bin, from the bin to its left (left) or itself, above (up) or level;
// z: the record's depth
float record_cover(uvec4 r, bool left, bool up, out float z) {
    float fx = uintBitsToFloat(r.x), fy = uintBitsToFloat(r.y);
    z = uintBitsToFloat(r.z);
#ifdef FRAME
    float a = 1.0;
#else
    float a = alpha_[r.w];
#endif
    float wx = left ? fx : 1.0 - fx;
    float wy = up ? fy : 1.0 - fy;
    return wx * wy * a;
}

void main() {
    uint i = invocation();
    if (i >= uint(src_size.x * dst_size.x * dst_size.y)) return;
    int o = int(i);
    int bin = output_bin(o);
    int wp = dst_size.y + 2;
    // per row r (0: the bins above, 1: this row), the records of the left bin, then of the bin over this one:
    // [first[r], split[r]) and [split[r], stop[r])
    uvec2 first = uvec2(bin_start(bin - wp - 1), bin_start(bin - 1));
    uvec2 split = uvec2(bin_start(bin - wp), bin_start(bin));
    uvec2 stop = uvec2(bin_start(bin - wp + 1), bin_start(bin + 1));
    float t_max = -INF;
    bool finite = false;
    for (int r = 0; r < 2; ++r) {
        for (uint j = first[r]; j < stop[r]; ++j) {
            float z;
            float cover = record_cover(record_[j], j < split[r], r == 0, z);
            if (cover != 0.0 && !isinf(z)) {
                t_max = max(t_max, log_splat_weight(cover, log_zbuffer(z)));
                finite = true;
            }
        }
    }
    int64_t cov = 0l, wsum = 0l;
    i64vec4 sums = i64vec4(0l);
    for (int r = 0; r < 2; ++r) {
        for (uint j = first[r]; j < stop[r]; ++j) {
            uvec4 rec = record_[j];
            float z;
            float cover = record_cover(rec, j < split[r], r == 0, z);
            if (cover == 0.0) continue;
            cov += fixed64(cover);
            bool sky = isinf(z);
            if (sky && finite) continue;  // a finite point landed here: sky counts for nothing
            float weight = sky ? cover : relative_weight(cover, log_zbuffer(z), t_max);
            vec3 rgb = point_color(rec.w);
            wsum += fixed64(weight);
            sums += i64vec4(fixed64(weight * rgb.r), fixed64(weight * rgb.g), fixed64(weight * rgb.b),
                            sky ? 0l : fixed64(weight * z));
        }
    }
    store_pixel(o, cov, wsum, sums, finite);
}
