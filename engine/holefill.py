"""The simple disocclusion fill used by the `reproject` and `flow2d` predictors.

After a forward warp, holes appear where the new view sees surfaces the old frame did not. Those are,
almost always, background revealed behind a foreground edge, so each hole pixel copies the *farther*
(larger depth) of its nearest known neighbours to the left and right on the same row. Rows with no
known pixel are filled the same way along columns, and anything still unknown (a frame that is all
hole) takes the fallback image (the last rendered frame). Every filled pixel is a copy of a known one:
nothing is blurred or invented, and no NaN can come out.
"""
from __future__ import annotations

from typing import Optional

import numpy as np


def _nearest_known(known: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Column index of the nearest known pixel to the left and right of each pixel, per row (-1: none)."""
    h, w = known.shape
    cols = np.broadcast_to(np.arange(w), (h, w))
    left = np.maximum.accumulate(np.where(known, cols, -1), axis=1)
    right = np.minimum.accumulate(np.where(known, cols, w)[:, ::-1], axis=1)[:, ::-1]
    return left, np.where(right == w, -1, right)


def _fill_rows(color: np.ndarray, depth: np.ndarray, holes: np.ndarray) -> np.ndarray:
    """Fill hole pixels from the farther of the nearest known left/right pixels; returns filled mask."""
    left, right = _nearest_known(~holes)
    rows = np.broadcast_to(np.arange(holes.shape[0])[:, None], holes.shape)
    depth_left = np.where(left >= 0, depth[rows, np.maximum(left, 0)], -np.inf)
    depth_right = np.where(right >= 0, depth[rows, np.maximum(right, 0)], -np.inf)
    source = np.where(depth_right > depth_left, right, left)
    fill = holes & (source >= 0)
    r, c = np.nonzero(fill)
    color[r, c] = color[r, source[r, c]]
    depth[r, c] = depth[r, source[r, c]]
    return fill


def fill_holes(color: np.ndarray, depth: np.ndarray, holes: np.ndarray,
               fallback: Optional[np.ndarray] = None) -> tuple[np.ndarray, np.ndarray]:
    """Background-biased hole fill (see the module docstring).

    Args:
        color: (H, W, 3) warped colour; values under ``holes`` are ignored.
        depth: (H, W) warped planar depth (+inf for sky, which counts as the farthest background).
        holes: (H, W) bool, True where the warp left no surface.
        fallback: (H, W, 3) colour used where neither rows nor columns hold a known pixel.
    Returns:
        (color, depth) filled copies; the inputs are not modified.
    """
    color = color.copy()
    depth = depth.copy()
    remaining = holes.copy()
    if not remaining.any():
        return color, depth
    remaining &= ~_fill_rows(color, depth, remaining)
    if remaining.any():
        filled_t = _fill_rows(color.transpose(1, 0, 2), depth.T, remaining.T)
        remaining &= ~filled_t.T
    if remaining.any():
        color[remaining] = 0.0 if fallback is None else fallback[remaining]
        depth[remaining] = np.inf
    return color, depth
