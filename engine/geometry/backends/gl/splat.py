"""The forward splat on the GPU (shaders ``splat_*.comp``): an MPI to another camera, as
``engine.geometry.forward_warp_mpi`` (its oracle, ``tests/geometry/test_gl_splat.py``).

Two splats give the same bits (``SPLATS``; each pass over the points recomputes their reprojection, cheaper
than storing it). The points are every pixel of a frame or one-plane MPI, else the alpha != 0 ones listed
by ``np.flatnonzero``; a destination bin is (plane, padded pixel), and a point has its four bilinear taps in
the bins of its top-left tap ``base``, base + 1, base + WP, base + WP + 1. Both sum, per bin, the coverage,
the weight and weight * (r, g, b, z) as 64-bit fixed point (2^-32 units), the weight relative to the bin's
largest log splat weight ``t_max`` (``cover * zbuf / exp(t_max)`` in (0, 1]: the per-bin factor cancels in
the normalisation), so the sums are exact and independent of the order; sky points (+inf) count only in bins
no finite point reached (the reference gives them e^-300). They differ in how the sums are made:

``"binned"`` (the default): the points are sorted into the bins of their top-left taps, then every output
pixel gathers its sums in registers from the four bins that reach it: one 32-bit atomic a point, no per-bin
sums in memory (the GPU's warp, ``docs/gpu.md``).

1. ``splat_bin_count``: a point's place in its bin (``atomicAdd`` on the bin's count) and the (min, max) of
   log(1 + z) over the kept finite points (reduced per workgroup in shared memory, then one ``atomicMin`` /
   ``atomicMax`` per workgroup on the order-preserving bits of the floats);
2. ``splat_bin_scan``: exclusive prefix sum of the counts within blocks of ``SCAN_BLOCK`` bins (it also zeroes
   the counts for the next splat: they are cleared once, when their buffer is made);
3. ``splat_bin_blocks``: prefix sum of the blocks' totals (one workgroup);
4. ``splat_bin_scatter``: a point's record (fx, fy, z, source index), 16 bytes, at its place;
5. ``splat_gather``: per output pixel, ``t_max`` over the records that reach it, then its sums, normalised.

``"atomic"``: the sums live in memory (``ACC_WORDS`` words a bin), made with 32-bit atomics.

1. ``splat_range``: the (min, max) of log(1 + z), as above;
2. ``splat_key``: per bin, ``t_max`` (``atomicMax`` on its order-preserving bits);
3. ``splat_accumulate``: the sums, each from two 32-bit ``atomicAdd`` (the carry into the high word only when
   non-zero);
4. ``splat_resolve``: per output pixel, normalise its bin (the padding ring is cropped).

Both end as ``shaders/splat_store.glsl`` says: the ``FRAME`` variant writes the one-plane composite and the
holes for the hole fill that follows on the GPU.

Deviations from the float64 reference: per-point arithmetic is float32 as in the reference's first pass,
weights are exponentiated in float32 (relative error ~1e-6), sums are exact 64-bit fixed point (absolute
resolution 2^-32 of weight * value). Needs OpenGL 4.5 compute with ``GL_ARB_gpu_shader_int64`` (Mesa llvmpipe
has both; no float or 64-bit atomics).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from engine.core.checks import checked_array, checked_matrix, checked_out_size, checked_sharpness
from engine.core.errors import InputError
from engine.geometry.backends.gl.context import LOCAL_SIZE, GlContext, shared_context
from engine.geometry.camera import MAX_PIXEL_COORD, TINY_DEPTH, reprojection_matrix
from engine.geometry.mpi import Mpi, checked_mpi
from engine.geometry.splat import COVERAGE_THRESHOLD, DEFAULT_SHARPNESS, MIN_LOG_WEIGHT, SUBPIXEL_SNAP

__all__ = ["SPLATS", "ACC_WORDS", "SPLAT_PASSES", "BINNED_PASSES", "SCAN_BLOCK", "checked_splat",
           "reprojection_uniforms", "splat_uniforms", "run_splat", "splat_bytes", "GlSplatter"]

#: The splats (same results, see above), the default first.
SPLATS = ("binned", "atomic")
#: 32-bit words of fixed-point accumulators per bin of the atomic splat: (low, high) of coverage, weight,
#: w r, w g, w b, w z.
ACC_WORDS = 12
#: The atomic splat's dispatches over the points, in order (then ``splat_resolve`` over the output pixels).
SPLAT_PASSES = ("splat_range", "splat_key", "splat_accumulate")
#: The binned splat's dispatches, in order: over the points, the bins' blocks, one group, the points, the
#: output pixels.
BINNED_PASSES = ("splat_bin_count", "splat_bin_scan", "splat_bin_blocks", "splat_bin_scatter", "splat_gather")
#: Bins per block of the binned splat's scan (``shaders/splat_common.glsl``'s ``SCAN_BLOCK``).
SCAN_BLOCK = 4 * LOCAL_SIZE


def checked_splat(splat: str) -> str:
    """``splat`` if it names one of ``SPLATS``, else an InputError naming the field."""
    if splat not in SPLATS:
        raise InputError(f"must be one of {', '.join(SPLATS)}, got {splat!r}", field="splat")
    return splat


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


def splat_bytes(splat: str, bins: int, points: int) -> dict[str, int]:
    """The bytes of the work buffers of ``splat`` for ``bins`` destination bins and ``points`` points (the
    inputs and the output excluded), by buffer: what a splat clears, writes and reads besides its inputs."""
    if checked_splat(splat) == "atomic":
        return {"range": 8, "keys": 4 * bins, "sums": 4 * ACC_WORDS * bins}
    return {"range": 8, "counts": 4 * bins, "slots": 4 * points, "offsets": 4 * bins,
            "blocks": 4 * -(-bins // SCAN_BLOCK), "records": 16 * points}


def run_splat(gl: GlContext, pool: dict, defines: dict, uniforms: dict, count: int, outputs: int,
              splat: str = SPLATS[0]) -> None:
    """Run ``splat`` (one of ``SPLATS``) over ``count`` points into ``outputs`` pixels, its work buffers in
    ``pool`` (sized from the uniforms; the atomic splat clears its keys and sums, the binned one only the
    counts of a new buffer). The inputs (bindings 0-4, 9) and outputs (8, 10) must be bound by the caller.
    GL thread only."""
    num_z = uniforms["src_size"][0]
    ho, wo = uniforms["dst_size"]
    bins = num_z * (ho + 2) * (wo + 2)
    sizes = splat_bytes(splat, bins, count)
    gl.buffer(pool, "range", sizes["range"]).write(np.array([0xFFFFFFFF, 0], dtype=np.uint32))
    pool["range"].bind_to_storage_buffer(5)
    if splat == "atomic":
        for key, binding in (("keys", 6), ("sums", 7)):
            buf = gl.buffer(pool, key, sizes[key])
            gl.clear_words(buf, sizes[key])
            buf.bind_to_storage_buffer(binding)
        for name in SPLAT_PASSES:
            gl.dispatch(gl.program(name, defines), count, uniforms)
        gl.dispatch(gl.program("splat_resolve", defines), outputs, uniforms)
        return
    counts = pool.get("counts")
    if counts is None or counts.size < sizes["counts"]:  # made now: zeroed once, then by every scan
        counts = gl.buffer(pool, "counts", sizes["counts"])
        gl.clear_words(counts, counts.size)
    for key, binding in (("counts", 20), ("slots", 21), ("offsets", 22), ("blocks", 23), ("records", 24)):
        gl.buffer(pool, key, sizes[key]).bind_to_storage_buffer(binding)
    blocks = -(-bins // SCAN_BLOCK)
    uniforms = {**uniforms, "num_bins": bins, "num_blocks": blocks}
    gl.dispatch(gl.program("splat_bin_count", defines), count, uniforms)
    gl.dispatch_groups(gl.program("splat_bin_scan", defines), blocks, uniforms)
    gl.dispatch_groups(gl.program("splat_bin_blocks", defines), 1, uniforms)
    gl.dispatch(gl.program("splat_bin_scatter", defines), count, uniforms)
    gl.dispatch(gl.program("splat_gather", defines), outputs, uniforms)


class GlSplatter:
    """``engine.geometry.forward_warp_mpi`` on a ``GlContext`` (the shared one by default) with one of
    ``SPLATS``: same arguments, checks and results.

    >>> warped, coverage = GlSplatter().forward_warp_mpi(mpi, K, T_src, K, T_dst)   # doctest: +SKIP
    """

    def __init__(self, gl: Optional[GlContext] = None, splat: str = SPLATS[0]) -> None:
        self.gl = shared_context() if gl is None else gl
        self.splat_kind = checked_splat(splat)
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
        run_splat(self.gl, self._pool, {}, uniforms, count, out[0].size, self.splat_kind)
        out_buf.read_into(out, size=out.nbytes)
        return Mpi(out[0:3], out[3], out[4], planes), out[5]

    def release(self) -> None:
        """Free this splatter's GPU buffers (the context stays)."""
        self.gl.release_pool(self._pool)
