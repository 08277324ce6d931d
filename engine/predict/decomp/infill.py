"""Disocclusion infilling in the engine (thesis Sec. 6.3.4), numpy + onnxruntime, no torch.

The network (``models/infill/network.py``, exported by ``export/infill.py``) runs at its working width (the
width its training frames had, from the ONNX metadata), like the flow network: the predicted frame is
block-downsampled (``downsample_holes``: a block is a hole if any of its pixels is), re-binned into a
one-hot MPI on frame n's planes (``hole_mpi``), and the network predicts per plane a correction of the
prior vectors (``prior_vectors``: where ``engine.geometry.holefill`` would copy from). At full resolution every
hole pixel then copies, per plane, the *nearest* point its block's vector (times the block size) points
to (``apply_vectors``); the nearest plane that received a copy is what the composite shows. ``g`` passes,
then the simple fill for what is still open (a hole with no known pixel anywhere it can point to).

Every filled pixel is thus a copy of a known pixel of the predicted frame: no colour is invented.
Conventions: ``engine/geometry/ops.py`` (pixel centres at +0.5, planar depth, +inf sky, MPIs (C, Z, H, W)).
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from engine import geometry
from engine.core.errors import InputError, InterleaveError
from engine.geometry import Mpi
from engine.geometry.holefill import fill_holes, fill_sources
from engine.predict.base import Timer
from engine.predict.decomp.gate import motion_boxes
from engine.predict.onnx import open_network
from engine.weights import INFILL

__all__ = ["InfillNetwork", "DEFAULT_INFILL_MODEL", "METADATA_KEY", "downsample_holes", "hole_mpi",
           "prior_vectors", "candidate_vectors", "apply_vectors", "composite_holes", "copy_along_vectors", "hole_boxes",
           "RECEPTIVE_MARGIN"]

#: The committed infilling network (see ``engine/weights/README.md``).
DEFAULT_INFILL_MODEL = INFILL
#: ONNX metadata key holding the network's ``InfillConfig`` and working width (JSON), set by ``export.infill``.
METADATA_KEY = "interleave.infill"
#: Pixels of the network grid around a hole that reach its vectors: the committed U-Net's receptive radius
#: (3 levels of two 3 x 3 convolutions, the first of each strided, and their mirror). The hole gate keeps
#: this much context by default, so gating changes no vector (tested).
RECEPTIVE_MARGIN = 48


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
    """(2, H, W) float32 (dx, dy) pixels from each hole pixel to where ``engine.geometry.holefill`` copies from; 0 at
    known pixels and at holes with no source."""
    src_r, src_c = fill_sources(depth, holes)
    ok = holes & (src_r >= 0)
    rows, cols = np.indices(holes.shape)
    return np.stack([np.where(ok, src_c - cols, 0), np.where(ok, src_r - rows, 0)]).astype(np.float32)


def _nearest_known(known: np.ndarray, reverse: bool) -> np.ndarray:
    """(H, W) column of the nearest known pixel to the left (or right with ``reverse``) in each row, -1: none."""
    w = known.shape[1]
    if not reverse:
        return np.maximum.accumulate(np.where(known, np.arange(w), -1), axis=1)
    idx = np.minimum.accumulate(np.where(known, np.arange(w), w)[:, ::-1], axis=1)[:, ::-1]
    return np.where(idx == w, -1, idx)


def candidate_vectors(depth: np.ndarray, holes: np.ndarray) -> np.ndarray:
    """(2 K, H, W) float32 candidate source vectors of the choice head (``models.infill.network.NUM_CANDIDATES`` = 5,
    (dx, dy) pairs in this order): the prior (``prior_vectors``), then the nearest known pixel to the left,
    right, above and below. A direction with no known pixel repeats the prior; 0 at known pixels."""
    prior = prior_vectors(depth, holes)
    known = ~holes
    rows, cols = np.indices(holes.shape)
    left, right = _nearest_known(known, False), _nearest_known(known, True)
    up, down = _nearest_known(known.T, False).T, _nearest_known(known.T, True).T
    out = [prior]
    for src, horizontal in ((left, True), (right, True), (up, False), (down, False)):
        ok = holes & (src >= 0)
        dx = np.where(ok, src - cols, prior[0]) if horizontal else np.where(ok, 0, prior[0])
        dy = np.where(ok, 0, prior[1]) if horizontal else np.where(ok, src - rows, prior[1])
        out += [dx, dy]
    vec = np.concatenate([out[0]] + [np.stack(out[i:i + 2]) for i in range(1, len(out), 2)]).astype(np.float32)
    return np.where(holes[None], vec, np.float32(0.0))


def apply_vectors(mpi: Mpi, holes: np.ndarray, vectors: np.ndarray) -> tuple[Mpi, np.ndarray]:
    """Copy, per plane, the nearest point at p + v into every hole pixel p (numpy mirror of
    ``models.infill.network.apply_vectors(mode='nearest')``: index = round-half-even(p + v), outside = empty).

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


