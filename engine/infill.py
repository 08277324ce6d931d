"""Disocclusion infilling in the engine (thesis Sec. 6.3.4), numpy + onnxruntime, no torch.

The network (``models/infill.py``, exported by ``export/infill.py``) runs at its working width (the
width its training frames had, from the ONNX metadata), like the flow network: the predicted frame is
block-downsampled (``downsample_holes``: a block is a hole if any of its pixels is), re-binned into a
one-hot MPI on frame n's planes (``hole_mpi``), and the network predicts per plane a correction of the
prior vectors (``prior_vectors``: where ``engine.holefill`` would copy from). At full resolution every
hole pixel then copies, per plane, the *nearest* point its block's vector (times the block size) points
to (``apply_vectors``); the nearest plane that received a copy is what the composite shows. ``g`` passes,
then the simple fill for what is still open (a hole with no known pixel anywhere it can point to).

Every filled pixel is thus a copy of a known pixel of the predicted frame: no colour is invented.
Conventions: ``engine/geometry.py`` (pixel centres at +0.5, planar depth, +inf sky, MPIs (C, Z, H, W)).
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional

import numpy as np

from engine import geometry
from engine.errors import InputError, InterleaveError
from engine.geometry import Mpi
from engine.holefill import fill_holes, fill_sources

__all__ = ["InfillNetwork", "DEFAULT_INFILL_MODEL", "METADATA_KEY", "downsample_holes", "hole_mpi",
           "prior_vectors", "apply_vectors", "composite_holes"]

#: The committed infilling network (see ``engine/weights/README.md``).
DEFAULT_INFILL_MODEL = Path(__file__).resolve().parent / "weights" / "infill.onnx"
#: ONNX metadata key holding the network's ``InfillConfig`` and working width (JSON), set by ``export.infill``.
METADATA_KEY = "interleave.infill"


def downsample_holes(color: np.ndarray, depth: np.ndarray, holes: np.ndarray,
                     factor: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Block-downsample a frame with holes by ``factor``: a block is a hole if any pixel of it is; known
    blocks take the colour mean and the depth minimum (as ``geometry.downsample_frame``). Rows and columns
    past the last whole block are dropped. Returns colour (h, w, 3), depth (h, w) (+inf in holes), holes."""
    f = int(factor)
    if f == 1:
        return color.astype(np.float32), np.where(holes, np.float32(np.inf), depth).astype(np.float32), holes.copy()
    h, w = depth.shape[0] // f, depth.shape[1] // f
    blocks = lambda a: a[:h * f, :w * f].reshape(h, f, w, f, *a.shape[2:])  # noqa: E731
    low_holes = blocks(holes).any(axis=(1, 3))
    low_color = blocks(color).mean(axis=(1, 3), dtype=np.float32)
    low_depth = blocks(depth).min(axis=(1, 3))
    low_color[low_holes] = 0.0
    low_depth = np.where(low_holes, np.float32(np.inf), low_depth).astype(np.float32)
    return low_color.astype(np.float32), low_depth, low_holes


def hole_mpi(color: np.ndarray, depth: np.ndarray, holes: np.ndarray, plane_depths: np.ndarray) -> Mpi:
    """One-hot MPI of a frame with holes on the given planes: alpha (and colour, depth) 0 at hole pixels."""
    mpi = geometry.build_mpi(color, np.where(holes, np.float32(np.inf), depth), len(plane_depths), plane_depths)
    if holes.any():
        mpi.alpha[:, holes] = 0.0
        mpi.color[:, :, holes] = 0.0
        mpi.depth[:, holes] = 0.0
    return mpi


def prior_vectors(depth: np.ndarray, holes: np.ndarray) -> np.ndarray:
    """(2, H, W) float32 (dx, dy) pixels from each hole pixel to where ``engine.holefill`` copies from; 0 at
    known pixels and at holes with no source."""
    src_r, src_c = fill_sources(depth, holes)
    ok = holes & (src_r >= 0)
    rows, cols = np.indices(holes.shape)
    return np.stack([np.where(ok, src_c - cols, 0), np.where(ok, src_r - rows, 0)]).astype(np.float32)


def apply_vectors(mpi: Mpi, holes: np.ndarray, vectors: np.ndarray) -> tuple[Mpi, np.ndarray]:
    """Copy, per plane, the nearest point at p + v into every hole pixel p (numpy mirror of
    ``models.infill.apply_vectors(mode='nearest')``: index = round-half-even(p + v), outside = empty).

    Args:
        mpi: (C, Z, H, W) MPI; holes: (H, W) bool; vectors: (2, Z, H, W) (dx, dy) pixels.
    Returns:
        the infilled MPI (copies) and the holes left (no plane received alpha).
    """
    num_z, h, w = mpi.alpha.shape
    r, c = np.nonzero(holes)
    color, depth, alpha = mpi.color.copy(), mpi.depth.copy(), mpi.alpha.copy()
    for z in range(num_z):
        sx = np.rint(c + vectors[0, z, r, c]).astype(np.int64)
        sy = np.rint(r + vectors[1, z, r, c]).astype(np.int64)
        inside = (sx >= 0) & (sx < w) & (sy >= 0) & (sy < h)
        sx, sy = np.where(inside, sx, 0), np.where(inside, sy, 0)
        a = np.where(inside, mpi.alpha[z, sy, sx], np.float32(0.0))
        on = a > 0
        alpha[z, r, c] = a
        depth[z, r, c] = np.where(on, mpi.depth[z, sy, sx], np.float32(0.0))
        color[:, z, r, c] = np.where(on, mpi.color[:, z, sy, sx], np.float32(0.0))
    left = holes & ~(alpha > 0).any(axis=0)
    return Mpi(color, depth, alpha, mpi.plane_depths), left


