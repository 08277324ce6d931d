// Flow pass 3, per patch of a pyramid level: DIS inverse search (Kroeger et al. 2016), the patch of the first
// image matched in the second by inverse-compositional Lucas-Kanade with mean normalisation. The template's
// gradients (central differences, centred on their patch means) give a fixed 2 x 2 Hessian (+ EPS I); each
// iteration samples the second image at x + u (bilinear), takes the mean-normalised difference e and steps
// u -= H^-1 sum(g e). The first sweep starts from the level's initial dense flow at the patch centre; with
// PROPAGATE (later sweeps) from the lowest mean-normalised SSD of the patch's own and its 4 neighbours'
// previous flows (a parallel stand-in for DIS's sequential spatial propagation). The result is the last
// iterate, or the start where that has a higher SSD or lies more than a patch away (flow_patch_thread.glsl).
#include "flow_patch_common.glsl"
#include "flow_patch_thread.glsl"

void main() {
    uint i = invocation();
    if (i >= uint(patch_count(size.x) * patch_count(size.y))) return;
#ifdef PROPAGATE
    patch_[i] = search_patch(int(i), true);
#else
    patch_[i] = search_patch(int(i), false);
#endif
}