def copy_along_vectors(color: np.ndarray, depth: np.ndarray, holes: np.ndarray, plane_depths: np.ndarray,
                       rows: np.ndarray, cols: np.ndarray,
                       vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The engine's copy step on the listed hole pixels only: the same result as ``hole_mpi`` ->
    ``apply_vectors`` -> ``composite_holes`` (the reference, tested equal), without building the MPI.

    A hole pixel p takes, over the planes front to back, the first known pixel at round-half-even(p + v_z)
    that lies on plane z (the nearest plane that received a copy in the reference's composite).

    Args:
        color: (H, W, 3); depth: (H, W) planar (+inf sky); holes: (H, W) bool; plane_depths: (Z,);
        rows, cols: (N,) the hole pixels to fill; vectors: (2, Z, N) (dx, dy) pixels per plane.
    Returns:
        (colour, depth, holes left): copies written into new arrays; unlisted holes stay holes.
    """
    h, w = holes.shape
    index = np.where(holes, -1, geometry.plane_index(np.where(holes, np.float32(np.inf), depth),
                                                     np.asarray(plane_depths, np.float32)))
    done = np.zeros(rows.shape, dtype=bool)
    src_r, src_c = np.zeros(rows.shape, np.int64), np.zeros(rows.shape, np.int64)
    for z in range(vectors.shape[1]):
        sx = np.rint(cols + vectors[0, z]).astype(np.int64)
        sy = np.rint(rows + vectors[1, z]).astype(np.int64)
        inside = (sx >= 0) & (sx < w) & (sy >= 0) & (sy < h)
        ok = inside & ~done
        ok[ok] = index[sy[ok], sx[ok]] == z
        src_r[ok], src_c[ok] = sy[ok], sx[ok]
        done |= ok
    color, depth, holes = color.copy(), depth.copy(), holes.copy()
    r, c = rows[done], cols[done]
    color[r, c] = color[src_r[done], src_c[done]]
    depth[r, c] = depth[src_r[done], src_c[done]]
    holes[r, c] = False
    return color, depth, holes


def hole_boxes(holes: np.ndarray, margin: int, stride: int,
               full_frame_fraction: float = 0.5) -> list[tuple[int, int, int, int]]:
    """Boxes (y0, y1, x0, x1) of the network grid the infilling network must see: tiles of ``stride``
    pixels holding a hole, grown by ``margin`` pixels of context, snapped to ``stride`` (so a box sees the
    same U-Net grid as the whole frame); the whole frame when the boxes cover more than
    ``full_frame_fraction`` of it (the motion gate's ``engine.predict.decomp.gate.motion_boxes``)."""
    return motion_boxes(holes, stride, 0.0, margin, stride, full_frame_fraction)


class InfillNetwork:
    """The exported infilling network in onnxruntime, and the engine's infilling loop (``fill``)."""

    def __init__(self, path: str | Path, threads: int = 2) -> None:
        path = Path(path)
        self.session, info = open_network(path, threads, METADATA_KEY, "infill_model", "infilling network not "
                                          "found (train and export one: interleave train infill / interleave "
                                          "export infill)")
        self.path = path
        self.config: dict = info["model"]
        self.num_planes = int(self.config["num_planes"])
        self.head = str(self.config.get("head", "residual"))
        self.stride = 2 ** len(self.config["channels"])  # models.infill.network.InfillConfig.stride
        self.working_width = int(info["working_width"])

    def vectors(self, mpi: Mpi, holes: np.ndarray, prior: np.ndarray) -> np.ndarray:
        """Residual head: infilling vectors (2, Z, H, W) = ``prior`` (2, H, W) + the network's correction,
        pixels of the MPI's grid."""
        if self.head != "residual":
            raise InputError("a choice-head network chooses among candidates (choices), it gives no vectors",
                             field="infill_model")
        return prior[:, None] + self._run(mpi, holes, prior)

    def choices(self, mpi: Mpi, holes: np.ndarray, candidates: np.ndarray) -> np.ndarray:
        """Choice head: (H, W) index of the candidate (``candidate_vectors`` (2 K, H, W)) the network scores
        highest (ties to 0, the prior). ``fill`` finds the chosen candidate again at full resolution."""
        if self.head != "choice":
            raise InputError("only a choice-head network chooses among candidates", field="infill_model")
        return np.argmax(self._run(mpi, holes, candidates), axis=0)

    def _run(self, mpi: Mpi, holes: np.ndarray, prior: np.ndarray) -> np.ndarray:
        """The network's raw output on one frame: residual (2, Z, H, W) or logits (K, H, W)."""
        h, w = holes.shape
        channels = 2 if self.head == "residual" else prior.shape[0]
        if mpi.alpha.shape != (self.num_planes, h, w) or prior.shape != (channels, h, w) or channels % 2:
            raise InputError(f"MPI {mpi.alpha.shape} / prior {prior.shape}: the network takes {self.num_planes} "
                             f"planes and (2, H, W) prior or (2 K, H, W) candidate vectors on the same grid",
                             field="mpi")
        feeds = {"color": mpi.color[None], "depth": mpi.depth[None, None], "alpha": mpi.alpha[None, None],
                 "plane_depths": np.asarray(mpi.plane_depths, np.float32)[None],
                 "holes": holes[None].astype(np.float32), "prior": prior[None]}
        ph, pw = -h % self.stride, -w % self.stride
        if ph or pw:  # pad to the U-Net's stride with empty, non-hole pixels; crop back
            feeds = {k: v if k == "plane_depths" else np.pad(v, [(0, 0)] * (v.ndim - 2) + [(0, ph), (0, pw)])
                     for k, v in feeds.items()}
        feeds = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in feeds.items()}
        out = self.session.run(None, feeds)[0][0][..., :h, :w]
        if not np.isfinite(out).all():
            raise InterleaveError("the infilling network returned non-finite outputs")
        return out

    def fill(self, color: np.ndarray, depth: np.ndarray, holes: np.ndarray, plane_depths: np.ndarray,
             fallback: Optional[np.ndarray] = None, iterations: int = 3,
             timer: Optional[Timer] = None, margin: Optional[int] = RECEPTIVE_MARGIN) -> tuple[np.ndarray, np.ndarray]:
        """Infill the holes of a predicted frame in ``iterations`` passes, then the simple fill for the rest.

        Args:
            color: (H, W, 3) linear RGB; depth: (H, W) planar (+inf sky or hole); holes: (H, W) bool.
            plane_depths: (Z,) planes of frame n (the network's Z); fallback: colour for pixels nothing
                can reach (``engine.geometry.holefill``); timer: collects the stage times (``engine.predict.base.Timer``).
            margin: the hole gate: the network runs on boxes around the holes with this many pixels of its
                grid as context (``hole_boxes``; the frame is downsampled and the prior vectors found within
                each box; at ``RECEPTIVE_MARGIN`` or more the vectors equal the whole-frame run's, tested);
                None: on the whole frame.
        Returns:
            (colour, depth) with every hole filled by a copy of a known pixel.
        """
        timer = timer if timer is not None else Timer()
        planes = np.asarray(plane_depths, np.float32)
        if planes.shape != (self.num_planes,):
            raise InputError(f"needs {self.num_planes} plane depths, got shape {planes.shape}", field="plane_depths")
        if margin is not None and int(margin) < 0:
            raise InputError(f"must be >= 0 or None, got {margin}", field="margin")
        color, depth, holes = color.astype(np.float32), depth.astype(np.float32), holes.astype(bool)
        big_h, big_w = holes.shape
        factor = min(geometry.downsample_factor(big_w, self.working_width), big_h, big_w)
        for _ in range(int(iterations)):
            if not holes.any():
                break
            h, w = big_h // factor, big_w // factor
            low_h = holes[:h * factor, :w * factor].reshape(h, factor, w, factor).any(axis=(1, 3))
            if not low_h.any() or low_h.all():
                break  # nothing at this scale to fill from (all hole) or the holes vanished in the blocks
            if margin is None:
                boxes = [(0, h, 0, w)]
            else:
                with timer("infill_prepare"):
                    boxes = hole_boxes(low_h, int(margin), self.stride)
            choice = self.head == "choice"
            vec = np.zeros((2, self.num_planes, h, w), dtype=np.float32)
            pick = np.zeros((h, w), dtype=np.intp)
            for y0, y1, x0, x1 in boxes:  # the frame is downsampled and the prior found inside each box only
                full = (slice(y0 * factor, y1 * factor), slice(x0 * factor, x1 * factor))
                with timer("infill_prepare"):
                    low_c, low_d, box_h = downsample_holes(color[full], depth[full], holes[full], factor)
                    prior = (candidate_vectors if choice else prior_vectors)(low_d, box_h)
                    low_mpi = hole_mpi(low_c, low_d, box_h, planes)
                with timer("infill_network"):
                    if choice:
                        pick[y0:y1, x0:x1] = self.choices(low_mpi, box_h, prior)
                    else:
                        vec[:, :, y0:y1, x0:x1] = self.vectors(low_mpi, box_h, prior)
            # full resolution: each hole pixel takes its block's vector times the block size (residual head),
            # or its block's choice of candidate, found at full resolution (choice head); edge blocks repeat
            rows, cols = np.nonzero(holes)
            brow, bcol = np.minimum(rows // factor, h - 1), np.minimum(cols // factor, w - 1)
            with timer("infill_apply"):
                if choice:
                    cand = candidate_vectors(depth, holes).reshape(-1, 2, big_h, big_w)
                    full_vec = np.broadcast_to(cand[pick[brow, bcol], :, rows, cols].T[:, None],
                                               (2, self.num_planes, rows.size))
                else:
                    full_vec = vec[:, :, brow, bcol] * np.float32(factor)
                color, depth, holes = copy_along_vectors(color, depth, holes, planes, rows, cols, full_vec)
        if holes.any():
            with timer("fill"):
                color, depth = fill_holes(color, depth, holes, fallback)
        return color, depth
