"""``flow2d``'s trust rules on the GPU (``engine.predict.dis.trusted_motion``): an estimated object motion
u(n -> n-k) is kept only where frame n-k saw the surface (``engine.geometry.seen_before``) and, under
``small`` pixels, only where it explains frame n better than no motion by more than ``margin`` 8-bit
levels (``window``^2 means of ``warp_error``); elsewhere it is zeroed,
in the flow's GPU buffer. The thresholds are ``engine.predict.dis``'s, passed in by the caller.

Passes: ``trust_errors`` (per pixel: the error of no motion and of the flow, sampled as OpenCV 5's
``remap`` samples, fused multiply-adds included), ``trust_blur_rows`` and ``trust_apply`` (the window means,
BORDER_REFLECT, sums in double as ``cv2.blur``; the reprojection test; the decision). Inputs are 8-bit lumas
as float buffers (H, W) (pass ``flow_luma`` makes them), the flow (H, W, 2) float32 and frame n's depth (H, W). Oracle: ``trusted_motion``
and ``seen_before`` on the CPU (``tests/geometry/test_gl_trust.py``).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from engine.core.checks import checked_array, checked_matrix
from engine.core.errors import InputError
from engine.geometry.backends.gl.context import GlContext, shared_context
from engine.geometry.backends.gl.splat import reprojection_uniforms
from engine.geometry.camera import reprojection_matrix

__all__ = ["GlTrust"]


class GlTrust:
    """The trust rules on a ``GlContext`` (the shared one by default), with the thresholds the caller takes from
    ``engine.predict.dis`` (``SMALL_MOTION``, ``CONFIDENCE_MARGIN``, ``CONFIDENCE_WINDOW``: this module sits
    below it)."""

    def __init__(self, small: float, margin: float, window: int, gl: Optional[GlContext] = None) -> None:
        if not (np.isfinite(small) and np.isfinite(margin) and int(window) >= 1 and int(window) % 2 == 1):
            raise InputError(f"thresholds must be finite and the window odd, got {small}, {margin}, {window}",
                             field="GlTrust")
        self.gl = shared_context() if gl is None else gl
        self.small, self.margin, self.window = float(small), float(margin), int(window)
        self._pool: dict = {}

    def apply_buffers(self, luma_n, target, flow, depth_n, shape: tuple[int, int], matrix: np.ndarray,
                      prev_size: tuple[int, int]) -> None:
        """Zero the untrusted motion of ``flow`` (a (H, W, 2) float32 buffer) in place. ``luma_n``, ``target``:
        (H, W) float buffers of 8-bit levels; ``depth_n`` (H, W) float32 buffer; ``matrix`` the float64
        reprojection matrix from frame n's pixels to frame n-k's (``reprojection_matrix``); GL thread only."""
        gl, pool = self.gl, self._pool
        h, w = shape
        n = h * w
        for binding, buf in ((20, luma_n), (21, target), (22, flow), (1, depth_n)):
            buf.bind_to_storage_buffer(binding)
        for key, binding, nbytes in (("still", 23, 4 * n), ("moved", 24, 4 * n), ("rows", 25, 16 * n)):
            gl.buffer(pool, key, nbytes).bind_to_storage_buffer(binding)
        defines = {"WINDOW": self.window}
        gl.dispatch(gl.program("trust_errors"), n, {"size": (h, w)})
        gl.dispatch(gl.program("trust_blur_rows", defines), n, {"size": (h, w)})
        gl.dispatch(gl.program("trust_apply", defines), n, {
            **reprojection_uniforms(matrix), "size": (h, w), "prev_size": tuple(int(s) for s in prev_size),
            "small": self.small, "margin": self.margin})

    def trusted(self, luma_n: np.ndarray, target: np.ndarray, flow: np.ndarray, depth_n: np.ndarray,
                K_n: np.ndarray, T_n: np.ndarray, K_prev: np.ndarray, T_prev: np.ndarray,
                prev_size: tuple[int, int]) -> np.ndarray:
        """The flow (H, W, 2) with its untrusted motion zeroed, from host arrays: ``luma_n``, ``target`` (H, W)
        uint8, ``flow`` (H, W, 2) pixels, ``depth_n`` (H, W) planar (+inf sky), cameras as ``seen_before``
        takes them."""
        sizes: dict = {}
        lumas = [np.ascontiguousarray(checked_array(a, name, ("H", "W"), sizes, floating=False), dtype=np.float32)
                 for name, a in (("luma_n", luma_n), ("target", target))]
        flow = np.ascontiguousarray(checked_array(flow, "flow", ("H", "W", 2), sizes))
        depth = np.ascontiguousarray(checked_array(depth_n, "depth_n", ("H", "W"), sizes))
        matrix = reprojection_matrix(checked_matrix(K_n, "K_n", 3), checked_matrix(T_n, "T_n", 4),
                                     checked_matrix(K_prev, "K_prev", 3), checked_matrix(T_prev, "T_prev", 4))
        out = np.empty_like(flow)

        def run():
            buffers = [self.gl.new_buffer(data=a) for a in (*lumas, flow, depth)]
            try:
                self.apply_buffers(*buffers, depth.shape, matrix, prev_size)
                buffers[2].read_into(out)
            finally:
                self.gl.discard(buffers)
        self.gl.call(run)
        return out

    def release(self) -> None:
        """Free the work buffers."""
        self.gl.release_pool(self._pool)
