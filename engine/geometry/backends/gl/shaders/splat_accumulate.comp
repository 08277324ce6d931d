// Splat pass 3: fixed-point sums of coverage, weight and weight * (r, g, b, z) per bin; the weight is
// relative to the bin's largest (cover * zbuf / exp(t_max), in (0, 1]). Sky points count only in bins no
// finite point reached.
#include "splat_common.glsl"

void add64(int word, float value) {
    // 64-bit fixed point (2^-32 units) added with two 32-bit atomics; exact and order-independent
    uvec2 parts = fixed_parts(value);
    uint old = atomicAdd(acc_[word], parts.x);
    uint high = parts.y + (old + parts.x < old ? 1u : 0u);
    if (high != 0u) atomicAdd(acc_[word + 1], high);
}

void main() {
    uint i = invocation();
    Point p;
    if (!project_point(i, p)) return;
    vec3 rgb = point_color(i);
    bool sky = isinf(p.z);
    float lw = sky ? 0.0 : log_zbuffer(p.z);
    for (int k = 0; k < 4; ++k) {
        int tap;
        float cover;
        tap_geometry(p, k, tap, cover);
        if (cover == 0.0) continue;
        int word = tap * 12;
        add64(word, cover);
        uint key = key_[tap];
        float weight;
        if (sky) {
            if (key != 0u) continue;  // a finite point landed here: sky counts for nothing
            weight = cover;
        } else {
            weight = relative_weight(cover, lw, order_float(key));
        }
        add64(word + 2, weight);
        add64(word + 4, weight * rgb.r);
        add64(word + 6, weight * rgb.g);
        add64(word + 8, weight * rgb.b);
        if (!sky) add64(word + 10, weight * p.z);
    }
}
