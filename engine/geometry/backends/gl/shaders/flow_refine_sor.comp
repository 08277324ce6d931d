// Flow refinement pass 4, per pixel of one colour of a checkerboard ((x + y) % 2 == parity): one SOR step of
// the linear system with the smoothness term, du first, then dv with the new du (OpenCV's red-black SOR):
// du <- (1 - omega) du + omega (b1 + sum_j w_j (u_j + du_j - u) - A12 dv) / (A11 + sum_j w_j) over the 4
// neighbours j inside the level, w_j the smoothness weight of the edge (that of its left / upper pixel).
#include "flow_refine_common.glsl"

uniform int parity;
uniform float omega;

void main() {
    uint i = invocation();
    if (i >= uint(size.x * size.y)) return;
    int y = int(i) / size.y, x = int(i) % size.y;
    if (((x + y) & 1) != parity) return;
    vec4 s0 = system_[2u * i], s1 = system_[2u * i + 1u];
    vec2 u = dense_[i];
    vec2 pull = vec2(0.0);
    float weight = 0.0;
    ivec2 around[4] = ivec2[4](ivec2(1, 0), ivec2(-1, 0), ivec2(0, 1), ivec2(0, -1));
    for (int k = 0; k < 4; ++k) {
        int nx = x + around[k].x, ny = y + around[k].y;
        if (nx < 0 || ny < 0 || nx >= size.y || ny >= size.x) continue;
        int j = ny * size.y + nx;
        float w = k % 2 == 0 ? s1.y : system_[2 * j + 1].y;
        pull += w * (dense_[j] + inc_[j] - u);
        weight += w;
    }
    vec2 du = inc_[i];
    du.x = (1.0 - omega) * du.x + omega * (s0.w + pull.x - s0.y * du.y) / (s0.x + weight);
    du.y = (1.0 - omega) * du.y + omega * (s1.x + pull.y - s0.y * du.x) / (s0.z + weight);
    inc_[i] = du;
}
