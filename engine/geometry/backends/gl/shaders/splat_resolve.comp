// Splat pass 4: per output pixel, normalise its bin (the padding ring is cropped).
// MPI: (r, g, b, depth, alpha, coverage) planes (6, Z, HO, WO) into out_.
// FRAME: the one-plane composite: warped_ (HO, WO, 4) = (r, g, b, depth) (0, 0, 0, +inf on holes; depth
// +inf where only sky landed) and hole_ (HO, WO) = 1 where nothing covered the pixel.
#include "splat_common.glsl"

layout(std430, binding = 8) writeonly buffer OutBuf { float out_[]; };
layout(std430, binding = 10) writeonly buffer HoleBuf { uint hole_[]; };

double read64(int word) {
    return double(int64_t(packUint2x32(uvec2(acc_[word], acc_[word + 1])))) * (1.0LF / 4294967296.0LF);
}

void main() {
    uint i = invocation();
    int ho = dst_size.x, wo = dst_size.y;
    int m = src_size.x * ho * wo;
    if (i >= uint(m)) return;
    int o = int(i);
    int x = o % wo, y = (o / wo) % ho, plane = o / (wo * ho);
    int bin = (plane * (ho + 2) + y + 1) * (wo + 2) + x + 1;
    int word = bin * 12;
    vec4 rgbd = vec4(0.0);
    float covered = 0.0, coverage = 0.0;
    if (acc_[word] != 0u || acc_[word + 1] != 0u) {
        double cov = read64(word);
        double wsum = read64(word + 2);
        coverage = float(cov);
        if (cov > coverage_threshold) {
            covered = 1.0;
            double inv_w = wsum > 0.0LF ? 1.0LF / wsum : 0.0LF;
            rgbd = vec4(float(read64(word + 4) * inv_w), float(read64(word + 6) * inv_w),
                        float(read64(word + 8) * inv_w), float(read64(word + 10) * inv_w));
            if (key_[bin] == 0u) rgbd.w = INF;  // only sky landed here
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
    out_[o] = rgbd.x;
    out_[m + o] = rgbd.y;
    out_[2 * m + o] = rgbd.z;
    out_[3 * m + o] = rgbd.w;
    out_[4 * m + o] = covered;
    out_[5 * m + o] = coverage;
#endif
}
