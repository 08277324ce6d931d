// Binned splat pass 3 (one workgroup): exclusive prefix sum of the scan blocks' totals in block_, in place;
// each invocation takes a run of consecutive blocks.
#include "splat_common.glsl"

uniform uint num_blocks;

shared uint partial[LOCAL_SIZE];
void main() {
    uint lane = gl_LocalInvocationIndex;
    uint run = (num_blocks + uint(LOCAL_SIZE) - 1u) / uint(LOCAL_SIZE);
    uint first = lane * run;
    uint last = min(first + run, num_blocks);
    uint total = 0u;
    for (uint b = first; b < last; ++b) total += block_[b];
    partial[lane] = total;
    barrier();
    for (uint step = 1u; step < uint(LOCAL_SIZE); step <<= 1) {
        uint add = lane >= step ? partial[lane - step] : 0u;
        barrier();
        partial[lane] += add;
        barrier();
    }
    uint start = partial[lane] - total;
    for (uint b = first; b < last; ++b) {
        uint count = block_[b];
        block_[b] = start;
        start += count;
    }
}
