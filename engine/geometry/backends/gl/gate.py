"""``decomp``'s motion gate on the GPU: per tile of the working resolution, how many pixels still changed after
camera motion is cancelled (the CPU's ``engine.predict.decomp.gate``: ``downsample_frame``, a one-plane warp of
frame n-k, ``motion_residual``, ``seen_before``, ``tile_counts``; its oracle in
``tests/predict/test_gl_gate.py``). Only the counts come back; the boxes are made from them on the CPU, as
from the CPU's counts.

Passes: ``gate_downsample`` (both frames to the working resolution; frame n's finite depth range), the
``FRAME`` splat of frame n-k's working-resolution image into frame n's view (``GlFrameWarper.splat``),
``gate_residual`` (the changed pixels) and ``gate_tiles`` (erosion, "seen before", the tile counts).
Conventions: ``engine.geometry`` (OpenCV cameras, pixel centres at +0.5, planar depth, +inf sky); the
thresholds are ``GateConfig``'s, passed in by the caller (this module sits below it).
"""
from __future__ import annotations

import math
import struct
from typing import Optional

import numpy as np

from engine.core.checks import checked_matrix
from engine.core.errors import InputError
from engine.geometry.backends.gl.context import GlContext, shared_context
from engine.geometry.backends.gl.frame import GlFrameWarper, GlImage
from engine.geometry.backends.gl.splat import reprojection_uniforms
from engine.geometry.camera import reprojection_matrix
from engine.geometry.mpi import downsampled_intrinsics
from engine.geometry.splat import DEFAULT_SHARPNESS

__all__ = ["GlGate"]


class GlGate:
    """The gate's passes with the caller's thresholds (``GateConfig``: ``color_threshold``, ``depth_threshold``,
    ``erode``, ``unseen``, ``tile``) on a ``GlContext`` (the shared one by default)."""

    def __init__(self, color_threshold: float, depth_threshold: float, erode: bool, unseen: bool, tile: int,
                 gl: Optional[GlContext] = None) -> None:
        if not (color_threshold > 0 and depth_threshold > 0 and int(tile) >= 1):
            raise InputError(f"thresholds must be > 0 and the tile >= 1, got {color_threshold}, {depth_threshold}, "
                             f"{tile}", field="GlGate")
        self.gl = shared_context() if gl is None else gl
        self.color_threshold, self.depth_threshold = float(color_threshold), float(depth_threshold)
        self.erode, self.unseen, self.tile = bool(erode), bool(unseen), int(tile)
        self._warper = GlFrameWarper(self.gl)  # its own splat buffers: a predictor's warps keep theirs
        self._pool: dict = {}

    def tile_counts(self, frame_n: GlImage, frame_p: GlImage, K_n: np.ndarray, T_n: np.ndarray, K_p: np.ndarray,
                    T_p: np.ndarray, factor: int, gpu_ms: Optional[dict] = None) -> np.ndarray:
        """(ceil(h / tile), ceil(w / tile)) uint32: per tile of the working resolution (h, w) = frame size //
        ``factor``, the pixels that moved (``engine.predict.decomp.gate.tile_counts`` of the CPU's changed
        mask). ``frame_n``, ``frame_p``: frames n and n-k on the GPU, of one size; ``K_*`` their full-resolution
        intrinsics, ``T_*`` world-to-camera. With ``gpu_ms`` the GPU milliseconds go to its stage ``gate``."""
        for name, image in (("frame_n", frame_n), ("frame_p", frame_p)):
            if not isinstance(image, GlImage) or image.gl is not self.gl:
                raise InputError("must be a GlImage of this context", field=name)
        if frame_p.shape != frame_n.shape:
            raise InputError(f"frame n-k is {frame_p.shape}, frame n {frame_n.shape}: the gate needs one size",
                             field="frame_p")
        big_h, big_w = frame_n.shape
        f = int(factor)
        if not 1 <= f <= min(big_h, big_w):
            raise InputError(f"must be between 1 and the frame's smaller side {min(big_h, big_w)}, got {factor}",
                             field="factor")
        low = (big_h // f, big_w // f)
        k_n = downsampled_intrinsics(checked_matrix(K_n, "K_n", 3), f)
        k_p = downsampled_intrinsics(checked_matrix(K_p, "K_p", 3), f)
        t_n, t_p = checked_matrix(T_n, "T_n", 4), checked_matrix(T_p, "T_p", 4)
        warp = reprojection_matrix(k_p, t_p, k_n, t_n)  # frame n-k's pixels into frame n's view
        back = reprojection_matrix(k_n, t_n, k_p, t_p)  # frame n's pixels into frame n-k's (seen before)
        tiles = (math.ceil(low[0] / self.tile), math.ceil(low[1] / self.tile))
        out = np.empty(tiles, np.uint32)
        threshold = np.frombuffer(struct.pack("<d", self.depth_threshold), np.uint32)
        n = low[0] * low[1]

        def run():
            gl, pool = self.gl, self._pool
            common = {"width": big_w, "low_size": low, "factor": f, "scale": float(np.float32(1.0 / (f * f)))}
            images = []
            with gl.timing(gpu_ms), gl.gpu_stage("gate"):
                rng = gl.buffer(pool, "range", 8)
                rng.write(np.array([0xFFFFFFFF, 0], dtype=np.uint32))  # (min, max) bits: empty
                for key, image in (("n", frame_n), ("p", frame_p)):
                    color = gl.buffer(pool, f"color_{key}", 12 * n)
                    depth = gl.buffer(pool, f"depth_{key}", 4 * n)
                    for binding, buf in ((0, image.color), (1, image.depth), (20, color), (21, depth), (22, rng)):
                        buf.bind_to_storage_buffer(binding)
                    gl.dispatch(gl.program("gate_downsample", {"RANGE": None} if key == "n" else None), n, common)
                    images.append(GlImage(low, color, depth, gl, owned=False))
                self._warper.splat(images[1], warp, DEFAULT_SHARPNESS)  # warped_ at 8, hole_ at 10
                changed = gl.buffer(pool, "changed", 4 * n)
                counts = gl.buffer(pool, "counts", 4 * tiles[0] * tiles[1])
                gl.clear_words(counts, 4 * tiles[0] * tiles[1])
                for binding, buf in ((20, images[0].color), (21, images[0].depth), (22, rng), (23, changed),
                                     (24, counts)):
                    buf.bind_to_storage_buffer(binding)
                gl.dispatch(gl.program("gate_residual"), n, {
                    "size": low, "color_threshold": float(np.float32(self.color_threshold)),
                    "depth_threshold": (int(threshold[0]), int(threshold[1]))})
                defines = {name: None for name, on in (("ERODE", self.erode), ("UNSEEN", self.unseen)) if on}
                gl.dispatch(gl.program("gate_tiles", defines), n, {
                    **reprojection_uniforms(back), "size": low, "tile": self.tile, "tiles_w": tiles[1],
                    "prev_size": low})
                counts.read_into(out, size=out.nbytes)
        self.gl.call(run)
        return out

    def release(self) -> None:
        """Free the work buffers."""
        self._warper.release()
        self.gl.release_pool(self._pool)
