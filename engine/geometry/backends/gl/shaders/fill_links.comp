// Hole fill pass 2, one workgroup: per row, the nearest rows above and below (-1: none) that hold a known
// pixel; rows without one are filled along columns from those (engine.geometry.holefill.fill_sources).
#include "fill_common.glsl"

void main() {
    uint lid = gl_LocalInvocationIndex;
    int h = size.x;
    int carry = -1;
    for (int start = 0; start < h; start += LOCAL_SIZE) {  // above (exclusive: a row without one is not known)
        int y = start + int(lid);
        scan_[lid] = (y < h && rowinfo_[y] != 0) ? y : -1;
        barrier();
        scan_max_forward(lid);
        if (y < h) links_[2 * y] = max(carry, scan_[lid]);
        carry = max(carry, scan_[LOCAL_SIZE - 1]);
        barrier();
    }
    int after = h;
    for (int start = ((h - 1) / LOCAL_SIZE) * LOCAL_SIZE; start >= 0; start -= LOCAL_SIZE) {  // below
        int y = start + int(lid);
        scan_[lid] = (y < h && rowinfo_[y] != 0) ? y : h;
        barrier();
        scan_min_backward(lid, h);
        int below = min(after, scan_[lid]);
        after = min(after, scan_[0]);
        barrier();
        if (y < h) links_[2 * y + 1] = below == h ? -1 : below;
    }
}
