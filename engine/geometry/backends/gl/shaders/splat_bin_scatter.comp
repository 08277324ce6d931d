// Binned splat pass 4: per kept point, its record (fx, fy, z, source index) at its place in the bin of its
// top-left tap: the records of bin b are record_[bin_start(b) .. bin_start(b + 1)), in no particular order.
#include "splat_common.glsl"

void main() {
    Point p;
    uint t = invocation();
    uint i = t;
    if (!project_point(i, p)) return;
    record_[bin_start(p.base) + slot_[t]] = uvec4(floatBitsToUint(p.fx), floatBitsToUint(p.fy),
                                                  floatBitsToUint(p.z), i);
}
