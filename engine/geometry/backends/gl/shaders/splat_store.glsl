// The splat's last step, shared by splat_resolve (sums from the atomic bins) and splat_gather (sums in
// registers): normalise one output pixel's 64-bit fixed-point sums (2^-32 units) and store it.
// MPI: (r, g, b, depth, alpha, coverage) planes (6, Z, HO, WO) into out_.
// FRAME: the one-plane composite: out_ (HO, WO, 4) = (r, g, b, depth) (0, 0, 0, +inf on holes; depth
// +inf where only sky landed) and hole_ (HO, WO) = 1 where nothing covered the pixel.

layout(std430, binding = 8) writeonly buffer OutBuf { float out_[]; };
layout(std430, binding = 10) writeonly buffer HoleBuf { uint hole_[]; };

double fixed_value(int64_t sum) {
    return double(sum) * (1.0LF / 4294967296.0LF);
}

// output pixel o (flat in (Z, HO, WO)); sums = weight * (r, g, b, z); finite: a finite point reached the bin
// (else its weight is all sky and a covered pixel's depth is +inf)
void store_pixel(int o, int64_t cov, int64_t wsum, i64vec4 sums, bool finite) {
    vec4 rgbd = vec4(0.0);
    float covered = 0.0, coverage = 0.0;
    if (cov != 0l) {
        double c = fixed_value(cov);
        double w = fixed_value(wsum);
        coverage = float(c);
        if (c > coverage_threshold) {
            covered = 1.0;
            double inv_w = w > 0.0LF ? 1.0LF / w : 0.0LF;
            rgbd = vec4(float(fixed_value(sums.x) * inv_w), float(fixed_value(sums.y) * inv_w),
                        float(fixed_value(sums.z) * inv_w), float(fixed_value(sums.w) * inv_w));
            if (!finite) rgbd.w = INF;
        }
    }
#ifdef FRAME
    if (covered == 0.0) rgbd.w = INF;
    out_[4 * o] = rgbd.x;
    out_[4 * o + 1] = rgbd.y;
    out_[4 * o + 2] = rgbd.z;
    out_[4 * o + 3] = rgbd.w;
    hole_[o] = covered == 0.0 ? 1u : 0u;
#else
    int m = src_size.x * dst_size.x * dst_size.y;
    out_[o] = rgbd.x;
    out_[m + o] = rgbd.y;
    out_[2 * m + o] = rgbd.z;
    out_[3 * m + o] = rgbd.w;
    out_[4 * m + o] = covered;
    out_[5 * m + o] = coverage;
#endif
}

// the padded bin (plane, y + 1, x + 1) of output pixel o
int output_bin(int o) {
    int ho = dst_size.x, wo = dst_size.y;
    int x = o % wo, y = (o / wo) % ho, plane = o / (wo * ho);
    return (plane * (ho + 2) + y + 1) * (wo + 2) + x + 1;
}
