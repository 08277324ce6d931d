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

from engine.geometry import kernels


def nearest_known(known: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Column index of the nearest known pixel to the left and right of each pixel, per row (-1: none)."""
    h, w = known.shape
    cols = np.broadcast_to(np.arange(w), (h, w))
    left = np.maximum.accumulate(np.where(known, cols, -1), axis=1)
    right = np.minimum.accumulate(np.where(known, cols, w)[:, ::-1], axis=1)[:, ::-1]
    return left, np.where(right == w, -1, right)


def row_sources(depth: np.ndarray, holes: np.ndarray) -> np.ndarray:
    """Per pixel, the column of the farther of its nearest known left / right pixels on the same row
    (-1: the row has no known pixel, or the pixel is known): ``engine.geometry.kernels.row_sources`` (oracle:
    ``engine.geometry.reference.row_sources_reference``)."""
    out = np.empty(holes.shape, dtype=np.int64)
    kernels.row_sources(np.ascontiguousarray(depth, dtype=np.float32), np.ascontiguousarray(holes, dtype=np.bool_),
                        out)
    return out


def fill_sources(depth: np.ndarray, holes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where each hole pixel copies from (see the module docstring): (row, column) index arrays (H, W),
    the pixel itself where it is known, -1 where neither its row nor its column holds a known pixel.

    Rows first (farther of the nearest known left / right pixels), then, for rows with no known pixel, the
    same along columns over the row-filled image; a column source that was itself row-filled resolves to
    its own source, so every source is a known pixel of the input.
    """
    h, w = holes.shape
    src_r = np.broadcast_to(np.arange(h)[:, None], (h, w)).copy()
    src_c = np.broadcast_to(np.arange(w)[None, :], (h, w)).copy()
    src_r[holes], src_c[holes] = -1, -1
    if not holes.any():
        return src_r, src_c
    cols = row_sources(depth, holes)
    filled = cols >= 0
    src_c[filled] = cols[filled]
    src_r[filled] = np.nonzero(filled)[0]
    remaining = holes & ~filled
    if remaining.any():
        row_depth = np.where(filled, depth[np.maximum(src_r, 0), np.maximum(src_c, 0)], depth)
        rows_t = row_sources(row_depth.T, remaining.T).T  # per pixel, the row of its column source
        fill = rows_t >= 0
        r, c = np.nonzero(fill)
        src_r[r, c], src_c[r, c] = src_r[rows_t[r, c], c], src_c[rows_t[r, c], c]
    return src_r, src_c


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

    Compiled: ``kernels.fill_rows`` (rows over the kernel threads), then, for holes no row source reaches (rows
    without a known pixel), ``kernels.fill_columns`` (columns over the threads). ``fill_holes_reference`` is
    the oracle, and the path for inputs of other dtypes or shapes.
    """
    h, w = holes.shape
    if color.dtype == np.float32 and depth.dtype == np.float32 and color.ndim == 3 and color.shape[:2] == (h, w) \
            and depth.shape == (h, w) and (fallback is None or np.shape(fallback) == color.shape):
        color_c, depth_c = np.ascontiguousarray(color), np.ascontiguousarray(depth)
        out_color, out_depth = np.empty_like(color_c), np.empty_like(depth_c)
        holes_c = np.ascontiguousarray(holes, dtype=np.bool_)
        remaining = np.zeros((h, w), np.bool_)  # untouched zero pages unless a row finds no source
        unfilled = kernels.run_ranges(lambda r0, r1: kernels.fill_rows(color_c, depth_c, holes_c, r0, r1, out_color,
                                                                       out_depth, remaining), kernels.split_rows(h, w))
        if sum(unfilled):
            rows = np.flatnonzero(remaining.any(axis=1))
            back = out_color if fallback is None else np.ascontiguousarray(fallback, dtype=np.float32)
            kernels.run_ranges(lambda c0, c1: kernels.fill_columns(out_color, out_depth, remaining, rows, c0, c1, back,
                                                                   fallback is not None),
                               kernels.split_rows(w, max(1, len(rows))))
        return out_color, out_depth
    return fill_holes_reference(color, depth, holes, fallback)


def fill_holes_reference(color: np.ndarray, depth: np.ndarray, holes: np.ndarray,
                         fallback: Optional[np.ndarray] = None) -> tuple[np.ndarray, np.ndarray]:
    """``fill_holes`` in numpy (rows by ``row_sources``, then columns, then the fallback): its oracle, and its
    path for colour and depth that are not float32 frames of the holes' size."""
    color = color.copy()
    depth = depth.copy()
    if not holes.any():
        return color, depth
    src_r, src_c = fill_sources(depth, holes)
    fill = holes & (src_r >= 0)
    r, c = np.nonzero(fill)
    color[r, c] = color[src_r[r, c], src_c[r, c]]
    depth[r, c] = depth[src_r[r, c], src_c[r, c]]
    remaining = holes & ~fill
    if remaining.any():
        color[remaining] = 0.0 if fallback is None else fallback[remaining]
        depth[remaining] = np.inf
    return color, depth
