// A coarser level's flow at a pixel of a finer one (passes flow_upsample and flow_coarse; FLOW_SOURCE(j) is
// element j of the coarse (Hc, Wc) flow): sampled bilinearly at the pyramid's block mapping x_fine + 0.5 =
// scale (x_coarse + 0.5), clamped to its border, and multiplied by scale (pixels of the finer level).
// Non-finite values become 0.

vec2 upsample_at(int y, int x, ivec2 src_size, float scale) {
    vec2 p = (vec2(float(x), float(y)) + 0.5) / scale - 0.5;
    p = clamp(p, vec2(0.0), vec2(float(src_size.y - 1), float(src_size.x - 1)));
    vec2 f = floor(p);
    vec2 t = p - f;
    int sx = int(f.x), sy = int(f.y);
    int x1 = min(sx + 1, src_size.y - 1), y1 = min(sy + 1, src_size.x - 1);
    vec2 top = mix(FLOW_SOURCE(sy * src_size.y + sx), FLOW_SOURCE(sy * src_size.y + x1), t.x);
    vec2 bottom = mix(FLOW_SOURCE(y1 * src_size.y + sx), FLOW_SOURCE(y1 * src_size.y + x1), t.x);
    vec2 u = mix(top, bottom, t.y) * scale;
    return nonfinite_bits(u) ? vec2(0.0) : u;
}
