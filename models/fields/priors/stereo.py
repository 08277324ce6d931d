"""Dense depth for the depth prior from plane-sweep stereo between the training views, with their KNOWN poses.

Where SIFT gives tens of points on repetitive or weakly textured views (40 on a generated forward-facing rig
at 504x378), a plane sweep scores every pixel (``docs/results/2026-11-29-ff-sparse-views.md``):

1. **Sweep** (:func:`plane_sweep_ncc`): for each training view (the reference) and each other view, the other
   view's grey image is warped onto ``planes`` fronto-parallel planes of the reference, uniform in inverse
   depth between its near and far bounds (a plane at planar depth z maps pixels by the homography
   ``K_o (R + t e3^T / z) K_r^-1``; ``cv2.warpPerspective`` on pixel indices, centres at +0.5 in the
   cameras' convention), and scored by zero-mean normalised cross-correlation over ``window`` x ``window``
   patches (box filters). A patch that leaves the other image scores -1. The score of a plane is the best
   over the other views, so a pixel hidden in one of them can still be matched in another.
2. **Winner** (:func:`sweep_depth`): the best plane, refined by a parabola through its neighbours' scores (in
   inverse depth). A pixel keeps its depth only if the score reaches ``min_ncc``, the peak is not at either
   end of the sweep (no bound, e.g. the sky), it is unique (every plane more than two planes away scores at
   least ``min_margin`` lower) and the patch is textured (grey standard deviation >= ``min_texture``). An other
   view votes on a patch only where at least ``min_epipolar`` of the patch's gradient runs along that view's
   epipolar lines (:func:`epipolar_share`: an edge along them matches at every depth, the aperture problem).
3. **Geometric consistency** (:func:`consistent_depth_points`): a depth is kept only if, projected into
   another view and back with that view's own depth, it lands within ``max_error`` pixels of where it
   started and within ``max_depth_change`` (relative) of its depth, as multi-view stereo filters depths
   (COLMAP's geometric consistency). At most ``max_points`` per view (a fixed-seed draw) are kept.

The points feed the sparse depth prior's loss (``sift_depth``) exactly as SIFT's triangulated matches do.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Sequence

import cv2
import numpy as np

from engine.core.colorspace import display_encode
from engine.core.checks import check_range
from engine.core.errors import InputError
from engine.geometry import reproject
from engine.geometry.camera import reprojection_matrix, reproject_points

__all__ = ["StereoDepth", "plane_depths_inverse", "plane_homography", "plane_sweep_ncc", "sweep_depth",
           "epipolar_share", "consistent_depth_points"]


@dataclass
class StereoDepth:
    """Settings of the plane-sweep stereo depth (the depth prior's ``stereo`` source)."""

    planes: int = field(default=96, metadata={"help": "plane-sweep planes, uniform in inverse depth"})
    window: int = field(default=7, metadata={"help": "NCC patch side (odd)"})
    min_ncc: float = field(default=0.9, metadata={"help": "keep a depth only where its NCC reaches this"})
    min_margin: float = field(default=0.1, metadata={
        "help": "keep a depth only where every plane more than 2 planes from the peak scores at least this much "
                "lower (a unique peak: not a smooth sky, a repeated pattern or a blank wall)"})
    min_texture: float = field(default=0.02, metadata={
        "help": "keep a depth only where the patch's grey standard deviation (display-encoded, 0-1) reaches this"})
    min_epipolar: float = field(default=0.5, metadata={
        "help": "another view votes on a patch only where at least this share of the patch's grey gradient runs "
                "along its epipolar lines (an edge along them matches at every depth: the aperture problem)"})
    max_error: float = field(default=1.0, metadata={
        "help": "geometric consistency: at most this many pixels from the start after a round trip"})
    max_depth_change: float = field(default=0.02, metadata={
        "help": "geometric consistency: at most this relative depth change after a round trip"})
    max_points: int = field(default=20000, metadata={"help": "points kept per view at most (fixed-seed draw)"})

    def validate(self) -> "StereoDepth":
        """Raise InputError naming the first bad option; returns self."""
        check_range(self.planes, "priors.depth.stereo.planes", low=3, integer=True)
        if self.window < 3 or self.window % 2 == 0:
            raise InputError(f"must be odd and >= 3, got {self.window}", field="priors.depth.stereo.window")
        check_range(self.min_ncc, "priors.depth.stereo.min_ncc", low=-1, high=1)
        check_range(self.min_epipolar, "priors.depth.stereo.min_epipolar", low=0, high=1)
        for name in ("min_texture", "max_error", "max_depth_change"):
            check_range(getattr(self, name), f"priors.depth.stereo.{name}", low=0)
        check_range(self.max_points, "priors.depth.stereo.max_points", low=1, integer=True)
        return self


def plane_homography(cam_ref, cam_other, depth: float) -> np.ndarray:
    """(3, 3) float64 map from reference pixels to the other view's pixels (continuous coordinates, centres at
    +0.5) of the fronto-parallel plane at planar ``depth`` in the reference (``inf``: the plane at infinity)."""
    rel = np.asarray(cam_other.world_to_camera, np.float64) @ np.linalg.inv(
        np.asarray(cam_ref.world_to_camera, np.float64))
    rot, t = rel[:3, :3], rel[:3, 3]
    plane = rot if np.isinf(depth) else rot + np.outer(t, [0.0, 0.0, 1.0 / depth])
    return np.asarray(cam_other.intrinsics, np.float64) @ plane @ np.linalg.inv(np.asarray(cam_ref.intrinsics,
                                                                                           np.float64))


def plane_depths_inverse(near: float, far: float, num_planes: int) -> np.ndarray:
    """(D,) planar depths uniform in inverse depth from ``near`` to ``far`` (far = inf gives +inf last): the
    planes of this sweep and of ViP's (``priors/vip.py``)."""
    disparity = np.linspace(1.0 / near, 0.0 if np.isinf(far) else 1.0 / far, num_planes)
    with np.errstate(divide="ignore"):
        return np.where(disparity > 0, 1.0 / np.where(disparity > 0, disparity, 1.0), np.inf)


_HALF = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
_MINUS_HALF = np.array([[1.0, 0.0, -0.5], [0.0, 1.0, -0.5], [0.0, 0.0, 1.0]])


def _box(x: np.ndarray, window: int) -> np.ndarray:
    return cv2.boxFilter(x, -1, (window, window), normalize=True, borderType=cv2.BORDER_REFLECT)


def plane_sweep_ncc(ref: np.ndarray, others: Sequence[np.ndarray], cam_ref, cam_others: Sequence,
                    depths: np.ndarray, window: int = 7, usable: Optional[Sequence[np.ndarray]] = None) -> np.ndarray:
    """NCC of the reference's patches against each other view warped onto each plane, the best over views.

    Args:
        ref: (H, W) float32 grey reference image.
        others: (H', W') float32 grey images of the other views.
        cam_ref, cam_others: their cameras (``intrinsics``, ``world_to_camera``).
        depths: (D,) planar depths of the planes in the reference (may hold inf).
        window: odd patch side.
        usable: optional (H, W) bool per other view: where that view may vote (elsewhere it scores -1).

    Returns:
        (D, H, W) float32 scores in [-1, 1]; -1 where a patch leaves every other image (or no view may vote).
    """
    if ref.ndim != 2 or not others or any(o.ndim != 2 for o in others) or len(others) != len(cam_others):
        raise InputError("need a (H, W) reference and one (H', W') image per other camera", field="stereo")
    h, w = ref.shape
    ref = ref.astype(np.float32)
    mu_r = _box(ref, window)
    var_r = np.maximum(_box(ref * ref, window) - mu_r * mu_r, 0.0)
    scores = np.full((len(depths), h, w), -1.0, np.float32)
    for k, (other, cam) in enumerate(zip(others, cam_others)):
        other = other.astype(np.float32)
        votes = None if usable is None else np.asarray(usable[k], bool)
        ones = np.ones_like(other)
        for d, z in enumerate(depths):
            m = _MINUS_HALF @ plane_homography(cam_ref, cam, float(z)) @ _HALF  # on pixel indices
            # WARP_INVERSE_MAP: m maps the output (reference) pixels to the input (other) pixels
            warped = cv2.warpPerspective(other, m, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                         borderValue=0.0)
            inside = cv2.warpPerspective(ones, m, (w, h), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                                         borderValue=0.0)
            mu_o = _box(warped, window)
            var_o = np.maximum(_box(warped * warped, window) - mu_o * mu_o, 0.0)
            cov = _box(ref * warped, window) - mu_r * mu_o
            ncc = cov / np.sqrt(var_r * var_o + 1e-8)
            ncc = np.where(_box(inside, window) > 0.999, ncc, -1.0)
            if votes is not None:
                ncc = np.where(votes, ncc, -1.0)
            np.maximum(scores[d], ncc, out=scores[d])
    return scores


def sweep_depth(scores: np.ndarray, depths: np.ndarray, ref: np.ndarray, config: StereoDepth
                ) -> tuple[np.ndarray, np.ndarray]:
    """The winning depth of a sweep (:func:`plane_sweep_ncc`) refined between planes, and where it holds.

    Returns:
        depth (H, W) float64 planar depth (NaN where rejected) and its score (H, W) float32.
    """
    num = len(depths)
    best = np.argmax(scores, axis=0)
    rows, cols = np.indices(best.shape)
    peak = scores[best, rows, cols]
    interior = (best > 0) & (best < num - 1)
    lo = scores[np.maximum(best - 1, 0), rows, cols]
    hi = scores[np.minimum(best + 1, num - 1), rows, cols]
    curve = lo - 2.0 * peak + hi
    shift = np.where(interior & (curve < 0), 0.5 * (lo - hi) / np.where(curve < 0, curve, -1.0), 0.0)
    disparity = 1.0 / np.asarray(depths, np.float64)                  # uniform steps (0 at infinity)
    step = disparity[1] - disparity[0]
    refined = disparity[best] + np.clip(shift, -0.5, 0.5) * step
    ref = ref.astype(np.float32)
    mu = _box(ref, config.window)
    texture = np.sqrt(np.maximum(_box(ref * ref, config.window) - mu * mu, 0.0))
    second = np.full(best.shape, -1.0, np.float32)
    for d in range(num):   # the best score more than 2 planes from the peak (a loop: no (D, H, W) temporary)
        np.maximum(second, np.where(np.abs(best - d) > 2, scores[d], -1.0), out=second)
    keep = (interior & (peak >= config.min_ncc) & (peak - second >= config.min_margin)
            & (texture >= config.min_texture) & (refined > 0))
    depth = np.where(keep, 1.0 / np.where(refined > 0, refined, 1.0), np.nan)
    return depth, peak


def epipolar_share(grey: np.ndarray, cam, other, window: int) -> np.ndarray:
    """(H, W) the share of each patch's grey gradient along the epipolar lines of ``other`` in this view:
    ``box(|g_x e_x| + |g_y e_y|) / box(|g_x| + |g_y|)`` with e the unit direction from the epipole (the other
    camera's centre projected into this view) to the pixel; 0 on a blank patch. Near 0, the patch is an edge
    along the lines and matches the other view at every depth (the aperture problem)."""
    h, w = grey.shape
    gx = np.abs(cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3))
    gy = np.abs(cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3))
    total = _box(gx + gy, window)
    u, v = np.meshgrid(np.arange(w, dtype=np.float64) + 0.5, np.arange(h, dtype=np.float64) + 0.5)
    proj = np.asarray(cam.intrinsics, np.float64) @ np.asarray(cam.world_to_camera, np.float64)[:3]
    e = proj @ np.append(np.asarray(other.position, np.float64), 1.0)
    ex, ey = u * e[2] - e[0], v * e[2] - e[1]   # from the epipole to the pixel, up to the sign of e[2]
    norm = np.maximum(np.hypot(ex, ey), 1e-12)
    along = _box((gx * np.abs(ex / norm) + gy * np.abs(ey / norm)).astype(np.float32), window)
    return np.where(total > 1e-6, along / np.maximum(total, 1e-6), 0.0).astype(np.float32)


