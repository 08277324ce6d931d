// Flow refinement pass 1, per pixel of a level: the second image warped by the level's flow, and du = 0
// (refine_warp in flow_refine_common.glsl).
#include "flow_refine_common.glsl"

void main() {
    uint i = invocation();
    if (i >= uint(size.x * size.y)) return;
    refine_warp(int(i));
}
