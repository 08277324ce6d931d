// The variational refinement's buffers (OpenCV's VariationalRefinement, as DIS runs it on every level):
// the energy delta Psi(E_I) + gamma Psi(E_G) + alpha Psi(E_S) of the increment du of the level's flow u,
// Psi(s^2) = sqrt(s^2 + eps^2), colour and gradient constancy linearised at the second image warped by u and
// normalised by the squared gradient + zeta^2, smoothness on the forward differences of u + du. Derivatives
// are OpenCV's Sobel of size 1, I(x + 1) - I(x - 1) (twice the central difference, as DIS uses them),
// borders replicated. Solved by lagged fixed-point iterations of red-black SOR. One function per pass, of one
// pixel i of the level (passes flow_refine_* run one each; flow_coarse runs them all).
#include "flow_common.glsl"

#ifdef COARSE
#define RW coherent
#else
#define RW
#endif
layout(std430, binding = 6) RW buffer DenseBuf { vec2 dense_[]; };        // (H, W) flow u of the level
layout(std430, binding = 9) RW buffer IncrementBuf { vec2 inc_[]; };      // (H, W) increment du
layout(std430, binding = 10) RW buffer AverageBuf { vec2 avg_[]; };       // (H, W) (mean of I0 and warped I1, Iz)
// (H, W, 2): (Ix, Iy, Iz, Ixx), (Ixy, Iyy, Ixz, Iyz)
layout(std430, binding = 11) RW buffer DerivBuf { vec4 deriv_[]; };
// (H, W, 2): (A11, A12, A22, b1), (b2, ws, 0, 0)
layout(std430, binding = 12) RW buffer SystemBuf { vec4 system_[]; };

uniform float alpha;  // smoothness weight
uniform float delta;  // colour constancy weight
uniform float gamma;  // gradient constancy weight
uniform float omega;  // SOR relaxation factor

const float ZETA2 = 0.1 * 0.1;
const float EPS2 = 0.001 * 0.001;

int pixel(int y, int x) {
    return clamp(y, 0, size.x - 1) * size.y + clamp(x, 0, size.y - 1);
}

// pass 1 (flow_refine_warp): the second image warped by the level's flow u (bilinear, borders replicated),
// stored as (mean of it and the first image, its difference Iz from the first image); du starts at 0
void refine_warp(int i) {
    int y = i / size.y, x = i % size.y;
    float warped = second_bilinear(vec2(float(x), float(y)) + dense_[i]);
    float first = first_at(y, x);
    avg_[i] = vec2(0.5 * (first + warped), warped - first);
    inc_[i] = vec2(0.0);
}

float mean_at(int y, int x) { return avg_[pixel(y, x)].x; }
float ix_at(int y, int x) {
    y = clamp(y, 0, size.x - 1);
    x = clamp(x, 0, size.y - 1);
    return mean_at(y, x + 1) - mean_at(y, x - 1);
}
float iy_at(int y, int x) {
    y = clamp(y, 0, size.x - 1);
    x = clamp(x, 0, size.y - 1);
    return mean_at(y + 1, x) - mean_at(y - 1, x);
}

// pass 2 (flow_refine_derivs): the derivatives of the energy, Sobel size 1 with replicated borders: Ix, Iy of
// the mean image, Ixx, Ixy of Ix, Iyy of Iy, Ixz, Iyz of Iz
void refine_derivs(int i) {
    int y = i / size.y, x = i % size.y;
    float iz = avg_[i].y;
    deriv_[2 * i] = vec4(ix_at(y, x), iy_at(y, x), iz, ix_at(y, x + 1) - ix_at(y, x - 1));
    deriv_[2 * i + 1] = vec4(ix_at(y + 1, x) - ix_at(y - 1, x), iy_at(y + 1, x) - iy_at(y - 1, x),
                             avg_[pixel(y, x + 1)].y - avg_[pixel(y, x - 1)].y,
                             avg_[pixel(y + 1, x)].y - avg_[pixel(y - 1, x)].y);
}

