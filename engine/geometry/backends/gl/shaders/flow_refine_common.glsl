// The variational refinement's buffers (OpenCV's VariationalRefinement, as DIS runs it on every level):
// the energy delta Psi(E_I) + gamma Psi(E_G) + alpha Psi(E_S) of the increment du of the level's flow u,
// Psi(s^2) = sqrt(s^2 + eps^2), colour and gradient constancy linearised at the second image warped by u and
// normalised by the squared gradient + zeta^2, smoothness on the forward differences of u + du. Derivatives
// are OpenCV's Sobel of size 1, I(x + 1) - I(x - 1) (twice the central difference, as DIS uses them),
// borders replicated. Solved by lagged fixed-point iterations of red-black SOR.
#include "flow_common.glsl"

layout(std430, binding = 6) buffer DenseBuf { vec2 dense_[]; };        // (H, W) flow u of the level
layout(std430, binding = 9) buffer IncrementBuf { vec2 inc_[]; };      // (H, W) increment du
layout(std430, binding = 10) buffer AverageBuf { vec2 avg_[]; };       // (H, W) (mean of I0 and warped I1, Iz)
// (H, W, 2): (Ix, Iy, Iz, Ixx), (Ixy, Iyy, Ixz, Iyz)
layout(std430, binding = 11) buffer DerivBuf { vec4 deriv_[]; };
layout(std430, binding = 12) buffer SystemBuf { vec4 system_[]; };     // (H, W, 2) (A11, A12, A22, b1), (b2, ws, 0, 0)

uniform float alpha;  // smoothness weight
uniform float delta;  // colour constancy weight
uniform float gamma;  // gradient constancy weight

const float ZETA2 = 0.1 * 0.1;
const float EPS2 = 0.001 * 0.001;

int pixel(int y, int x) {
    return clamp(y, 0, size.x - 1) * size.y + clamp(x, 0, size.y - 1);
}
