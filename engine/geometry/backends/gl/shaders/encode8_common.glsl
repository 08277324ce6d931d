// 8-bit display encoding of linear light, the CPU kernel's rule (engine.geometry.kernels.encode8, oracle
// engine.core.colorspace.encode8_reference): clip to [0, 1] (NaN and values <= 0 give the first level), bucket
// b = floor(c * BUCKETS) (exact: a power of two), code level[b] + (c >= step[b]). The including pass declares
// table_, the rows (step, level) of colorspace.encode8_table (engine.geometry.backends.gl.frame
// .encode8_table_rows), and BUCKETS is defined at compile time: bit for bit the CPU's codes.
uint encode8(float c) {
    if (nan_bits(c) || c <= 0.0) return uint(table_[0].y);  // NaN by its bits (context.py: NVIDIA folds negations)
    c = min(c, 1.0);
    vec2 bucket = table_[int(c * float(BUCKETS))];
    return uint(bucket.y) + (c >= bucket.x ? 1u : 0u);
}
