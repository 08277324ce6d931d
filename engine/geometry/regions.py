"""The per-region check that an estimated motion explained the last interval, behind the fall-back to the
camera-only warp of ``mvec[fallback=true]`` (errors of 3D positions, ``rigid.hindcast_keeps``) and of
``flow2d`` / ``decomp`` with ``fallback`` (photometric errors, ``engine.predict.dis.explained_motion``).

Regions are int labels per moving pixel (M,) (``rigid.motion_components``' groups, or rigid parts).
"""
from __future__ import annotations

import numpy as np

__all__ = ["region_keeps"]


def region_keeps(regions: np.ndarray, count: int, model: np.ndarray, still: np.ndarray, valid: np.ndarray, *,
                 ratio: float = 1.0, min_share: float = 0.25) -> np.ndarray:
    """Per region, whether a motion model explained the last interval: (count,) bool.

    ``regions`` (M,) int labels in [0, count); ``model`` / ``still`` (M,) each point's error under the model
    and under no object motion (the camera-only warp), in any one unit. A region keeps its motion unless the
    model's error, summed over its ``valid`` points with finite errors, exceeds ``ratio`` times the summed
    error of no object motion; a tie keeps it. Regions with fewer than ``min_share`` of their points valid have
    no evidence and keep their motion."""
    ok = valid & np.isfinite(model) & np.isfinite(still)
    model_sum = np.bincount(regions[ok], model[ok], minlength=count)
    still_sum = np.bincount(regions[ok], still[ok], minlength=count)
    evidence = np.bincount(regions[ok], minlength=count) >= min_share * np.bincount(regions, minlength=count)
    return ~evidence | (model_sum <= ratio * still_sum)
