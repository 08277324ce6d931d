// Flow pass "coarse": the coarse levels of the pyramid, from the coarsest down to level `last`, in one
// workgroup and one dispatch. Per level, every step of the passes in their order, each a loop of the
// workgroup's invocations over the level's pixels or patches and a barrier after it: the initial flow
// (0 at the coarsest, else flow_upsample's of the coarser level's dense flow), `sweeps` inverse searches
// (flow_patch: each sweep's patch flows are copied to prev_ for the next), flow_densify, and the refinement
// (flow_refine_warp, _derivs, per fixed-point iteration _system and red-black _sor, _apply). The same
// arithmetic as the passes: on a small level a dispatch per step leaves the GPU almost idle, waiting on the
// next command, and 64 dispatches a level became one for all the coarse levels. The result is the dense flow
// of level `last` in dense_ (binding 6), where the passes of the finer levels read it.
#define COARSE 1
#include "flow_patch_common.glsl"
#include "flow_patch_thread.glsl"
#include "flow_densify.glsl"
#define FLOW_SOURCE(j) dense_[j]
#include "flow_refine_common.glsl"
#include "flow_upsample.glsl"

uniform ivec2 full_size;    // H, W of level 0
uniform int coarsest;       // the coarsest level (DIS's choice, flow.py's pyramid_levels)
uniform int last;           // the finest level run here (>= the finest level searched)
uniform int sweeps;
uniform int refine_iterations;
uniform int sor_iterations;

void sync() {
    memoryBarrierBuffer();
    barrier();
}

void main() {
    int lane = int(gl_LocalInvocationIndex);
    // sizes and offsets of the levels (pyramid_levels: level l + 1 is ceil(level l / 2) a side)
    ivec2 level_size = full_size;
    int level_offset = 0;
    ivec2 sizes[32];
    int offsets[32];
    for (int l = 0; l <= coarsest; ++l) {
        sizes[l] = level_size;
        offsets[l] = level_offset;
        level_offset += level_size.x * level_size.y;
        level_size = (level_size + 1) / 2;
    }
    for (int level = coarsest; level >= last; --level) {
        size = sizes[level];
        offset = offsets[level];
        int n = size.x * size.y;
        for (int i = lane; i < n; i += LOCAL_SIZE) {
            init_[i] = level == coarsest ? vec2(0.0) : upsample_at(i / size.y, i % size.y, sizes[level + 1], 2.0);
        }
        sync();
        int patches = patch_count(size.x) * patch_count(size.y);
        for (int sweep = 0; sweep < sweeps; ++sweep) {
            for (int i = lane; i < patches; i += LOCAL_SIZE) patch_[i] = search_patch(i, sweep > 0);
            sync();
            for (int i = lane; i < patches; i += LOCAL_SIZE) prev_[i] = patch_[i];
            sync();
        }
        for (int i = lane; i < n; i += LOCAL_SIZE) dense_[i] = densify_at(i / size.y, i % size.y);
        sync();
        if (refine_iterations > 0) {
            for (int i = lane; i < n; i += LOCAL_SIZE) refine_warp(i);
            sync();
            for (int i = lane; i < n; i += LOCAL_SIZE) refine_derivs(i);
            sync();
            for (int it = 0; it < refine_iterations; ++it) {
                for (int i = lane; i < n; i += LOCAL_SIZE) refine_system(i);
                sync();
                for (int s = 0; s < sor_iterations; ++s) {
                    for (int parity = 0; parity < 2; ++parity) {
                        for (int i = lane; i < n; i += LOCAL_SIZE) refine_sor(i, parity);
                        sync();
                    }
                }
            }
            for (int i = lane; i < n; i += LOCAL_SIZE) refine_apply(i);
            sync();
        }
    }
}