def _grey(image: np.ndarray) -> np.ndarray:
    return display_encode(np.clip(image, 0.0, 1.0)).astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)


def consistent_depth_points(views, config: StereoDepth, seed: int = 0):
    """Plane-sweep depths of every training view that survive the geometric consistency check (module doc).

    Args:
        views: :class:`~models.fields.data.views.Views` (at least two) with ``near_far`` bounds.

    Returns:
        ``(view, xy, depth, error)``: (P,) int64, (P, 2) pixel centres, (P,) planar depth, (P,) round-trip error
        in pixels (the smallest over the views that confirm it).
    """
    config.validate()
    n = len(views)
    if n < 2:
        return np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0), np.zeros(0)
    greys = [_grey(image) for image in views.images]
    maps = []
    for i in range(n):
        depths = plane_depths_inverse(float(views.near_far[i, 0]), float(views.near_far[i, 1]), config.planes)
        others = [j for j in range(n) if j != i]
        usable = [epipolar_share(greys[i], views.cameras[i], views.cameras[j], config.window) >= config.min_epipolar
                  for j in others]
        scores = plane_sweep_ncc(greys[i], [greys[j] for j in others], views.cameras[i],
                                 [views.cameras[j] for j in others], depths, config.window, usable)
        maps.append(sweep_depth(scores, depths, greys[i], config)[0])
    rng = np.random.default_rng(seed)
    view_l, xy_l, depth_l, err_l = [], [], [], []
    for i in range(n):
        depth_i = maps[i]
        finite = np.isfinite(depth_i)
        best_err = np.full(depth_i.shape, np.inf)
        for j in range(n):
            if j == i:
                continue
            err = _round_trip_error(depth_i, maps[j], views.cameras[i], views.cameras[j], config.max_depth_change)
            best_err = np.minimum(best_err, err)
        keep = finite & (best_err <= config.max_error)
        ys, xs = np.nonzero(keep)
        if len(ys) > config.max_points:
            pick = np.sort(rng.choice(len(ys), config.max_points, replace=False))
            ys, xs = ys[pick], xs[pick]
        view_l.append(np.full(len(ys), i, np.int64))
        xy_l.append(np.stack([xs + 0.5, ys + 0.5], axis=-1).astype(np.float64))
        depth_l.append(depth_i[ys, xs].astype(np.float64))
        err_l.append(best_err[ys, xs].astype(np.float64))
    return np.concatenate(view_l), np.concatenate(xy_l), np.concatenate(depth_l), np.concatenate(err_l)


