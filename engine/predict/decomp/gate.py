"""The motion gate of ``decomp``: where, after camera motion is cancelled, frame n-k still differs from
frame n, so the flow network must run (and nowhere, in a static view).

Frame n-k, a one-plane MPI at the working resolution, is forward-warped into frame n's view; pixels whose
encoded colour or inverse depth still changed (``motion_residual``), among those frame n-k saw
(``geometry.seen_before``), mark tiles as moving; connected moving tiles, grown by a margin of context, become the
boxes the network sees (``motion_boxes``). Conventions: ``engine.geometry`` (OpenCV cameras, pixel centres
at +0.5, planar depth with +inf sky, MPIs (C, Z, H, W)); boxes are (y0, y1, x0, x1), end exclusive.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from engine import geometry
from engine.core.config import option
from engine.core.errors import InputError
from engine.geometry import Mpi

__all__ = ["GateConfig", "Box", "encode_color", "motion_residual", "tile_counts", "boxes_from_counts", "motion_boxes",
           "gate_boxes"]

#: A box (y0, y1, x0, x1) of pixels, end exclusive.
Box = tuple[int, int, int, int]


@dataclass(frozen=True)
class GateConfig:
    """Options of the motion gate (``decomp[gate.tile=16]``)."""

    enabled: bool = option(True, "run the network only on boxes around tiles whose camera-compensated residual "
                                 "shows object motion, and not at all when none does")
    color_threshold: float = option(0.05, "residual of the encoded colour (0..1, max over RGB) that marks a "
                                         "pixel as changed")
    depth_threshold: float = option(0.02, "relative inverse-depth change that marks a pixel as changed")
    erode: bool = option(True, "erode the changed-pixel mask by 3 x 3 before counting tiles (removes the "
                               "one-pixel seams that resampling leaves along depth edges of a static scene)")
    unseen: bool = option(True, "ignore pixels of frame n whose surface, if static, lay outside frame n-k's "
                                "view (content entering at the frame border under camera motion: frame n-k "
                                "holds nothing to compare it with, and no flow can be estimated there)")
    tile: int = option(8, "tile size of the motion gate, in network pixels")
    min_tiles: int = option(3, "smallest group of connected moving tiles that counts as motion (smaller groups: "
                                "resampling noise along depth edges of a static view)")
    tile_fraction: float = option(0.05, "fraction of a tile's pixels that must change for it to count as moving")
    margin: int = option(24, "network pixels of context kept around moving tiles (covers the search range)")
    full_frame_fraction: float = option(0.5, "run on the whole frame when the boxes cover more than this "
                                             "fraction of it")

    def __post_init__(self) -> None:
        checks = [
            (self.color_threshold > 0 and self.depth_threshold > 0, "thresholds must be > 0"),
            (self.tile >= 1 and self.margin >= 0 and self.min_tiles >= 1, "tile, min_tiles >= 1, margin >= 0"),
            (0 < self.tile_fraction <= 1 and 0 < self.full_frame_fraction <= 1, "fractions must be in (0, 1]"),
        ]
        for ok, problem in checks:
            if not ok:
                raise InputError(problem, field="GateConfig")


def encode_color(color: np.ndarray) -> np.ndarray:
    """numpy mirror of ``models.flow.network.encode_color``: ``sqrt(c / (1 + c) + 1e-4) - 0.01``, c clipped at 0."""
    c = np.maximum(color, np.float32(0.0))
    return np.sqrt(c / (np.float32(1.0) + c) + np.float32(1.0e-4)) - np.float32(0.01)


def motion_residual(mpi_n: Mpi, mpi_prev_warped: Mpi, color_threshold: float, depth_threshold: float,
                    erode: bool = True) -> np.ndarray:
    """(H, W) bool: pixels where the camera-compensated frame n-k differs from frame n (object motion).

    Compares the composites of both MPIs where the warped n-k covers the pixel (disocclusions are not
    evidence of motion): encoded colour (max over RGB) above ``color_threshold`` or inverse depth changed by
    more than ``depth_threshold`` relative to the MPI's middle depth. With ``erode`` a 3 x 3 erosion then
    removes the one-pixel seams that resampling leaves along depth edges of a static scene.
    """
    color_n, depth_n, _ = geometry.composite(mpi_n)
    color_w, depth_w, acc_w = geometry.composite(mpi_prev_warped)
    planes = np.asarray(mpi_n.plane_depths, dtype=np.float64)
    finite = planes[np.isfinite(planes)]
    ref = 2.0 / (1.0 / finite[0] + 1.0 / finite[-1]) if finite.size else 1.0
    inv_n = np.where(np.isfinite(depth_n), 1.0 / np.maximum(depth_n, 1e-30), 0.0)
    inv_w = np.where(np.isfinite(depth_w), 1.0 / np.maximum(depth_w, 1e-30), 0.0)
    diff = np.abs(encode_color(color_n) - encode_color(color_w))
    d_color = np.maximum(np.maximum(diff[..., 0], diff[..., 1]), diff[..., 2])  # max over RGB (axis=-1 is slow)
    d_depth = np.abs(inv_n - inv_w) * ref
    changed = (acc_w > 0.5) & ((d_color > color_threshold) | (d_depth > depth_threshold))
    if not erode:
        return changed
    return cv2.erode(changed.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)


def tile_counts(changed: np.ndarray, tile: int) -> np.ndarray:
    """(ceil(h / tile), ceil(w / tile)) int64: the changed pixels of each ``tile`` x ``tile`` tile of a (h, w)
    bool mask (the last row and column of tiles may be partial)."""
    h, w = changed.shape
    th, tw = math.ceil(h / tile), math.ceil(w / tile)
    padded = np.zeros((th * tile, tw * tile), dtype=np.int64)
    padded[:h, :w] = changed
    return padded.reshape(th, tile, tw, tile).sum(axis=(1, 3))


def boxes_from_counts(counts: np.ndarray, size: tuple[int, int], tile: int, tile_fraction: float, margin: int,
                      stride: int, full_frame_fraction: float, min_tiles: int = 1) -> list[Box]:
    """Boxes (y0, y1, x0, x1) the network must see, from the changed pixels per tile (``tile_counts``, or the
    GPU's ``GlGate``) of a (h, w) = ``size`` frame: moving tiles, grown by ``margin``, snapped to ``stride``.

    A tile moves when more than ``tile_fraction`` of its tile x tile pixels changed (a partial tile counts
    the pixels outside the frame as unchanged); groups of fewer than ``min_tiles`` connected moving tiles are
    dropped. Connected groups of moving tiles (after growing by the margin) give one box each; when the boxes
    cover more than ``full_frame_fraction`` of the frame the whole frame is returned instead (one network call
    is then cheaper than many). Returns [] when nothing moved.
    """
    h, w = size
    moving = np.asarray(counts).astype(np.float32) / np.float32(tile * tile) > tile_fraction
    if min_tiles > 1 and moving.any():  # drop isolated groups of moving tiles (resampling noise, not objects)
        count, labels, stats, _ = cv2.connectedComponentsWithStats(moving.astype(np.uint8), connectivity=8)
        moving = (stats[:, cv2.CC_STAT_AREA] >= min_tiles)[labels] & moving
    if not moving.any():
        return []
    grow = math.ceil(margin / tile)
    grown = cv2.dilate(moving.astype(np.uint8), np.ones((2 * grow + 1, 2 * grow + 1), np.uint8))
    count, _, stats, _ = cv2.connectedComponentsWithStats(grown, connectivity=8)
    boxes = []
    for label in range(1, count):
        x, y, bw, bh = (int(v) for v in stats[label, :4])
        y0, x0 = (y * tile) // stride * stride, (x * tile) // stride * stride
        y1 = min(h, -(-((y + bh) * tile) // stride) * stride)
        x1 = min(w, -(-((x + bw) * tile) // stride) * stride)
        boxes.append((y0, y1, x0, x1))
    if sum((b[1] - b[0]) * (b[3] - b[2]) for b in boxes) > full_frame_fraction * h * w:
        return [(0, h, 0, w)]
    return boxes


def motion_boxes(changed: np.ndarray, tile: int, tile_fraction: float, margin: int, stride: int,
                 full_frame_fraction: float, min_tiles: int = 1) -> list[Box]:
    """``boxes_from_counts`` of a (h, w) bool mask of changed pixels (``tile_counts``)."""
    return boxes_from_counts(tile_counts(changed, tile), changed.shape, tile, tile_fraction, margin, stride,
                             full_frame_fraction, min_tiles)


def gate_boxes(config: GateConfig, low_n: tuple, low_p: tuple, t_n: np.ndarray, t_p: np.ndarray,
               stride: int) -> list[Box]:
    """The gate on a frame pair at the working resolution: ``low_n`` / ``low_p`` are (colour (h, w, 3), depth
    (h, w), intrinsics) of frames n and n-k (``geometry.downsample_frame``), ``t_n`` / ``t_p`` their
    world-to-camera transforms; ``stride`` the network's. One-plane MPIs suffice to see the residual.
    Returns the boxes (``motion_boxes``), [] when nothing moved, the whole frame when the gate is off."""
    h, w = low_n[1].shape
    if not config.enabled:
        return [(0, h, 0, w)]
    g_n = geometry.build_mpi(low_n[0], low_n[1], 1)
    g_p = geometry.build_mpi(low_p[0], low_p[1], 1)
    g_w, _ = geometry.forward_warp_mpi(g_p, low_p[2], t_p, low_n[2], t_n)
    changed = motion_residual(g_n, g_w, config.color_threshold, config.depth_threshold, config.erode)
    if config.unseen and changed.any():
        changed &= geometry.seen_before(low_n[1], low_n[2], t_n, low_p[2], t_p, low_p[1].shape)
    return motion_boxes(changed, config.tile, config.tile_fraction, config.margin, stride,
                        config.full_frame_fraction, config.min_tiles)
