"""``decomp``'s boxes on the GPU: the initial flow block-averaged as the network's input, and the refinement
check that follows the network (the CPU's ``engine.predict.decomp.predictor.refine_box``, its oracle:
``tests/predict/test_gl_refine.py``): the network's residual flow upsampled to the box's full-resolution
pixels, added to the initial flow resident on the GPU, and per pixel the refined or the initial flow kept by
their photometric errors, none where frame n-k did not see the surface.

Passes: ``refine_downsample`` (``engine.geometry.downsample_flow`` of the box), ``refine_errors`` (the pixel's
plane as ``engine.geometry.plane_index``, the upsampling as ``engine.geometry.kernels.upsample_planes``, both
errors as ``engine.predict.dis.warp_error`` samples them), ``trust_blur_rows`` (row sums of the window, in
double) and ``refine_select`` (the window means, the choice, ``seen_before``), written into the flow's buffer.
Boxes are (y0, y1, x0, x1) of full-resolution pixels, end exclusive; flows (du, dv) pixels; the lumas 8-bit
levels as float buffers (``GlOpticalFlow.lumas``); depth planar, +inf sky.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from engine.core.checks import checked_array
from engine.core.errors import InputError
from engine.geometry import kernels
from engine.geometry.backends.gl.context import GlContext, shared_context
from engine.geometry.backends.gl.frame import GlFlow, GlImage
from engine.geometry.backends.gl.splat import reprojection_uniforms

__all__ = ["GlFlowRefine", "upsample_taps"]


def upsample_taps(size: tuple[int, int], low_size: tuple[int, int], factor: int) -> np.ndarray:
    """(h + w, 4) int32 rows (first, second, weight as float32 bits, 0): ``kernels.upsample_planes``' bilinear
    taps of the box's rows, then of its columns."""
    taps = []
    for n, small in zip(size, low_size):
        first, second, weight = kernels._linear_taps(int(n), int(small), int(factor))
        part = np.zeros((int(n), 4), np.int32)
        part[:, 0], part[:, 1] = first, second
        part[:, 2] = np.asarray(weight, np.float32).view(np.int32)
        taps.append(part)
    return np.ascontiguousarray(np.concatenate(taps))


