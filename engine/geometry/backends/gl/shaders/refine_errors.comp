// Refinement pass 2 (decomp's refinement check), per pixel of a box of frame n (``size`` its (h, w), ``origin``
// its corner): the pixel's plane (engine.geometry.plane_index: the plane nearest in inverse depth, from frame
// n's depth and the bounds between planes), the network's residual flow of that plane upsampled as
// engine.geometry.kernels.upsample_planes does it (OpenCV's bilinear resize taps, alpha-normalised, (du, dv)
// times the block factor), added to the initial flow, and the photometric errors of both flows
// (engine.predict.dis.warp_error before its window mean; remap_common.glsl).

layout(std430, binding = 20) readonly buffer LumaNBuf { float luma_n_[]; };    // (H, W) 8-bit levels, frame n
layout(std430, binding = 21) readonly buffer TargetBuf { float target_[]; };   // (H, W) camera-compensated n-k
layout(std430, binding = 30) readonly buffer InitBuf { vec2 init_[]; };        // (H, W) initial u(n -> n-k)
layout(std430, binding = 23) writeonly buffer RefinedErrBuf { float refined_err_[]; };  // (h, w)
layout(std430, binding = 24) writeonly buffer InitErrBuf { float init_err_[]; };        // (h, w)
layout(std430, binding = 26) writeonly buffer RefinedBuf { vec2 refined_[]; };          // (h, w)
// (Z, h_low, w_low) alpha-weighted (du, dv, dz) and alpha of the network's residual, spread into empty
// neighbours (engine.predict.decomp.upsample.spread_plane)
layout(std430, binding = 27) readonly buffer PackedBuf { vec4 packed_[]; };
layout(std430, binding = 1) readonly buffer DepthBuf { float depth_[]; };   // (H, W) frame n, +inf sky
layout(std430, binding = 28) readonly buffer BoundBuf { float bounds_[]; };  // Z - 1 (engine.geometry.plane_bounds)
struct Tap { int first; int second; float weight; float unused; };
layout(std430, binding = 29) readonly buffer TapBuf { Tap taps_[]; };    // h row taps, then w column taps

#include "trust_common.glsl"
uniform ivec2 frame;     // H, W of frame n
uniform ivec2 origin;    // (y0, x0) of the box
uniform ivec2 low_size;  // (h_low, w_low) of the network's box
uniform float factor;    // the block factor: (du, dv) scale

#include "remap_common.glsl"

uniform int num_bounds;  // Z - 1

int plane_of(float d) {  // float32's 1 / d rounded as numpy rounds it; sky (+inf) -> 0 -> the farthest plane
    float inv = d > 0.0 ? float(1.0LF / double(d)) : uintBitsToFloat(0x7f800000u);
    int z = 0;
    for (int j = 0; j < num_bounds; ++j) z += inv <= bounds_[j] ? 1 : 0;
    return z;
}

vec4 packed_at(int z, int y, int x) { return packed_[(z * low_size.x + y) * low_size.y + x]; }

void main() {
    uint i = invocation();
    int h = size.x, w = size.y;
    if (i >= uint(h * w)) return;
    int y = int(i) / w, x = int(i) % w;
    int gx = origin.y + x, gy = origin.x + y;
    uint g = uint(gy * frame.y + gx);
    int z = plane_of(depth_[g]);
    Tap ty = taps_[y], tx = taps_[h + x];
    float u = tx.weight, v = ty.weight;
    precise vec4 s = (packed_at(z, ty.first, tx.first) * (1.0 - u) + packed_at(z, ty.first, tx.second) * u) * (1.0 - v)
        + (packed_at(z, ty.second, tx.first) * (1.0 - u) + packed_at(z, ty.second, tx.second) * u) * v;
    precise vec2 residual = vec2(0.0);
    if (s.w > 1e-6) {  // the quotient rounded as numpy rounds it (GLSL's float division may be 2.5 ulp off)
        residual = vec2(float(double(s.x) / double(s.w)), float(double(s.y) / double(s.w))) * factor;
    }
    vec2 init = init_[g];
    precise vec2 refined = residual + init;
    refined_[i] = refined;
    float luma = luma_n_[g];
    refined_err_[i] = remap_error(luma, gx, gy, refined, frame);
    init_err_[i] = remap_error(luma, gx, gy, init, frame);
}
