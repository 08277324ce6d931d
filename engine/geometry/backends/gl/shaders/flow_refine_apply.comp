// Flow refinement pass 5, per pixel of a level: u <- u + du (refine_apply in flow_refine_common.glsl).
#include "flow_refine_common.glsl"

void main() {
    uint i = invocation();
    if (i >= uint(size.x * size.y)) return;
    refine_apply(int(i));
}
