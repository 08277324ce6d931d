// Binned splat pass 1: per point, its place in the bin of its top-left tap (slot_ = atomicAdd on count_),
// and the (min, max) of log(1 + z) over the kept finite points as splat_range (reduced per workgroup in
// shared memory, then one atomicMin / atomicMax per workgroup on the order-preserving bits).
#include "splat_common.glsl"

shared uint group_lo;
shared uint group_hi;
void main() {
    if (gl_LocalInvocationIndex == 0u) {
        group_lo = 0xffffffffu;
        group_hi = 0u;
    }
    barrier();
    Point p;
    uint t = invocation();
    uint i = t;
    if (project_point(i, p)) {
        slot_[t] = atomicAdd(count_[p.base], 1u);
        if (p.a > 0.0 && !isinf(p.z)) {
            uint bits = order_bits(log1p_(p.z));
            atomicMin(group_lo, bits);
            atomicMax(group_hi, bits);
        }
    }
    barrier();
    if (gl_LocalInvocationIndex == 0u && group_hi != 0u) {
        atomicMin(range_[0], group_lo);
        atomicMax(range_[1], group_hi);
    }
}