def _round_trip_error(depth_i: np.ndarray, depth_j: np.ndarray, cam_i, cam_j, max_depth_change: float) -> np.ndarray:
    """(H, W) pixels between each pixel centre of view i and where its depth, projected into view j and back from
    the pixel it lands in (its centre, at view j's depth there), lands in view i; inf where either depth is
    missing or a depth changes by more than ``max_depth_change`` (relative) on the way."""
    h, w = depth_i.shape
    hj, wj = depth_j.shape
    has = np.isfinite(depth_i)
    uv, z, valid = reproject(np.where(has, depth_i, 1.0).astype(np.float32), cam_i.intrinsics,
                             cam_i.world_to_camera, cam_j.intrinsics, cam_j.world_to_camera)
    col = np.floor(uv[..., 0]).astype(np.int64)
    row = np.floor(uv[..., 1]).astype(np.int64)
    ok = valid & has & (col >= 0) & (col < wj) & (row >= 0) & (row < hj)
    dj = np.where(ok, depth_j[np.clip(row, 0, hj - 1), np.clip(col, 0, wj - 1)], np.nan)
    ok &= np.isfinite(dj) & (np.abs(dj - z) <= max_depth_change * z)
    matrix = reprojection_matrix(*(np.asarray(m, np.float64) for m in (cam_j.intrinsics, cam_j.world_to_camera,
                                                                       cam_i.intrinsics, cam_i.world_to_camera)))
    bu, bv, bz, bvalid = reproject_points((col + 0.5).reshape(-1).astype(np.float32),
                                          (row + 0.5).reshape(-1).astype(np.float32),
                                          np.where(ok, dj, 1.0).reshape(-1).astype(np.float32), matrix)
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    err = np.hypot(bu.reshape(h, w) - u, bv.reshape(h, w) - v)
    scale = max_depth_change * np.where(has, depth_i, 1.0)
    ok &= bvalid.reshape(h, w) & (np.abs(bz.reshape(h, w) - depth_i) <= scale)
    return np.where(ok, err, np.inf)
