// Hole fill pass 1, one workgroup per row: per hole pixel, the column of the farther (larger depth; ties:
// the left one) of its nearest known pixels to the left and right (-1 for known pixels and rows without a
// known pixel): engine.geometry.kernels.row_sources. rowinfo_[row] = 1 when the row has a known pixel.
// Each invocation walks its own run of ceil(W / LOCAL_SIZE) columns; one scan over the runs' summaries in
// shared memory per direction carries the nearest known pixel across runs (two scans a row, not two a chunk).
#include "fill_common.glsl"

void main() {
    int row = int(gl_WorkGroupID.x + gl_WorkGroupID.y * gl_NumWorkGroups.x);
    uint lid = gl_LocalInvocationIndex;
    int h = size.x, w = size.y;
    if (row >= h) return;  // uniform across the workgroup
    int base = row * w;
    int run = (w + LOCAL_SIZE - 1) / LOCAL_SIZE;
    int x0 = min(int(lid) * run, w), x1 = min(x0 + run, w);

    // to the left: the last known pixel of each run, scanned by max; the run before gives the carry in
    int last = -1;
    for (int x = x0; x < x1; ++x) {
        if (hole_[base + x] == 0u) last = x;
    }
    scan_[lid] = last;
    barrier();
    scan_max_forward(lid);
    int left = lid > 0u ? scan_[lid - 1u] : -1;
    bool any_known = scan_[LOCAL_SIZE - 1] >= 0;
    barrier();
    if (lid == 0u) rowinfo_[row] = any_known ? 1 : 0;
    for (int x = x0; x < x1; ++x) {  // hole pixels keep their left neighbour until the right walk
        if (hole_[base + x] == 0u) {
            left = x;
        } else {
            rowsrc_[base + x] = left;
        }
    }

    // to the right: the first known pixel of each run, scanned by min from the end
    int first = w;
    for (int x = x1 - 1; x >= x0; --x) {
        if (hole_[base + x] == 0u) first = x;
    }
    scan_[lid] = first;
    barrier();
    scan_min_backward(lid, w);
    int right = lid + 1u < uint(LOCAL_SIZE) ? scan_[lid + 1u] : w;
    for (int x = x1 - 1; x >= x0; --x) {
        if (hole_[base + x] == 0u) {
            right = x;
            rowsrc_[base + x] = -1;
            continue;
        }
        int l = rowsrc_[base + x];
        int r = right == w ? -1 : right;
        float depth_left = l >= 0 ? warped_[base + l].w : -INF;
        float depth_right = r >= 0 ? warped_[base + r].w : -INF;
        rowsrc_[base + x] = depth_right > depth_left ? r : l;
    }
}
