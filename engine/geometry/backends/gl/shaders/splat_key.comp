// Splat pass 2: per destination bin, the largest log splat weight t = log(cover) + log_zbuf of the finite
// points landing there with cover != 0 (atomicMax on order-preserving bits).
#include "splat_common.glsl"

void main() {
    Point p;
    uint i = invocation();
    if (!project_point(i, p) || isinf(p.z)) return;
    float lw = log_zbuffer(p.z);
    for (int k = 0; k < 4; ++k) {
        int tap;
        float cover;
        tap_geometry(p, k, tap, cover);
        if (cover != 0.0) atomicMax(key_[tap], order_bits(log_splat_weight(cover, lw)));
    }
}
