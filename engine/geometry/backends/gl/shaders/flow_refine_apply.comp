// Flow refinement pass 5, per pixel of a level: u <- u + du (a non-finite increment is dropped).
#include "flow_refine_common.glsl"

void main() {
    uint i = invocation();
    if (i >= uint(size.x * size.y)) return;
    vec2 du = inc_[i];
    if (!nonfinite_bits(du)) dense_[i] += du;
}
