// The forward splat's buffers, uniforms and per-point geometry (shared by the splat_* passes).
// Variants: FRAME (one-plane frame warp: colour (H, W, 3) and flow (H, W, FLOW_CHANNELS) interleaved,
// alpha = 1 everywhere, no index list) or, without it, an MPI: colour (3, Z, H, W), depth / alpha (Z, H, W),
// flow (3, Z, H, W), the points of a multi-plane MPI listed in index_.

layout(std430, binding = 0) readonly buffer ColorBuf { float color_[]; };
layout(std430, binding = 1) readonly buffer DepthBuf { float depth_[]; };
layout(std430, binding = 2) readonly buffer AlphaBuf { float alpha_[]; };
layout(std430, binding = 3) readonly buffer FlowBuf { float flow_[]; };
layout(std430, binding = 4) readonly buffer MidBuf { float mids_[]; };      // (Z - 1,) inverse-depth midpoints
layout(std430, binding = 5) buffer RangeBuf { uint range_[]; };             // ordered bits of (lo, hi)
layout(std430, binding = 6) buffer KeyBuf { uint key_[]; };                 // (Z, HP, WP) ordered bits of t_max
layout(std430, binding = 7) buffer AccBuf { uint acc_[]; };                 // (Z, HP, WP, 12) fixed-point sums
layout(std430, binding = 9) readonly buffer IndexBuf { uint index_[]; };    // flat indices of alpha != 0
// the binned splat's buffers (splat_bin_*, splat_gather)
layout(std430, binding = 20) buffer CountBuf { uint count_[]; };            // (Z, HP, WP) points a bin holds
layout(std430, binding = 21) buffer SlotBuf { uint slot_[]; };              // (points,) a point's place in its bin
layout(std430, binding = 22) buffer OffsetBuf { uint offset_[]; };          // (Z, HP, WP) start in its scan block
layout(std430, binding = 23) buffer BlockBuf { uint block_[]; };            // (blocks,) start of a scan block
layout(std430, binding = 24) buffer RecordBuf { uvec4 record_[]; };         // (points,) fx, fy, z, source index

uniform ivec3 src_size;     // Z, H, W
uniform ivec2 dst_size;     // HO, WO
uniform int has_flow;
uniform float flow_scale;   // the object flow is multiplied by this (FRAME; 1 for an MPI)
uniform int num_points;     // points to process: index_[0 .. num_points) when use_index, else all
uniform int use_index;
uniform float sharpness;
uniform float snap;
uniform float snap_scale;
uniform float min_log_weight;
uniform double coverage_threshold;

#include "reproject.glsl"

#ifndef FLOW_CHANNELS
#define FLOW_CHANNELS 3
#endif

const float INF = uintBitsToFloat(0x7f800000u);
// bins per block of the binned splat's scan (splat_bin_scan: 4 a invocation)
const uint SCAN_BLOCK = 4u * uint(LOCAL_SIZE);

// the first record of bin b (the binned splat, after splat_bin_scan and splat_bin_blocks)
uint bin_start(int b) {
    return offset_[b] + block_[uint(b) / SCAN_BLOCK];
}

// value as 64-bit fixed point (2^-32 units), split in float32 (exact: scaling by 2^32, then the high part is
// s rounded down to a multiple of 2^32): (low, high) words, floor(value * 2^32) in two's complement
uvec2 fixed_parts(float value) {
    float s = value * 4294967296.0;
    float high_f = floor(s * (1.0 / 4294967296.0));
    return uvec2(uint(s - high_f * 4294967296.0), uint(int(high_f)));
}

// order-preserving float <-> uint (0 is below every encoded value: "empty")
uint order_bits(float f) {
    uint u = floatBitsToUint(f);
    return (u & 0x80000000u) != 0u ? ~u : (u | 0x80000000u);
}
float order_float(uint u) {
    return uintBitsToFloat((u & 0x80000000u) != 0u ? (u & 0x7fffffffu) : ~u);
}

float log1p_(float z) {
    float u = 1.0 + z;
    return u == 1.0 ? z : log(u) * (z / (u - 1.0));
}

