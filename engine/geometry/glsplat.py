"""OpenGL compute-shader MPI forward splat: the fast path of ``engine.geometry.forward_warp_mpi``.

``GlSplatter.forward_warp_mpi`` has the signature, validation, semantics and return types of
``engine.geometry.forward_warp_mpi`` (the numpy function is its oracle, ``tests/geometry/test_glsplat.py``); it runs
on a headless moderngl context (EGL; Mesa llvmpipe is enough: OpenGL 4.5 compute shaders plus
``GL_ARB_gpu_shader_int64`` for arithmetic, no float or 64-bit atomics needed).

Design (four dispatches over the points: every pixel of a one-plane MPI, else the alpha != 0 ones listed
by ``np.flatnonzero``; each pass recomputes the reprojection of its points, cheaper than storing them):

1. ``range``: (min, max) of log(1 + z) over the kept finite points (the reference's ``_log_depth_range``),
   reduced per workgroup in shared memory, then one ``atomicMin`` / ``atomicMax`` per workgroup on the
   order-preserving uint bits of the floats.
2. ``key``: per destination bin (plane, padded pixel), the largest log splat weight
   ``t = log(cover) + log_zbuf`` of the finite points that land there with cover != 0 (``atomicMax``).
3. ``splat``: fixed-point sums of coverage, weight, weight * (r, g, b, z) where weight is relative to the
   bin's largest one, ``cover * zbuf / exp(t_max)`` in (0, 1]: the per-bin factor cancels in the
   normalisation, and no weight is tiny where it matters. Sums are 64-bit fixed point (2^-32 units) built
   from two 32-bit ``atomicAdd`` (low word, then the carry into the high word only when it is non-zero), so
   they are exact and order-independent. Sky points (+inf depth) are added (weight = cover) only to bins
   that no finite point reached: the reference gives them e^-300, i.e. they count only there.
4. ``resolve``: per output pixel, normalise its bin into (r, g, b, depth, alpha, coverage) float32 planes
   (the padding ring is cropped). Keys and sums are zeroed with ``Buffer.clear`` before each warp.

Deviations from the float64 reference: per-point arithmetic (reprojection, bilinear fractions, log weights)
is float32 as in the reference's first pass, weights are exponentiated in float32 (relative error ~1e-6),
and sums are exact 64-bit fixed point (absolute resolution 2^-32 of weight * value). A bin where finite
points landed ignores sky points exactly (the reference: up to ~e^-200 relatively). Calls on one instance
are serialised by a lock, but the EGL context stays current on the thread that created it: use an instance
(and ``shared_splatter()``) from that thread only (another thread gets "cannot create buffer").
"""
from __future__ import annotations

import threading
from typing import Optional

import numpy as np

from engine.core.checks import checked_array, checked_matrix, checked_out_size, checked_sharpness
from engine.geometry.camera import MAX_PIXEL_COORD, TINY_DEPTH, reprojection_matrix
from engine.geometry.mpi import Mpi, checked_mpi
from engine.geometry.splat import COVERAGE_THRESHOLD, DEFAULT_SHARPNESS, MIN_LOG_WEIGHT, SUBPIXEL_SNAP

_LOCAL = 256
#: 32-bit words of fixed-point accumulators per bin: (low, high) of coverage, weight, w r, w g, w b, w z.
_ACC_WORDS = 12

