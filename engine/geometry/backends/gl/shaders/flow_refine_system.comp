// Flow refinement pass 3, per pixel of a level, once per fixed-point iteration: the data term's part of the
// linear system in (du, dv) (A11, A12, A22, b1, b2, with the robust weights lagged at the current du) and the
// smoothness weight ws = alpha / 2 / sqrt(|grad(u + du)|^2 + eps^2) of the pixel's right and lower edges.
#include "flow_refine_common.glsl"

void main() {
    uint i = invocation();
    if (i >= uint(size.x * size.y)) return;
    int y = int(i) / size.y, x = int(i) % size.y;
    vec4 d0 = deriv_[2u * i], d1 = deriv_[2u * i + 1u];
    float ix = d0.x, iy = d0.y, iz = d0.z, ixx = d0.w, ixy = d1.x, iyy = d1.y, ixz = d1.z, iyz = d1.w;
    vec2 du = inc_[i];

    float norm = ix * ix + iy * iy + ZETA2;
    float residual = iz + ix * du.x + iy * du.y;
    float w = (0.5 * delta / sqrt(residual * residual / norm + EPS2)) / norm;
    float a11 = w * ix * ix + ZETA2, a12 = w * ix * iy, a22 = w * iy * iy + ZETA2;
    float b1 = -w * iz * ix, b2 = -w * iz * iy;

    float norm_x = ixx * ixx + ixy * ixy + ZETA2, norm_y = iyy * iyy + ixy * ixy + ZETA2;
    float rx = ixz + ixx * du.x + ixy * du.y, ry = iyz + ixy * du.x + iyy * du.y;
    w = 0.5 * gamma / sqrt(rx * rx / norm_x + ry * ry / norm_y + EPS2);
    a11 += w * (ixx * ixx / norm_x + ixy * ixy / norm_y);
    a12 += w * (ixx * ixy / norm_x + ixy * iyy / norm_y);
    a22 += w * (ixy * ixy / norm_x + iyy * iyy / norm_y);
    b1 -= w * (ixx * ixz / norm_x + ixy * iyz / norm_y);
    b2 -= w * (ixy * ixz / norm_x + iyy * iyz / norm_y);

    vec2 here = dense_[i] + du;
    vec2 gx = dense_[pixel(y, x + 1)] + inc_[pixel(y, x + 1)] - here;
    vec2 gy = dense_[pixel(y + 1, x)] + inc_[pixel(y + 1, x)] - here;
    float ws = 0.5 * alpha / sqrt(dot(gx, gx) + dot(gy, gy) + EPS2);
    system_[2u * i] = vec4(a11, a12, a22, b1);
    system_[2u * i + 1u] = vec4(b2, ws, 0.0, 0.0);
}