// the data term's part of pixel i's linear system in (du, dv), the robust weights lagged at its du: (A11,
// A12, A22, b1) and b2 into b2
vec4 data_system(int i, vec2 du, out float b2) {
    vec4 d0 = deriv_[2 * i], d1 = deriv_[2 * i + 1];
    float ix = d0.x, iy = d0.y, iz = d0.z, ixx = d0.w, ixy = d1.x, iyy = d1.y, ixz = d1.z, iyz = d1.w;

    float norm = ix * ix + iy * iy + ZETA2;
    float residual = iz + ix * du.x + iy * du.y;
    float w = (0.5 * delta / sqrt(residual * residual / norm + EPS2)) / norm;
    float a11 = w * ix * ix + ZETA2, a12 = w * ix * iy, a22 = w * iy * iy + ZETA2;
    float b1 = -w * iz * ix;
    b2 = -w * iz * iy;

    float norm_x = ixx * ixx + ixy * ixy + ZETA2, norm_y = iyy * iyy + ixy * ixy + ZETA2;
    float rx = ixz + ixx * du.x + ixy * du.y, ry = iyz + ixy * du.x + iyy * du.y;
    w = 0.5 * gamma / sqrt(rx * rx / norm_x + ry * ry / norm_y + EPS2);
    a11 += w * (ixx * ixx / norm_x + ixy * ixy / norm_y);
    a12 += w * (ixx * ixy / norm_x + ixy * iyy / norm_y);
    a22 += w * (ixy * ixy / norm_x + iyy * iyy / norm_y);
    b1 -= w * (ixx * ixz / norm_x + ixy * iyz / norm_y);
    b2 -= w * (ixy * ixz / norm_x + iyy * iyz / norm_y);
    return vec4(a11, a12, a22, b1);
}

// the smoothness weight ws = alpha / 2 / sqrt(|grad(u + du)|^2 + eps^2) of pixel (y, x)'s right and lower
// edges, from u (dense_) and du (inc_)
float smooth_weight(int y, int x) {
    int i = y * size.y + x;
    vec2 here = dense_[i] + inc_[i];
    vec2 gx = dense_[pixel(y, x + 1)] + inc_[pixel(y, x + 1)] - here;
    vec2 gy = dense_[pixel(y + 1, x)] + inc_[pixel(y + 1, x)] - here;
    return 0.5 * alpha / sqrt(dot(gx, gx) + dot(gy, gy) + EPS2);
}

// pass 3 (flow_refine_system), once per fixed-point iteration: the data term's part of the linear system in
// (du, dv) (A11, A12, A22, b1, b2, with the robust weights lagged at the current du) and the smoothness weight
// ws of the pixel's right and lower edges
void refine_system(int i) {
    float b2;
    system_[2 * i] = data_system(i, inc_[i], b2);
    system_[2 * i + 1] = vec4(b2, smooth_weight(i / size.y, i % size.y), 0.0, 0.0);
}

// one SOR step of pixel (y, x) with system s0 = (A11, A12, A22, b1), b2, flow u and increment du, given its 4
// neighbours (right, left, down, up: that order) as u_j + du_j in totals[k] and the smoothness weights of the
// edges to them in weights[k], those outside the level left out (inside[k] false): du first, then dv with the
// new du
vec2 sor_step(vec4 s0, float b2, vec2 u, vec2 du, vec2 totals[4], float weights[4], bvec4 inside) {
    vec2 pull = vec2(0.0);
    float weight = 0.0;
    for (int k = 0; k < 4; ++k) {
        if (!inside[k]) continue;
        pull += weights[k] * (totals[k] - u);
        weight += weights[k];
    }
    du.x = (1.0 - omega) * du.x + omega * (s0.w + pull.x - s0.y * du.y) / (s0.x + weight);
    du.y = (1.0 - omega) * du.y + omega * (b2 + pull.y - s0.y * du.x) / (s0.z + weight);
    return du;
}

const ivec2 AROUND[4] = ivec2[4](ivec2(1, 0), ivec2(-1, 0), ivec2(0, 1), ivec2(0, -1));  // right, left, down, up

// pass 4 (flow_refine_sor), for the pixels of one colour of a checkerboard ((x + y) % 2 == parity): one SOR
// step of the linear system with the smoothness term (OpenCV's red-black SOR):
// du <- (1 - omega) du + omega (b1 + sum_j w_j (u_j + du_j - u) - A12 dv) / (A11 + sum_j w_j) over the
// 4 neighbours j inside the level, w_j the smoothness weight of the edge (that of its left / upper pixel)
void refine_sor(int i, int parity) {
    int y = i / size.y, x = i % size.y;
    if (((x + y) & 1) != parity) return;
    vec4 s0 = system_[2 * i], s1 = system_[2 * i + 1];
    vec2 totals[4];
    float weights[4];
    bvec4 inside;
    for (int k = 0; k < 4; ++k) {
        int nx = x + AROUND[k].x, ny = y + AROUND[k].y;
        inside[k] = nx >= 0 && ny >= 0 && nx < size.y && ny < size.x;
        int j = inside[k] ? ny * size.y + nx : i;
        totals[k] = dense_[j] + inc_[j];
        weights[k] = k % 2 == 0 ? s1.y : system_[2 * j + 1].y;
    }
    inc_[i] = sor_step(s0, s1.x, dense_[i], inc_[i], totals, weights, inside);
}

// pass 5 (flow_refine_apply): u <- u + du (a non-finite increment is dropped)
void refine_apply(int i) {
    vec2 du = inc_[i];
    if (!nonfinite_bits(du)) dense_[i] += du;
}
