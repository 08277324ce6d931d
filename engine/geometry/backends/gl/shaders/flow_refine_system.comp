// Flow refinement pass 3, per pixel of a level, once per fixed-point iteration: the linear system
// (refine_system in flow_refine_common.glsl).
#include "flow_refine_common.glsl"

void main() {
    uint i = invocation();
    if (i >= uint(size.x * size.y)) return;
    refine_system(int(i));
}