def _checked_box(box, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    y0, y1, x0, x1 = (int(v) for v in box)
    if not (0 <= y0 < y1 <= shape[0] and 0 <= x0 < x1 <= shape[1]):
        raise InputError(f"box {tuple(box)} is empty or outside the frame {shape}", field="box")
    return y0, y1, x0, x1


class GlFlowRefine:
    """The boxes' passes with the caller's ``margin`` (8-bit levels) and ``window`` (odd, pixels), on a
    ``GlContext`` (the shared one by default)."""

    def __init__(self, margin: float, window: int, gl: Optional[GlContext] = None) -> None:
        if not (np.isfinite(margin) and int(window) >= 1 and int(window) % 2 == 1):
            raise InputError(f"the margin must be finite and the window odd, got {margin}, {window}",
                             field="GlFlowRefine")
        self.gl = shared_context() if gl is None else gl
        self.margin, self.window = float(margin), int(window)
        self._pool: dict = {}

    def _check_flow(self, name: str, flow, shape=None) -> None:
        if not isinstance(flow, GlFlow) or flow.channels != 2 or flow.gl is not self.gl or \
                (shape is not None and flow.shape != shape):
            raise InputError("must be a 2-channel GlFlow of this context" + (f" of shape {shape}" if shape else ""),
                             field=name)

    def initial_low(self, initial: GlFlow, box: tuple[int, int, int, int], factor: int) -> np.ndarray:
        """The block means of ``initial`` over ``box`` by ``factor``, in working-resolution pixels: (h // factor,
        w // factor, 2) float32 read back (``engine.geometry.downsample_flow`` of the box; rows and columns
        past the last whole block drop out)."""
        self._check_flow("initial", initial)
        y0, y1, x0, x1 = _checked_box(box, initial.shape)
        f = int(factor)
        if f < 1 or (y1 - y0) < f or (x1 - x0) < f:
            raise InputError(f"must be >= 1 and at most the box's sides {(y1 - y0, x1 - x0)}, got {factor}",
                             field="factor")
        low = ((y1 - y0) // f, (x1 - x0) // f)
        out = np.empty(low + (2,), np.float32)

        def run():
            gl = self.gl
            buf = gl.buffer(self._pool, "low", 8 * low[0] * low[1])
            initial.buffer.bind_to_storage_buffer(30)
            buf.bind_to_storage_buffer(26)
            gl.dispatch(gl.program("refine_downsample"), low[0] * low[1],
                        {"frame": initial.shape, "origin": (y0, x0), "low_size": low, "factor": f})
            buf.read_into(out, size=out.nbytes)
        self.gl.call(run)
        return out

    def apply(self, flow: GlFlow, initial: GlFlow, lumas, frame_n: GlImage, matrix: np.ndarray,
              prev_size: tuple[int, int], bounds: np.ndarray, box: tuple[int, int, int, int], packed: np.ndarray,
              factor: int, gpu_ms: Optional[dict] = None) -> None:
        """Write the part ``box`` of ``flow`` (a 2-channel ``GlFlow`` of frame n): the refined flow where it wins,
        else ``initial``'s (the initial flow: ``flow`` itself, or a copy when boxes overlap, so that every box
        starts from the initial flow as on the CPU), and 0 where frame n-k did not see the surface.

        ``lumas``: a callable giving, on the GL thread, (luma of frame n, luma of the camera-compensated frame
        n-k) as (H, W) float buffers (``GlOpticalFlow.lumas``); ``frame_n``: frame n on the GPU (its depth);
        ``matrix``: the float64 reprojection matrix from frame n's pixels to frame n-k's
        (``reprojection_matrix``, 4 x 4), ``prev_size`` frame n-k's (h, w); ``bounds``: the network's plane bounds
        (``plane_bounds``, Z - 1 float32); ``packed`` (Z, h_low, w_low, 4) float32: per plane the
        alpha-weighted residual (du, dv, dz) and alpha spread into empty neighbours (``spread_plane``) on the
        network's box, whose pixel i spans full pixels [factor i, factor (i + 1)) from the box's corner. With
        ``gpu_ms`` the GPU milliseconds go to its stage ``refine``."""
        self._check_flow("flow", flow)
        self._check_flow("initial", initial, flow.shape)
        if not isinstance(frame_n, GlImage) or frame_n.gl is not self.gl or frame_n.shape != flow.shape:
            raise InputError(f"must be a GlImage of this context of shape {flow.shape}", field="frame_n")
        big_h, big_w = flow.shape
        y0, y1, x0, x1 = _checked_box(box, flow.shape)
        h, w = y1 - y0, x1 - x0
        packed = np.ascontiguousarray(checked_array(packed, "packed", ("Z", "h_low", "w_low", 4), {}))
        num_z, low_h, low_w, _ = packed.shape
        if int(factor) < 1 or not (0 < low_h * factor <= h and 0 < low_w * factor <= w):
            raise InputError(f"the network's box {(low_h, low_w)} times {factor} must fit the box {(h, w)}",
                             field="packed")
        bounds = np.ascontiguousarray(checked_array(bounds, "bounds", (num_z - 1,), {}))
        matrix = np.asarray(matrix, np.float64)
        if matrix.shape != (4, 4) or not np.isfinite(matrix).all():
            raise InputError(f"must be a finite (4, 4) reprojection matrix, got shape {matrix.shape}", field="matrix")
        uniforms = reprojection_uniforms(matrix)
        taps = upsample_taps((h, w), (low_h, low_w), int(factor))
        n = h * w

        def run():
            gl, pool = self.gl, self._pool
            bound_data = bounds if bounds.size else np.zeros(1, np.float32)  # one plane: no bounds
            uploads = [gl.new_buffer(data=a) for a in (packed, taps, bound_data)]
            try:
                luma_n, target = lumas()
                for binding, buf in ((20, luma_n), (21, target), (22, flow.buffer), (30, initial.buffer),
                                     (1, frame_n.depth), (27, uploads[0]), (29, uploads[1]), (28, uploads[2])):
                    buf.bind_to_storage_buffer(binding)
                for key, binding, nbytes in (("refined_err", 23, 4 * n), ("init_err", 24, 4 * n),
                                             ("rows", 25, 16 * n), ("refined", 26, 8 * n)):
                    gl.buffer(pool, key, nbytes).bind_to_storage_buffer(binding)
                common = {"size": (h, w), "frame": (big_h, big_w), "origin": (y0, x0)}
                defines = {"WINDOW": self.window}
                with gl.timing(gpu_ms), gl.gpu_stage("refine"):
                    gl.dispatch(gl.program("refine_errors"), n, {**common, "low_size": (low_h, low_w),
                                                                 "factor": float(factor), "num_bounds": num_z - 1})
                    gl.dispatch(gl.program("trust_blur_rows", defines), n, {"size": (h, w)})
                    gl.dispatch(gl.program("refine_select", defines), n, {
                        **common, **uniforms, "margin": self.margin,
                        "prev_size": tuple(int(s) for s in prev_size)})
            finally:
                gl.discard(uploads)
        self.gl.call(run)

    def release(self) -> None:
        """Free the work buffers."""
        self.gl.release_pool(self._pool)
