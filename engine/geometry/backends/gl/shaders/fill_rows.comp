// Hole fill pass 1, one workgroup per row: per hole pixel, the column of the farther (larger depth; ties:
// the left one) of its nearest known pixels to the left and right (-1 for known pixels and rows without a
// known pixel): engine.geometry.kernels.row_sources. rowinfo_[row] = 1 when the row has a known pixel.
#include "fill_common.glsl"

void main() {
    int row = int(gl_WorkGroupID.x + gl_WorkGroupID.y * gl_NumWorkGroups.x);
    uint lid = gl_LocalInvocationIndex;
    int h = size.x, w = size.y;
    if (row >= h) return;  // uniform across the workgroup
    int base = row * w;
    int carry = -1;
    for (int start = 0; start < w; start += LOCAL_SIZE) {  // nearest known to the left (inclusive)
        int x = start + int(lid);
        scan_[lid] = (x < w && hole_[base + x] == 0u) ? x : -1;
        barrier();
        scan_max_forward(lid);
        if (x < w) rowsrc_[base + x] = max(carry, scan_[lid]);
        carry = max(carry, scan_[LOCAL_SIZE - 1]);
        barrier();
    }
    if (lid == 0u) rowinfo_[row] = carry >= 0 ? 1 : 0;
    int after = w;
    for (int start = ((w - 1) / LOCAL_SIZE) * LOCAL_SIZE; start >= 0; start -= LOCAL_SIZE) {  // to the right
        int x = start + int(lid);
        bool hole = x < w && hole_[base + x] != 0u;
        scan_[lid] = (x < w && !hole) ? x : w;
        barrier();
        scan_min_backward(lid, w);
        int right = min(after, scan_[lid]);
        after = min(after, scan_[0]);
        barrier();
        if (x < w && !hole) rowsrc_[base + x] = -1;
        if (hole) {
            int left = rowsrc_[base + x];
            if (right == w) right = -1;
            float depth_left = left >= 0 ? warped_[base + left].w : -INF;
            float depth_right = right >= 0 ? warped_[base + right].w : -INF;
            rowsrc_[base + x] = depth_right > depth_left ? right : left;
        }
    }
}
