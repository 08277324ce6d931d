"""The forward splat on the GPU (shaders ``splat_*.comp``): an MPI to another camera, as
``engine.geometry.forward_warp_mpi`` (its oracle, ``tests/geometry/test_gl_splat.py``).

Four dispatches over the points (every pixel of a frame or one-plane MPI, else the alpha != 0 ones listed by
``np.flatnonzero``); each recomputes the reprojection of its points, cheaper than storing them:

1. ``splat_range``: (min, max) of log(1 + z) over the kept finite points, reduced per workgroup in shared
   memory, then one ``atomicMin`` / ``atomicMax`` per workgroup on the order-preserving bits of the floats.
2. ``splat_key``: per destination bin (plane, padded pixel), the largest log splat weight
   ``t = log(cover) + log_zbuf`` of the finite points that land there with cover != 0 (``atomicMax``).
3. ``splat_accumulate``: fixed-point sums of coverage, weight, weight * (r, g, b, z), the weight relative to
   the bin's largest, ``cover * zbuf / exp(t_max)`` in (0, 1]: the per-bin factor cancels in the
   normalisation. Sums are 64-bit fixed point (2^-32 units) from two 32-bit ``atomicAdd`` (the carry into the
   high word only when non-zero): exact and order-independent. Sky points (+inf) count only in bins no finite
   point reached (the reference gives them e^-300).
4. ``splat_resolve``: per output pixel, normalise its bin (the padding ring is cropped); the ``FRAME`` variant
   writes the one-plane composite and the holes for the hole fill that follows on the GPU.

Deviations from the float64 reference: per-point arithmetic is float32 as in the reference's first pass,
weights are exponentiated in float32 (relative error ~1e-6), sums are exact 64-bit fixed point (absolute
resolution 2^-32 of weight * value). Needs OpenGL 4.5 compute with ``GL_ARB_gpu_shader_int64`` (Mesa llvmpipe
has both; no float or 64-bit atomics).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from engine.core.checks import checked_array, checked_matrix, checked_out_size, checked_sharpness
from engine.geometry.backends.gl.context import GlContext, shared_context
from engine.geometry.camera import MAX_PIXEL_COORD, TINY_DEPTH, reprojection_matrix
from engine.geometry.mpi import Mpi, checked_mpi
from engine.geometry.splat import COVERAGE_THRESHOLD, DEFAULT_SHARPNESS, MIN_LOG_WEIGHT, SUBPIXEL_SNAP

__all__ = ["ACC_WORDS", "SPLAT_PASSES", "reprojection_uniforms", "splat_uniforms", "run_splat", "GlSplatter"]

#: 32-bit words of fixed-point accumulators per bin: (low, high) of coverage, weight, w r, w g, w b, w z.
ACC_WORDS = 12
#: The splat's dispatches over the points, in order (then ``splat_resolve`` over the output pixels).
SPLAT_PASSES = ("splat_range", "splat_key", "splat_accumulate")


def reprojection_uniforms(matrix: np.ndarray) -> dict:
    """The uniforms of ``shaders/reproject.glsl``: the float32 rows of the 3x4 reprojection ``matrix`` and the
    validity constants of ``engine.geometry.camera``."""
    rows = matrix.astype(np.float32)
    return {"row0": tuple(float(c) for c in rows[0]), "row1": tuple(float(c) for c in rows[1]),
            "row2": tuple(float(c) for c in rows[2]), "max_coord_inv": float(np.float32(1.0 / MAX_PIXEL_COORD)),
            "tiny_depth": float(np.float32(TINY_DEPTH))}


def splat_uniforms(matrix: np.ndarray, src_size: tuple[int, int, int], dst_size: tuple[int, int],
                   sharpness: float, has_flow: bool, flow_scale: float = 1.0) -> dict:
    """The splat passes' uniforms: ``reprojection_uniforms``, sizes (Z, H, W) and (HO, WO), the soft z-buffer
    and snapping constants of ``engine.geometry.splat``."""
    return {
        **reprojection_uniforms(matrix),
        "src_size": tuple(int(s) for s in src_size), "dst_size": tuple(int(s) for s in dst_size),
        "has_flow": int(has_flow), "flow_scale": float(flow_scale),
        "sharpness": float(np.float32(sharpness)), "snap": float(np.float32(SUBPIXEL_SNAP)),
        "snap_scale": float(np.float32(1.0 / (1.0 - 2.0 * SUBPIXEL_SNAP))),
        "min_log_weight": float(MIN_LOG_WEIGHT), "coverage_threshold": float(COVERAGE_THRESHOLD),
    }


def run_splat(gl: GlContext, pool: dict, defines: dict, uniforms: dict, count: int, outputs: int) -> None:
    """Clear the range, keys and sums (buffers 5-7 of ``pool``, sized from the uniforms), then dispatch the
    three point passes over ``count`` points and ``splat_resolve`` over ``outputs`` pixels. The inputs (0-4,
    9) and outputs (8, 10) must be bound by the caller. GL thread only."""
    num_z = uniforms["src_size"][0]
    ho, wo = uniforms["dst_size"]
    bins = num_z * (ho + 2) * (wo + 2)
    gl.buffer(pool, "range", 8).write(np.array([0xFFFFFFFF, 0], dtype=np.uint32))
    pool["range"].bind_to_storage_buffer(5)
    keys = gl.buffer(pool, "keys", 4 * bins)
    gl.clear_words(keys, 4 * bins)
    keys.bind_to_storage_buffer(6)
    sums = gl.buffer(pool, "sums", 4 * ACC_WORDS * bins)
    gl.clear_words(sums, 4 * ACC_WORDS * bins)
    sums.bind_to_storage_buffer(7)
    for name in SPLAT_PASSES:
        gl.dispatch(gl.program(name, defines), count, uniforms)
    gl.dispatch(gl.program("splat_resolve", defines), outputs, uniforms)


class GlSplatter:
    """``engine.geometry.forward_warp_mpi`` on a ``GlContext`` (the shared one by default): same arguments,
    checks and results.

    >>> warped, coverage = GlSplatter().forward_warp_mpi(mpi, K, T_src, K, T_dst)   # doctest: +SKIP
    """

    def __init__(self, gl: Optional[GlContext] = None) -> None:
        self.gl = shared_context() if gl is None else gl
        self._pool: dict = {}

    def forward_warp_mpi(self, mpi: Mpi, K_src: np.ndarray, T_src: np.ndarray, K_dst: np.ndarray,
                         T_dst: np.ndarray, object_flow: Optional[np.ndarray] = None, *,
                         out_size: Optional[tuple[int, int]] = None,
                         sharpness: float = DEFAULT_SHARPNESS) -> tuple[Mpi, np.ndarray]:
        """Returns ``(warped Mpi, coverage (Z, HO, WO))``, float32 numpy arrays (the warped colour, depth and
        alpha are views of one freshly allocated array)."""
        sizes: dict = {}
        mpi = checked_mpi(mpi, sizes)
        if object_flow is not None:
            object_flow = checked_array(object_flow, "object_flow", (3, "Z", "H", "W"), sizes)
        ho, wo = checked_out_size(out_size, (sizes["H"], sizes["W"]))
        matrix = reprojection_matrix(checked_matrix(K_src, "K_src", 3), checked_matrix(T_src, "T_src", 4),
                                     checked_matrix(K_dst, "K_dst", 3), checked_matrix(T_dst, "T_dst", 4))
        return self.gl.call(self._warp, mpi, matrix, object_flow, ho, wo, checked_sharpness(sharpness))

    def _upload(self, key: str, binding: int, array: Optional[np.ndarray]) -> None:
        data = np.zeros(4, np.float32) if array is None else np.ascontiguousarray(array)
        buf = self.gl.buffer(self._pool, key, data.nbytes)
        buf.write(data)
        buf.bind_to_storage_buffer(binding)

    def _warp(self, mpi: Mpi, matrix: np.ndarray, object_flow, ho: int, wo: int, sharpness: float):
        color, depth, alpha, planes = mpi
        num_z, h, w = alpha.shape
        inv_planes = np.float32(1.0) / planes
        mids = (inv_planes[:-1] + inv_planes[1:]) * np.float32(0.5)
        for key, binding, array in (("color", 0, color), ("depth", 1, depth), ("alpha", 2, alpha),
                                    ("flow", 3, object_flow), ("mids", 4, mids if mids.size else None)):
            self._upload(key, binding, array)
        # the points: every pixel of a one-plane MPI, else the alpha != 0 ones (as the reference)
        index = None if num_z == 1 else np.flatnonzero(alpha).astype(np.uint32)
        self._upload("index", 9, index)
        count = num_z * h * w if index is None else index.size
        out = np.empty((6, num_z, ho, wo), dtype=np.float32)
        out_buf = self.gl.buffer(self._pool, "out", out.nbytes)
        out_buf.bind_to_storage_buffer(8)
        uniforms = splat_uniforms(matrix, (num_z, h, w), (ho, wo), sharpness, object_flow is not None)
        uniforms.update(num_points=count, use_index=int(index is not None))
        run_splat(self.gl, self._pool, {}, uniforms, count, out[0].size)
        out_buf.read_into(out, size=out.nbytes)
        return Mpi(out[0:3], out[3], out[4], planes), out[5]

    def release(self) -> None:
        """Free this splatter's GPU buffers (the context stays)."""
        self.gl.release_pool(self._pool)
