// Flow pass 5, per pixel of a finer level: the flow of a coarser level (scale times smaller per axis, the
// pyramid's block mapping x_fine + 0.5 = scale (x_coarse + 0.5)) sampled bilinearly, clamped to its border,
// and multiplied by scale (pixels of the finer level). Non-finite values become 0.

layout(std430, binding = 6) readonly buffer SrcBuf { vec2 src_[]; };   // (Hc, Wc) coarse flow
layout(std430, binding = 7) writeonly buffer DstBuf { vec2 dst_[]; };  // (Hf, Wf) fine flow

uniform ivec2 src_size;  // Hc, Wc
uniform ivec2 dst_size;  // Hf, Wf
uniform float scale;

vec2 src_at(int y, int x) {
    return src_[clamp(y, 0, src_size.x - 1) * src_size.y + clamp(x, 0, src_size.y - 1)];
}

void main() {
    uint i = invocation();
    if (i >= uint(dst_size.x * dst_size.y)) return;
    int y = int(i) / dst_size.y, x = int(i) % dst_size.y;
    vec2 p = (vec2(float(x), float(y)) + 0.5) / scale - 0.5;
    p = clamp(p, vec2(0.0), vec2(float(src_size.y - 1), float(src_size.x - 1)));
    vec2 f = floor(p);
    vec2 t = p - f;
    int sx = int(f.x), sy = int(f.y);
    vec2 u = mix(mix(src_at(sy, sx), src_at(sy, sx + 1), t.x), mix(src_at(sy + 1, sx), src_at(sy + 1, sx + 1), t.x),
                 t.y) * scale;
    dst_[i] = nonfinite_bits(u) ? vec2(0.0) : u;
}