_COMMON = """
#version 450
#extension GL_ARB_gpu_shader_int64 : require
layout(local_size_x = %(local)d) in;

layout(std430, binding = 0) readonly buffer ColorBuf { float color_[]; };   // (3, Z, H, W)
layout(std430, binding = 1) readonly buffer DepthBuf { float depth_[]; };   // (Z, H, W)
layout(std430, binding = 2) readonly buffer AlphaBuf { float alpha_[]; };   // (Z, H, W)
layout(std430, binding = 3) readonly buffer FlowBuf { float flow_[]; };     // (3, Z, H, W)
layout(std430, binding = 4) readonly buffer MidBuf { float mids_[]; };      // (Z - 1,) inverse-depth midpoints
layout(std430, binding = 5) buffer RangeBuf { uint range_[]; };             // ordered bits of (lo, hi)
layout(std430, binding = 6) buffer KeyBuf { uint key_[]; };                 // (Z, HP, WP) ordered bits of t_max
layout(std430, binding = 7) buffer AccBuf { uint acc_[]; };                 // (Z, HP, WP, 12)
layout(std430, binding = 8) writeonly buffer OutBuf { float out_[]; };      // (6, Z, HO, WO)
layout(std430, binding = 9) readonly buffer IndexBuf { uint index_[]; };    // flat indices of alpha != 0

uniform ivec3 src_size;     // Z, H, W
uniform ivec2 dst_size;     // HO, WO
uniform vec4 row0;
uniform vec4 row1;
uniform vec4 row2;
uniform int has_flow;
uniform int num_points;     // points to process: index_[0 .. num_points) when use_index, else all
uniform int use_index;
uniform float sharpness;
uniform float snap;
uniform float snap_scale;
uniform float max_coord_inv;
uniform float tiny_depth;
uniform float min_log_weight;
uniform double coverage_threshold;

const float INF = uintBitsToFloat(0x7f800000u);

uint invocation() {
    return gl_GlobalInvocationID.x + gl_GlobalInvocationID.y * gl_NumWorkGroups.x * gl_WorkGroupSize.x;
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
    uint n = uint(src_size.x) * hw;
    if (i >= uint(num_points)) return false;
    if (use_index != 0) i = index_[i];
    float alpha = alpha_[i];
    if (alpha == 0.0) return false;
    uint pix = i %% hw;
    float u = float(pix %% uint(src_size.z)) + 0.5;
    float v = float(pix / uint(src_size.z)) + 0.5;
    float d = depth_[i];
    if (has_flow != 0) {
        u = u + flow_[i];
        v = v + flow_[n + i];
        d = d + flow_[2u * n + i];
    }
    bool sky = isinf(d);
    float s = sky ? 1.0 : d;
    float w = sky ? 0.0 : 1.0;
    precise float x = u * s;
    precise float y = v * s;
    precise float hu = row0.x * x + row0.y * y + row0.z * s + row0.w * w;
    precise float hv = row1.x * x + row1.y * y + row1.z * s + row1.w * w;
    precise float hz = row2.x * x + row2.y * y + row2.z * s + row2.w * w;
    precise float bound = (abs(hu) + abs(hv)) * max_coord_inv + tiny_depth;
    bool valid = hz > bound;
    if (!valid) return false;
    precise float uo = hu / hz;
    precise float vo = hv / hz;
    float z = sky ? INF : hz;
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
    float inv = 1.0 / z;
    int plane = 0;
    for (int k = 0; k < src_size.x - 1; ++k) {
        plane += inv <= mids_[k] ? 1 : 0;
    }
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

void tap_geometry(Point p, int k, out int tap, out float cover) {
    float wx = (k & 1) != 0 ? p.fx : 1.0 - p.fx;
    float wy = (k & 2) != 0 ? p.fy : 1.0 - p.fy;
    int wp = dst_size.y + 2;
    tap = p.base + ((k & 1) != 0 ? 1 : 0) + ((k & 2) != 0 ? wp : 0);
    cover = wx * wy * p.a;
}
"""

_RANGE = """
shared uint group_lo;
shared uint group_hi;
void main() {
    if (gl_LocalInvocationIndex == 0u) {
        group_lo = 0xffffffffu;
        group_hi = 0u;
    }
    barrier();
    Point p;
    uint i = invocation();
    if (project_point(i, p) && p.a > 0.0 && !isinf(p.z)) {
        uint bits = order_bits(log1p_(p.z));
        atomicMin(group_lo, bits);
        atomicMax(group_hi, bits);
    }
    barrier();
    if (gl_LocalInvocationIndex == 0u && group_hi != 0u) {
        atomicMin(range_[0], group_lo);
        atomicMax(range_[1], group_hi);
    }
}
"""

_KEY = """
void main() {
    Point p;
    uint i = invocation();
    if (!project_point(i, p) || isinf(p.z)) return;
    float lw = log_zbuffer(p.z);
    for (int k = 0; k < 4; ++k) {
        int tap;
        float cover;
        tap_geometry(p, k, tap, cover);
        if (cover != 0.0) atomicMax(key_[tap], order_bits(log(abs(cover)) + lw));
    }
}
"""

_SPLAT = """
void add64(int word, float value) {
    // 64-bit fixed point (2^-32 units) added with two 32-bit atomics; exact and order-independent.
    // Split in float32 (exact: scaling by 2^32, then the high part is s rounded down to a multiple of 2^32)
    float s = value * 4294967296.0;
    float high_f = floor(s * (1.0 / 4294967296.0));
    uvec2 parts = uvec2(uint(s - high_f * 4294967296.0), uint(int(high_f)));
    uint old = atomicAdd(acc_[word], parts.x);
    uint high = parts.y + (old + parts.x < old ? 1u : 0u);
    if (high != 0u) atomicAdd(acc_[word + 1], high);
}

void main() {
    uint i = invocation();
    Point p;
    if (!project_point(i, p)) return;
    uint n = uint(src_size.x * src_size.y * src_size.z);
    vec3 rgb = vec3(color_[i], color_[n + i], color_[2u * n + i]);
    bool sky = isinf(p.z);
    float lw = sky ? 0.0 : log_zbuffer(p.z);
    for (int k = 0; k < 4; ++k) {
        int tap;
        float cover;
        tap_geometry(p, k, tap, cover);
        if (cover == 0.0) continue;
        int word = tap * 12;
        add64(word, cover);
        uint key = key_[tap];
        float weight;
        if (sky) {
            if (key != 0u) continue;  // a finite point landed here: sky counts for nothing
            weight = cover;
        } else {
            weight = sign(cover) * exp(log(abs(cover)) + lw - order_float(key));
        }
        add64(word + 2, weight);
        add64(word + 4, weight * rgb.r);
        add64(word + 6, weight * rgb.g);
        add64(word + 8, weight * rgb.b);
        if (!sky) add64(word + 10, weight * p.z);
    }
}
"""

