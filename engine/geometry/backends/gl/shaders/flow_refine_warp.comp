// Flow refinement pass 1, per pixel of a level: the second image warped by the level's flow u (bilinear,
// borders replicated), stored as (mean of it and the first image, its difference Iz from the first image);
// the increment du starts at 0.
#include "flow_refine_common.glsl"

void main() {
    uint i = invocation();
    if (i >= uint(size.x * size.y)) return;
    int y = int(i) / size.y, x = int(i) % size.y;
    float warped = second_bilinear(vec2(float(x), float(y)) + dense_[i]);
    float first = first_at(y, x);
    avg_[i] = vec2(0.5 * (first + warped), warped - first);
    inc_[i] = vec2(0.0);
}
