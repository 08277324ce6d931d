"""``decomp``'s refinement check on the GPU, per network box: the network's residual flow upsampled to the box's
full-resolution pixels, added to the initial flow resident on the GPU, and per pixel the refined or the
initial flow kept by their photometric errors (the CPU's ``engine.predict.decomp.predictor.refine_box``, its
oracle: ``tests/geometry/test_gl_refine.py``).

Passes: ``refine_errors`` (upsampling as ``engine.geometry.kernels.upsample_planes``, both errors as
``engine.predict.dis.warp_error`` samples them), ``trust_blur_rows`` (row sums of the window, in double) and
``refine_select`` (the window means, the choice, no motion where frame n-k did not see the surface), written
into the flow's buffer. Boxes are (y0, y1, x0, x1) of full-resolution pixels, end exclusive; flows (du, dv)
pixels; the lumas 8-bit levels as float buffers (``GlOpticalFlow.lumas``).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from engine.core.checks import checked_array
from engine.core.errors import InputError
from engine.geometry import kernels
from engine.geometry.backends.gl.context import GlContext, shared_context
from engine.geometry.backends.gl.frame import GlFlow

__all__ = ["GlFlowRefine", "refine_codes", "upsample_taps"]

#: Bit of a ``refine_codes`` byte set where frame n-k saw the surface (the plane index in the bits below).
SEEN_BIT = 128


def refine_codes(plane_index: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(h, w) uint8 a pixel of a box: its plane (< 128) plus ``SEEN_BIT`` where frame n-k saw the surface."""
    if plane_index.shape != seen.shape or (plane_index.size and int(plane_index.max()) >= SEEN_BIT):
        raise InputError(f"plane index {plane_index.shape} (planes < {SEEN_BIT}) and seen {seen.shape} must match",
                         field="plane_index")
    return (plane_index.astype(np.uint8) | (seen.astype(np.uint8) * np.uint8(SEEN_BIT))).astype(np.uint8)


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


class GlFlowRefine:
    """The refinement check with the caller's ``margin`` (8-bit levels) and ``window`` (odd, pixels), on a
    ``GlContext`` (the shared one by default)."""

    def __init__(self, margin: float, window: int, gl: Optional[GlContext] = None) -> None:
        if not (np.isfinite(margin) and int(window) >= 1 and int(window) % 2 == 1):
            raise InputError(f"the margin must be finite and the window odd, got {margin}, {window}",
                             field="GlFlowRefine")
        self.gl = shared_context() if gl is None else gl
        self.margin, self.window = float(margin), int(window)
        self._pool: dict = {}

    def apply(self, flow: GlFlow, initial: GlFlow, lumas, box: tuple[int, int, int, int], packed: np.ndarray,
              factor: int, codes: np.ndarray, gpu_ms: Optional[dict] = None) -> None:
        """Write the part ``box`` of ``flow`` (a 2-channel ``GlFlow`` of frame n): the refined flow where it wins,
        else ``initial``'s (the initial flow: ``flow`` itself, or a copy when boxes overlap, so that every box
        starts from the initial flow as on the CPU). ``lumas``: a callable giving, on the GL thread, (luma of frame n, luma of the camera-compensated
        frame n-k) as (H, W) float buffers (``GlOpticalFlow.lumas``); ``packed`` (Z, h_low, w_low, 4)
        float32: per plane the alpha-weighted residual (du, dv, dz) and alpha spread into empty neighbours
        (``spread_plane``) on the network's box, whose pixel i spans full pixels [factor i, factor (i + 1))
        from the box's corner; ``codes`` (h, w) uint8 of the box (``refine_codes``). With ``gpu_ms`` the GPU
        milliseconds go to its stage ``refine``."""
        for name, f in (("flow", flow), ("initial", initial)):
            if not isinstance(f, GlFlow) or f.channels != 2 or f.gl is not self.gl or f.shape != flow.shape:
                raise InputError("must be a 2-channel GlFlow of this context, of the flow's shape", field=name)
        big_h, big_w = flow.shape
        y0, y1, x0, x1 = (int(v) for v in box)
        if not (0 <= y0 < y1 <= big_h and 0 <= x0 < x1 <= big_w):
            raise InputError(f"box {box} is empty or outside the frame {flow.shape}", field="box")
        h, w = y1 - y0, x1 - x0
        codes = np.ascontiguousarray(checked_array(codes, "codes", (h, w), {}, np.uint8, floating=False))
        packed = np.ascontiguousarray(checked_array(packed, "packed", ("Z", "h_low", "w_low", 4), {}))
        num_z, low_h, low_w, _ = packed.shape
        if int(factor) < 1 or not (0 < low_h * factor <= h and 0 < low_w * factor <= w):
            raise InputError(f"the network's box {(low_h, low_w)} times {factor} must fit the box {(h, w)}",
                             field="packed")
        if int((codes & (SEEN_BIT - 1)).max()) >= num_z:
            raise InputError(f"codes name planes up to {int((codes & (SEEN_BIT - 1)).max())}, the residual has "
                             f"{num_z}", field="codes")
        taps = upsample_taps((h, w), (low_h, low_w), int(factor))
        code_words = np.zeros(-(-h * w // 4) * 4, np.uint8)
        code_words[:h * w] = codes.ravel()
        n = h * w

        def run():
            gl, pool = self.gl, self._pool
            uploads = [gl.new_buffer(data=a) for a in (packed, code_words, taps)]
            try:
                luma_n, target = lumas()
                for binding, buf in ((20, luma_n), (21, target), (22, flow.buffer), (30, initial.buffer),
                                     (27, uploads[0]), (28, uploads[1]), (29, uploads[2])):
                    buf.bind_to_storage_buffer(binding)
                for key, binding, nbytes in (("refined_err", 23, 4 * n), ("init_err", 24, 4 * n),
                                             ("rows", 25, 16 * n), ("refined", 26, 8 * n)):
                    gl.buffer(pool, key, nbytes).bind_to_storage_buffer(binding)
                common = {"size": (h, w), "frame": (big_h, big_w), "origin": (y0, x0)}
                defines = {"WINDOW": self.window}
                with gl.timing(gpu_ms), gl.gpu_stage("refine"):
                    gl.dispatch(gl.program("refine_errors"), n,
                                {**common, "low_size": (low_h, low_w), "factor": float(factor)})
                    gl.dispatch(gl.program("trust_blur_rows", defines), n, {"size": (h, w)})
                    gl.dispatch(gl.program("refine_select", defines), n, {**common, "margin": self.margin})
            finally:
                gl.discard(uploads)
        self.gl.call(run)

    def release(self) -> None:
        """Free the work buffers."""
        self.gl.release_pool(self._pool)
