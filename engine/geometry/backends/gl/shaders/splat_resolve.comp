// Splat pass 4 (atomic splat): per output pixel, normalise its bin (the padding ring is cropped); output as
// splat_store.glsl says.
#include "splat_common.glsl"
#include "splat_store.glsl"

int64_t read64(int word) {
    return int64_t(packUint2x32(uvec2(acc_[word], acc_[word + 1])));
}

void main() {
    uint i = invocation();
    if (i >= uint(src_size.x * dst_size.x * dst_size.y)) return;
    int o = int(i);
    int bin = output_bin(o);
    int word = bin * 12;
    int64_t cov = read64(word);
    i64vec4 sums = i64vec4(0l);
    int64_t wsum = 0l;
    if (cov != 0l) {
        wsum = read64(word + 2);
        sums = i64vec4(read64(word + 4), read64(word + 6), read64(word + 8), read64(word + 10));
    }
    store_pixel(o, cov, wsum, sums, key_[bin] != 0u);
}