vec3 point_color(uint i) {
#ifdef FRAME
    return vec3(color_[3u * i], color_[3u * i + 1u], color_[3u * i + 2u]);
#else
    uint n = uint(src_size.x * src_size.y * src_size.z);
    return vec3(color_[i], color_[n + i], color_[2u * n + i]);
#endif
}

vec3 point_flow(uint i) {
#ifdef FRAME
    uint c = uint(FLOW_CHANNELS);
    vec3 f = vec3(flow_[c * i], flow_[c * i + 1u], FLOW_CHANNELS == 3 ? flow_[c * i + 2u] : 0.0);
    return flow_scale * f;
#else
    uint n = uint(src_size.x * src_size.y * src_size.z);
    return vec3(flow_[i], flow_[n + i], flow_[2u * n + i]);
#endif
}

struct Point {
    int base;      // top-left tap in the flat padded volume
    float fx;      // snapped bilinear fraction of the right tap
    float fy;      // ... of the bottom tap
    float a;       // alpha (0 for points that are dropped)
    float z;       // destination depth (+inf: sky)
};

// the reference's pass 1 (reprojection, bilinear taps, destination plane), float32 throughout
bool project_point(inout uint i, out Point p) {
    uint hw = uint(src_size.y * src_size.z);
    if (i >= uint(num_points)) return false;
#ifdef FRAME
    float alpha = 1.0;
#else
    if (use_index != 0) i = index_[i];
    float alpha = alpha_[i];
    if (alpha == 0.0) return false;
#endif
    uint pix = i % hw;
    float u = float(pix % uint(src_size.z)) + 0.5;
    float v = float(pix / uint(src_size.z)) + 0.5;
    float d = depth_[i];
    if (has_flow != 0) {
        vec3 f = point_flow(i);
        u = u + f.x;
        v = v + f.y;
        d = d + f.z;
    }
    float uo, vo, hz;
    if (!reproject_point(u, v, d, uo, vo, hz)) return false;
    float z = isinf(d) ? INF : hz;
    int ho = dst_size.x, wo = dst_size.y;
    precise float xc = clamp(uo - 0.5, -2.0, float(wo + 1));
    precise float yc = clamp(vo - 0.5, -2.0, float(ho + 1));
    float left = floor(xc);
    float top = floor(yc);
    precise float fx = clamp((xc - left - snap) * snap_scale, 0.0, 1.0);
    precise float fy = clamp((yc - top - snap) * snap_scale, 0.0, 1.0);
    int x0 = int(left) + 1;
    int y0 = int(top) + 1;
    if (x0 < 0 || x0 > wo || y0 < 0 || y0 > ho) return false;
    int plane = 0;
#ifndef FRAME
    float inv = 1.0 / z;
    for (int k = 0; k < src_size.x - 1; ++k) {
        plane += inv <= mids_[k] ? 1 : 0;
    }
#endif
    p.base = (plane * (ho + 2) + y0) * (wo + 2) + x0;
    p.fx = fx;
    p.fy = fy;
    p.a = alpha;
    p.z = z;
    return true;
}

// clipped soft z-buffer log-weight of a finite point (the reference's _soft_zbuffer_weight, in log)
float log_zbuffer(float z) {
    uint lo_bits = range_[0];
    float lz = log1p_(z);
    if (lo_bits != 0xffffffffu) lz -= order_float(lo_bits);
    float hi = max(order_float(range_[1]), 1e-30);
    return clamp(lz * (-sharpness / hi), min_log_weight, 0.0);
}

// log splat weight t = log(cover) + log_zbuf of a finite point's tap (the bin's largest is its key)
float log_splat_weight(float cover, float lw) {
    return log(abs(cover)) + lw;
}

// a finite point's splat weight relative to its bin's largest log weight t_max: cover * zbuf / exp(t_max)
float relative_weight(float cover, float lw, float t_max) {
    return sign(cover) * exp(log_splat_weight(cover, lw) - t_max);
}

void tap_geometry(Point p, int k, out int tap, out float cover) {
    float wx = (k & 1) != 0 ? p.fx : 1.0 - p.fx;
    float wy = (k & 2) != 0 ? p.fy : 1.0 - p.fy;
    int wp = dst_size.y + 2;
    tap = p.base + ((k & 1) != 0 ? 1 : 0) + ((k & 2) != 0 ? wp : 0);
    cover = wx * wy * p.a;
}