_RESOLVE = """
double read64(int word) {
    return double(int64_t(packUint2x32(uvec2(acc_[word], acc_[word + 1])))) * (1.0LF / 4294967296.0LF);
}

void main() {
    uint i = invocation();
    int ho = dst_size.x, wo = dst_size.y;
    int m = src_size.x * ho * wo;
    if (i >= uint(m)) return;
    int o = int(i);
    int x = o %% wo, y = (o / wo) %% ho, plane = o / (wo * ho);
    int bin = (plane * (ho + 2) + y + 1) * (wo + 2) + x + 1;
    int word = bin * 12;
    vec4 rgbd = vec4(0.0);
    float covered = 0.0, coverage = 0.0;
    if (acc_[word] != 0u || acc_[word + 1] != 0u) {
        double cov = read64(word);
        double wsum = read64(word + 2);
        coverage = float(cov);
        if (cov > coverage_threshold) {
            covered = 1.0;
            double inv_w = wsum > 0.0LF ? 1.0LF / wsum : 0.0LF;
            rgbd = vec4(float(read64(word + 4) * inv_w), float(read64(word + 6) * inv_w),
                        float(read64(word + 8) * inv_w), float(read64(word + 10) * inv_w));
            if (key_[bin] == 0u) rgbd.w = INF;  // only sky landed here
        }
    }
    out_[o] = rgbd.x;
    out_[m + o] = rgbd.y;
    out_[2 * m + o] = rgbd.z;
    out_[3 * m + o] = rgbd.w;
    out_[4 * m + o] = covered;
    out_[5 * m + o] = coverage;
}
"""


