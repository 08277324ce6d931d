// Binned splat pass 2: exclusive prefix sum of count_ within blocks of SCAN_BLOCK bins (one workgroup a
// block, 4 bins an invocation) into offset_, each block's total into block_; count_ is left zeroed for the
// next splat (so no pass clears it).
#include "splat_common.glsl"

uniform uint num_bins;
uniform uint num_blocks;

shared uint partial[LOCAL_SIZE];
void main() {
    uint block = gl_WorkGroupID.x + gl_WorkGroupID.y * gl_NumWorkGroups.x;
    if (block >= num_blocks) return;  // the spare groups of a dispatch spread over y (uniform in the group)
    uint lane = gl_LocalInvocationIndex;
    uint first = block * SCAN_BLOCK + 4u * lane;
    uvec4 c = uvec4(0u);
    for (uint k = 0u; k < 4u; ++k) {
        if (first + k < num_bins) {
            c[k] = count_[first + k];
            count_[first + k] = 0u;
        }
    }
    uint total = c.x + c.y + c.z + c.w;
    partial[lane] = total;
    barrier();
    // inclusive scan of the invocations' totals (Hillis-Steele)
    for (uint step = 1u; step < uint(LOCAL_SIZE); step <<= 1) {
        uint add = lane >= step ? partial[lane - step] : 0u;
        barrier();
        partial[lane] += add;
        barrier();
    }
    uint start = partial[lane] - total;
    uvec4 starts = uvec4(start, start + c.x, start + c.x + c.y, start + c.x + c.y + c.z);
    for (uint k = 0u; k < 4u; ++k) {
        if (first + k < num_bins) offset_[first + k] = starts[k];
    }
    if (lane == uint(LOCAL_SIZE) - 1u) block_[block] = partial[lane];
}
