// Flow refinement pass 2, per pixel of a level: the derivatives of the refinement's energy
// (refine_derivs in flow_refine_common.glsl).
#include "flow_refine_common.glsl"

void main() {
    uint i = invocation();
    if (i >= uint(size.x * size.y)) return;
    refine_derivs(int(i));
}
