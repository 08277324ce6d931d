// Flow refinement pass 4, per pixel of one colour of a checkerboard: one red-black SOR step (refine_sor in
// flow_refine_common.glsl).
#include "flow_refine_common.glsl"

uniform int parity;  // the colour updated: (x + y) % 2

void main() {
    uint i = invocation();
    if (i >= uint(size.x * size.y)) return;
    refine_sor(int(i), parity);
}