def _dispatch(program, count: int) -> None:
    groups = max(1, -(-count // _LOCAL))
    gx = min(groups, 65535)
    program.run(gx, -(-groups // gx), 1)


class GlSplatter:
    """One headless GL context, the compiled passes and grow-only GPU buffers of the MPI forward splat.

    >>> splatter = GlSplatter()                     # doctest: +SKIP
    >>> warped, coverage = splatter.forward_warp_mpi(mpi, K, T_src, K, T_dst)   # doctest: +SKIP
    """

    def __init__(self) -> None:
        import moderngl

        self.ctx = moderngl.create_standalone_context(backend="egl")
        self._lock = threading.Lock()
        common = _COMMON % {"local": _LOCAL}
        with self.ctx:
            self._programs = {name: self.ctx.compute_shader(common + (body.replace("%%", "%")))
                              for name, body in (("range", _RANGE), ("key", _KEY), ("splat", _SPLAT),
                                                 ("resolve", _RESOLVE))}
        self._buffers: dict = {}

    def _buffer(self, binding: int, nbytes: int):
        """Grow-only buffer bound to ``binding`` (contents undefined)."""
        nbytes = max(int(nbytes), 16)
        buf = self._buffers.get(binding)
        if buf is None or buf.size < nbytes:
            if buf is not None:
                buf.release()
            buf = self._buffers[binding] = self.ctx.buffer(reserve=nbytes)
        buf.bind_to_storage_buffer(binding)
        return buf

    def _upload(self, binding: int, array: np.ndarray) -> None:
        array = np.ascontiguousarray(array, dtype=np.float32)
        self._buffer(binding, array.nbytes).write(array)

    def _set_uniforms(self, values: dict) -> None:
        for program in self._programs.values():
            for name, value in values.items():
                try:
                    program[name].value = value
                except KeyError:  # optimised out of this pass
                    pass

    def forward_warp_mpi(self, mpi: Mpi, K_src: np.ndarray, T_src: np.ndarray, K_dst: np.ndarray,
                         T_dst: np.ndarray, object_flow: Optional[np.ndarray] = None, *,
                         out_size: Optional[tuple[int, int]] = None,
                         sharpness: float = DEFAULT_SHARPNESS) -> tuple[Mpi, np.ndarray]:
        """``engine.geometry.forward_warp_mpi`` on the GL context: same arguments, checks and results.

        Returns ``(warped Mpi, coverage (Z, HO, WO))``, float32 numpy arrays (the warped colour, depth and
        alpha are views of one freshly allocated array).
        """
        sizes: dict = {}
        mpi = checked_mpi(mpi, sizes)
        if object_flow is not None:
            object_flow = checked_array(object_flow, "object_flow", (3, "Z", "H", "W"), sizes)
        ho, wo = checked_out_size(out_size, (sizes["H"], sizes["W"]))
        matrix = reprojection_matrix(checked_matrix(K_src, "K_src", 3), checked_matrix(T_src, "T_src", 4),
                                      checked_matrix(K_dst, "K_dst", 3), checked_matrix(T_dst, "T_dst", 4))
        sharp = checked_sharpness(sharpness)
        with self._lock, self.ctx:  # make this context current (another module's GL context may be)
            return self._warp(mpi, matrix, object_flow, ho, wo, sharp)

    def _warp(self, mpi: Mpi, matrix: np.ndarray, object_flow, ho: int, wo: int, sharpness: float):
        color, depth, alpha, planes = mpi
        num_z, h, w = alpha.shape
        n = num_z * h * w
        bins = num_z * (ho + 2) * (wo + 2)
        inv_planes = np.float32(1.0) / planes
        mids = (inv_planes[:-1] + inv_planes[1:]) * np.float32(0.5)
        rows = matrix.astype(np.float32)
        self._set_uniforms({
            "src_size": (num_z, h, w), "dst_size": (ho, wo),
            "row0": tuple(float(c) for c in rows[0]), "row1": tuple(float(c) for c in rows[1]),
            "row2": tuple(float(c) for c in rows[2]), "has_flow": int(object_flow is not None),
            "sharpness": float(np.float32(sharpness)), "snap": float(np.float32(SUBPIXEL_SNAP)),
            "snap_scale": float(np.float32(1.0 / (1.0 - 2.0 * SUBPIXEL_SNAP))),
            "max_coord_inv": float(np.float32(1.0 / MAX_PIXEL_COORD)), "tiny_depth": float(np.float32(TINY_DEPTH)),
            "min_log_weight": float(MIN_LOG_WEIGHT), "coverage_threshold": float(COVERAGE_THRESHOLD),
        })
        self._upload(0, color)
        self._upload(1, depth)
        self._upload(2, alpha)
        if object_flow is not None:
            self._upload(3, object_flow)
        else:
            self._buffer(3, 16)
        self._upload(4, mids)
        # the points: every pixel of a one-plane MPI, else the alpha != 0 ones (as the reference)
        index = None if num_z == 1 else np.flatnonzero(alpha).astype(np.uint32)
        count = n if index is None else index.size
        if index is not None:
            self._buffer(9, index.nbytes).write(index)
        else:
            self._buffer(9, 16)
        self._set_uniforms({"num_points": count, "use_index": int(index is not None)})
        self._buffer(5, 8).write(np.array([0xFFFFFFFF, 0], dtype=np.uint32))
        self._buffer(6, 4 * bins).clear(size=4 * bins)
        self._buffer(7, 4 * _ACC_WORDS * bins).clear(size=4 * _ACC_WORDS * bins)
        out = np.empty((6, num_z, ho, wo), dtype=np.float32)
        out_buf = self._buffer(8, out.nbytes)
        for name in ("range", "key", "splat"):
            _dispatch(self._programs[name], count)
            self.ctx.memory_barrier()
        _dispatch(self._programs["resolve"], out[0].size)
        self.ctx.memory_barrier()
        out_buf.read_into(out, size=out.nbytes)
        warped = Mpi(out[0:3], out[3], out[4], planes)
        return warped, out[5]

    def release(self) -> None:
        """Free the GL buffers, programs and context."""
        with self.ctx:
            for buf in self._buffers.values():
                buf.release()
            self._buffers.clear()
            for program in self._programs.values():
                program.release()
        self.ctx.release()


_SHARED: Optional[GlSplatter] = None
_AVAILABLE: Optional[bool] = None
_SHARED_LOCK = threading.Lock()


def shared_splatter() -> GlSplatter:
    """The process-wide ``GlSplatter``, created on first use (raises if no EGL compute context can be made)."""
    global _SHARED
    with _SHARED_LOCK:
        if _SHARED is None:
            _SHARED = GlSplatter()
        return _SHARED


def available() -> bool:
    """True when a headless EGL context with the compute shaders of ``GlSplatter`` can be created (cached)."""
    global _AVAILABLE
    if _AVAILABLE is None:
        try:
            shared_splatter()
            _AVAILABLE = True
        except Exception:  # no moderngl, no EGL, no GL 4.5 / int64: the numpy path is used instead
            _AVAILABLE = False
    return _AVAILABLE