def composite_holes(mpi: Mpi) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(colour, depth, holes) of a one-hot MPI: ``geometry.composite`` with holes = nothing covered."""
    color, depth, acc = geometry.composite(mpi)
    return color, depth, acc <= 0


class InfillNetwork:
    """The exported infilling network in onnxruntime, and the engine's infilling loop (``fill``)."""

    def __init__(self, path: str | Path, threads: int = 2) -> None:
        from engine.decomp import open_network

        path = Path(path)
        self.session, info = open_network(path, threads, METADATA_KEY, "infill_model", "infilling network not "
                                          "found (train and export one: interleave train infill / interleave "
                                          "export infill)")
        self.path = path
        self.config: dict = info["model"]
        self.num_planes = int(self.config["num_planes"])
        self.stride = 2 ** (len(self.config["channels"]) - 1)
        self.working_width = int(info["working_width"])

    def vectors(self, mpi: Mpi, holes: np.ndarray, prior: np.ndarray) -> np.ndarray:
        """Infilling vectors (2, Z, H, W) = prior + the network's correction, pixels of the MPI's grid."""
        h, w = holes.shape
        if mpi.alpha.shape != (self.num_planes, h, w) or prior.shape != (2, h, w):
            raise InputError(f"MPI {mpi.alpha.shape} / prior {prior.shape}: the network takes {self.num_planes} "
                             f"planes and a (2, H, W) prior on the same grid", field="mpi")
        feeds = {"color": mpi.color[None], "depth": mpi.depth[None, None], "alpha": mpi.alpha[None, None],
                 "plane_depths": np.asarray(mpi.plane_depths, np.float32)[None],
                 "holes": holes[None].astype(np.float32), "prior": prior[None]}
        ph, pw = -h % self.stride, -w % self.stride
        if ph or pw:  # pad to the U-Net's stride with empty, non-hole pixels; crop back
            feeds = {k: v if k == "plane_depths" else np.pad(v, [(0, 0)] * (v.ndim - 2) + [(0, ph), (0, pw)])
                     for k, v in feeds.items()}
        feeds = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in feeds.items()}
        residual = self.session.run(None, feeds)[0][0][..., :h, :w]
        if not np.isfinite(residual).all():
            raise InterleaveError("the infilling network returned non-finite vectors")
        return prior[:, None] + residual

    def fill(self, color: np.ndarray, depth: np.ndarray, holes: np.ndarray, plane_depths: np.ndarray,
             fallback: Optional[np.ndarray] = None, iterations: int = 3,
             timer: Optional[Callable] = None) -> tuple[np.ndarray, np.ndarray]:
        """Infill the holes of a predicted frame in ``iterations`` passes, then the simple fill for the rest.

        Args:
            color: (H, W, 3) linear RGB; depth: (H, W) planar (+inf sky or hole); holes: (H, W) bool.
            plane_depths: (Z,) planes of frame n (the network's Z); fallback: colour for pixels nothing
                can reach (``engine.holefill``); timer: optional ``timer(stage, fn, *args)`` (stage times).
        Returns:
            (colour, depth) with every hole filled by a copy of a known pixel.
        """
        run = timer if timer is not None else (lambda _name, fn, *a: fn(*a))
        planes = np.asarray(plane_depths, np.float32)
        if planes.shape != (self.num_planes,):
            raise InputError(f"needs {self.num_planes} plane depths, got shape {planes.shape}", field="plane_depths")
        color, depth, holes = color.astype(np.float32), depth.astype(np.float32), holes.astype(bool)
        big_h, big_w = holes.shape
        factor = min(geometry.downsample_factor(big_w, self.working_width), big_h, big_w)
        for _ in range(int(iterations)):
            if not holes.any():
                break
            low_c, low_d, low_h = run("infill_prepare", downsample_holes, color, depth, holes, factor)
            if not low_h.any() or low_h.all():
                break  # nothing at this scale to fill from (all hole) or the holes vanished in the blocks
            low_mpi = run("infill_prepare", hole_mpi, low_c, low_d, low_h, planes)
            prior = run("infill_prepare", prior_vectors, low_d, low_h)
            vec = run("infill_network", self.vectors, low_mpi, low_h, prior)
            # full resolution: each pixel takes its block's vector times the block size (edge blocks repeat)
            rows = np.minimum(np.arange(big_h) // factor, low_h.shape[0] - 1)
            cols = np.minimum(np.arange(big_w) // factor, low_h.shape[1] - 1)
            full_vec = vec[:, :, rows][:, :, :, cols] * np.float32(factor)
            mpi = run("infill_apply", hole_mpi, color, depth, holes, planes)
            mpi, _ = run("infill_apply", apply_vectors, mpi, holes, full_vec)
            color, depth, holes = run("infill_apply", composite_holes, mpi)
        if holes.any():
            color, depth = run("fill", fill_holes, color, depth, holes, fallback)
        return color, depth
