"""Sparse depth prior (DS-NeRF; thesis Eq. 3.13) from SIFT matches triangulated with the KNOWN poses (and, with
``source`` stereo or sift+stereo, from plane-sweep stereo between the training views: ``priors/stereo.py``).

Pipeline (once per run, cached in the run directory):

1. SIFT keypoints and descriptors of every training view (``pycolmap``'s CPU extractor, on the
   display-encoded grey image in [0, 1]); keypoint coordinates are COLMAP's, whose pixel centres are at
   +0.5, i.e. already the project's continuous pixel coordinates (``engine/core/frames.py``).
2. Mutual nearest-neighbour matches with Lowe's ratio test (:func:`match_descriptors`: COLMAP's CPU matcher,
   brute force in numpy) between every pair of training views. No pose is estimated: the poses are the views' own.
3. Linear (DLT) triangulation of each match from the two OpenCV cameras ``P = K [R | t]``
   (:func:`triangulate_dlt`, float64), kept only if it lies in front of both cameras and reprojects within
   ``max_reprojection_error`` pixels in both (:func:`reprojection_errors`, with ``engine.geometry.project``).
4. Each kept match gives two supervised pixels: (view a, x_a, planar depth of the point in a) and the same
   in view b.

The loss term ``sift_depth`` renders an extra batch of ``rays`` rays through randomly drawn keypoints (their
exact sub-pixel positions) and takes ``mean |sum_i w_i t_i - z| / scale``: the expected planar depth
against the triangulated one, normalised by the scene's depth scale (:func:`scene_depth_scale`); for
forward-facing scenes the same in disparity, ``mean |sum_i w_i near / t_i - near / z|``. An L1
rather than Eq. 3.13's square, so a few wrong matches cannot dominate. Matches seen under less than
``min_triangulation_angle`` degrees are dropped (their depth is unknown, e.g. the sky). Views without a match contribute no
points; with no points at all the prior warns once and adds a zero loss.
"""
from __future__ import annotations

import hashlib
import json
import os
import warnings
import zipfile
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from engine.core.colorspace import display_encode
from engine.core.errors import InputError
from engine.geometry import project
from models.fields.components.render import module_device
from models.fields.losses import LossInputs, register_loss_term
from models.fields.priors.stereo import StereoDepth, consistent_depth_points

__all__ = ["SparseDepthPrior", "SparseDepthPoints", "projection_matrix", "triangulate_dlt", "reprojection_errors",
           "triangulate_checked", "CACHE_ENV", "feature_cache_dir", "sift_features", "MAX_DESCRIPTOR_ANGLE",
           "match_descriptors", "match_views", "sparse_depth_points", "load_or_compute_sparse_depth", "keypoint_rays",
           "scene_depth_scale", "SparseDepthState", "triangulation_angles", "DEPTH_SOURCES",
           "AUTO_SOURCES", "depth_source"]


@dataclass
class SparseDepthPrior:
    """DS-NeRF sparse depth from SIFT matches triangulated with the known poses."""

    enabled: bool = field(default=False, metadata={"help": "use the SIFT sparse-depth prior (loss sift_depth)"})
    weight: float = field(default=0.1, metadata={"help": "weight of mean |expected depth - z| / depth scale"})
    rays: int = field(default=256, metadata={"help": "keypoint rays rendered per step for the depth loss"})
    max_reprojection_error: float = field(default=2.0, metadata={
        "help": "keep a triangulated match only if it reprojects within this many pixels in both views"})
    min_triangulation_angle: float = field(default=1.0, metadata={
        "help": "keep a match only if the two viewing rays meet at this angle (degrees) or more: below it the "
                "depth is poorly constrained (COLMAP's default is 1.5)"})
    ratio: float = field(default=0.8, metadata={"help": "Lowe ratio test of the SIFT matcher"})
    max_features: int = field(default=8192, metadata={"help": "SIFT features per view at most"})
    start_step: int = field(default=0, metadata={"help": "first step at which the depth loss is applied"})
    source: str = field(default="auto", metadata={
        "help": "where the depth points come from: sift (triangulated matches), stereo (plane-sweep stereo between "
                "the training views, models/fields/priors/stereo.py), sift+stereo, or auto: sift+stereo for "
                "forward-facing scenes, sift for bounded ones (AUTO_SOURCES, "
                "docs/results/2026-11-29-ff-sparse-views.md)"})
    stereo: StereoDepth = field(default_factory=StereoDepth, metadata={"help": "the plane-sweep stereo's settings"})


@dataclass
class SparseDepthPoints:
    """Pixels with a triangulated depth.

    Attributes:
        view: (P,) int64 training-view index.
        xy: (P, 2) float64 continuous pixel coordinates (pixel centres at +0.5).
        depth: (P,) float64 planar depth in that view.
        error: (P,) float64 reprojection error (pixels) of the match's point in that view.
        matches: number of raw SIFT matches per pair, ``{"a-b": n}``, and the stereo points, ``{"stereo": n}``.
    """

    view: np.ndarray
    xy: np.ndarray
    depth: np.ndarray
    error: np.ndarray
    matches: dict[str, int]

    def __len__(self) -> int:
        return int(self.view.shape[0])


def projection_matrix(intrinsics: np.ndarray, world_to_camera: np.ndarray) -> np.ndarray:
    """``P = K [R | t]`` (3, 4) of an OpenCV camera: world points -> homogeneous pixel coordinates (+0.5
    centres)."""
    return np.asarray(intrinsics, np.float64) @ np.asarray(world_to_camera, np.float64)[:3, :]


def triangulate_dlt(projections: np.ndarray, points: np.ndarray, observed: Optional[np.ndarray] = None) -> np.ndarray:
    """Linear (DLT) triangulation of M points seen in V views.

    Each observation (x, y) of view v adds the rows ``x P_v[2] - P_v[0]`` and ``y P_v[2] - P_v[1]``; each row
    is scaled to unit norm (equal say for every view) and the point is the right singular vector of the
    smallest singular value, in float64.

    Args:
        projections: (V, 3, 4) camera matrices (:func:`projection_matrix`).
        points: (M, V, 2) pixel coordinates.
        observed: (M, V) bool, which views see each point (default: all); at least two per point.

    Returns:
        (M, 3) world points (NaN for points with fewer than two observations or at infinity).

    >>> k = np.array([[100.0, 0, 50], [0, 100, 50], [0, 0, 1]]); t2 = np.eye(4); t2[0, 3] = -1.0
    >>> p = np.stack([projection_matrix(k, np.eye(4)), projection_matrix(k, t2)])
    >>> triangulate_dlt(p, np.array([[[50.0, 50.0], [30.0, 50.0]]])).round(6).tolist()
    [[0.0, 0.0, 5.0]]
    """
    projections = np.asarray(projections, np.float64)
    points = np.asarray(points, np.float64)
    m, v = points.shape[:2]
    observed = np.ones((m, v), bool) if observed is None else np.asarray(observed, bool)
    rows_x = points[..., 0:1] * projections[None, :, 2, :] - projections[None, :, 0, :]  # (M, V, 4)
    rows_y = points[..., 1:2] * projections[None, :, 2, :] - projections[None, :, 1, :]
    a = np.stack([rows_x, rows_y], axis=2)  # (M, V, 2, 4)
    norm = np.linalg.norm(a, axis=-1, keepdims=True)
    a = np.where(norm > 0, a / np.where(norm > 0, norm, 1.0), 0.0) * observed[:, :, None, None]
    a = a.reshape(m, 2 * v, 4)
    if m == 0:
        return np.zeros((0, 3))
    _, _, vt = np.linalg.svd(a)
    x = vt[:, -1, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        world = x[:, :3] / x[:, 3:4]
    bad = (observed.sum(axis=1) < 2) | (np.abs(x[:, 3]) < 1e-12)
    world[bad] = np.nan
    return world


def reprojection_errors(world: np.ndarray, cameras: Sequence, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reprojection error (pixels) and planar depth of world points (M, 3) in each camera.

    Args:
        world: (M, 3) points (NaN rows give inf errors).
        cameras: V cameras (``intrinsics``, ``world_to_camera``).
        points: (M, V, 2) observed pixel coordinates.

    Returns:
        error (M, V) (inf where the point is behind / on the camera plane or NaN), depth (M, V) (0 there).
    """
    m = world.shape[0]
    ok_world = np.isfinite(world).all(axis=1)
    homog = np.concatenate([np.where(ok_world[:, None], world, 0.0), np.ones((m, 1))], axis=1)
    errors, depths = np.full((m, len(cameras)), np.inf), np.zeros((m, len(cameras)))
    for v, cam in enumerate(cameras):
        cam_points = homog @ np.asarray(cam.world_to_camera, np.float64).T
        uv, z, valid = project(cam_points.astype(np.float64), cam.intrinsics)
        valid = valid & ok_world
        err = np.linalg.norm(uv - points[:, v], axis=-1)
        errors[:, v] = np.where(valid, err, np.inf)
        depths[:, v] = np.where(valid, cam_points[:, 2], 0.0)
    return errors, depths


def triangulation_angles(world: np.ndarray, cameras: Sequence) -> np.ndarray:
    """(M,) largest angle (degrees) between the viewing rays of any two of ``cameras`` at each world point
    (M, 3); 0 for a point at a camera centre."""
    rays = []
    for c in cameras:
        centre = -np.asarray(c.world_to_camera, np.float64)[:3, :3].T @ np.asarray(c.world_to_camera)[:3, 3]
        d = world - centre
        rays.append(d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-300))
    best = np.zeros(world.shape[0])
    for i in range(len(rays)):
        for j in range(i + 1, len(rays)):
            cos = np.clip((rays[i] * rays[j]).sum(-1), -1.0, 1.0)
            best = np.maximum(best, np.degrees(np.arccos(cos)))
    return best


def triangulate_checked(cameras: Sequence, points: np.ndarray, max_error: float = 2.0,
                        min_angle: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangulate correspondences seen in every one of ``cameras`` and reject the bad ones.

    Args:
        cameras: V known cameras.
        points: (M, V, 2) pixel coordinates (pixel centres at +0.5).
        max_error: largest reprojection error (pixels) allowed in every view.
        min_angle: smallest triangulation angle (degrees, :func:`triangulation_angles`): with narrow
            baselines a point far away reprojects well at almost any depth, so the angle, not the
            reprojection error, says whether its depth is known.

    Returns:
        keep (M,) bool (in front of every camera, within ``max_error`` everywhere and seen at ``min_angle``
        or more), planar depth (M, V) and reprojection error (M, V) of each point in each view.
    """
    proj = np.stack([projection_matrix(c.intrinsics, c.world_to_camera) for c in cameras])
    world = triangulate_dlt(proj, points)
    errors, depths = reprojection_errors(world, cameras, points)
    keep = (errors < max_error).all(axis=1) & (depths > 0).all(axis=1)
    if min_angle > 0:
        keep &= triangulation_angles(world, cameras) >= min_angle
    return keep, depths, errors


def _extractor(max_features: int):
    import pycolmap

    options = pycolmap.FeatureExtractionOptions()
    options.num_threads = 1
    options.sift.max_num_features = int(max_features)
    return pycolmap.FeatureExtractor.create(options, pycolmap.Device.cpu)


#: Environment variable naming the folder of the per-view SIFT cache (default ``~/.cache/interleave/sift``;
#: an empty value switches the cache off).
CACHE_ENV = "INTERLEAVE_SIFT_CACHE"


def feature_cache_dir() -> Optional[Path]:
    """Where :func:`sift_features` keeps each view's features: ``$INTERLEAVE_SIFT_CACHE``, else
    ``~/.cache/interleave/sift``; None when the variable is set empty."""
    value = os.environ.get(CACHE_ENV)
    if value is not None:
        return Path(value) if value else None
    return Path.home() / ".cache" / "interleave" / "sift"


def sift_features(images: np.ndarray, max_features: int = 8192, *, cache_dir: Optional[Path] = None
                  ) -> list[tuple[np.ndarray, np.ndarray]]:
    """SIFT of (N, H, W, 3) linear-RGB images: per view (xy (M, 2) float64, descriptors (M, 128) uint8,
    COLMAP's: L2-normalised to 512 and rounded).

    Features are taken on the display-encoded grey image in [0, 1] (``pycolmap``'s CPU extractor); ``xy`` are
    continuous pixel coordinates (pixel centres at +0.5, COLMAP's convention and the project's). With
    ``cache_dir`` each view's features are kept there under the SHA-1 of its grey image, ``max_features``
    and the pycolmap version: a view is extracted once whatever run, prior or pair uses it.
    """
    import pycolmap

    extractor = None
    out = []
    for image in images:
        grey = np.ascontiguousarray(np.clip(display_encode(image).mean(axis=-1), 0.0, 1.0).astype(np.float32))
        cached = None
        if cache_dir is not None:
            digest = hashlib.sha1(grey.tobytes())
            digest.update(f"{grey.shape} {int(max_features)} {pycolmap.__version__}".encode())
            cached = Path(cache_dir) / f"{digest.hexdigest()}.npz"
            if cached.is_file():
                try:
                    with np.load(cached) as data:
                        out.append((data["xy"], data["descriptors"]))
                    continue
                except (OSError, ValueError, KeyError, zipfile.BadZipFile):  # a damaged entry: extract again
                    pass
        extractor = extractor or _extractor(max_features)
        keypoints, descriptors = extractor.extract_from_float32_array(grey)
        xy = np.array([[kp.x, kp.y] for kp in keypoints], np.float64).reshape(-1, 2)
        features = (xy, np.asarray(descriptors.data, np.uint8).reshape(-1, 128))
        if cached is not None:
            cached.parent.mkdir(parents=True, exist_ok=True)
            partial = cached.with_suffix(f".{os.getpid()}.tmp.npz")
            np.savez(partial, xy=features[0], descriptors=features[1])
            os.replace(partial, cached)  # whole files only, also with two runs at once
        out.append(features)
    return out


#: COLMAP's SIFT matching defaults: the largest angle (radians) between matched descriptors.
MAX_DESCRIPTOR_ANGLE = 0.7


def match_descriptors(da: np.ndarray, db: np.ndarray, ratio: float = 0.8,
                      max_angle: float = MAX_DESCRIPTOR_ANGLE) -> np.ndarray:
    """Mutual nearest-neighbour matches of two sets of SIFT descriptors ((Na, 128), (Nb, 128) uint8, COLMAP's)
    with Lowe's ratio test: ``(K, 2)`` int64 index pairs, sorted by the first index.

    COLMAP's CPU matcher (``pycolmap.FeatureMatcher`` with cross check, its test oracle), brute force: the
    angle between two descriptors is ``arccos(a . b / 512^2)``; a's best match j (smallest angle) is kept
    when that angle is at most ``max_angle`` and below ``ratio`` times the second smallest, and when a is in
    turn j's best match under the same test. The dot products of uint8 descriptors are integers below
    2^24, exact in float32 (one matrix product; 7x faster than pycolmap's matcher on a rig's 1448 pairs,
    ``docs/results/2026-11-28-flow-prior-cost.md``).
    """
    if len(da) == 0 or len(db) == 0:
        return np.zeros((0, 2), np.int64)
    dots = np.asarray(da, np.float32) @ np.asarray(db, np.float32).T

    def best(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each row's best column and whether it passes the distance and ratio tests."""
        if d.shape[1] == 1:
            top, values = np.zeros((d.shape[0], 1), np.int64), d
        else:
            top = np.argpartition(-d, 1, axis=1)[:, :2]
            values = np.take_along_axis(d, top, axis=1)
            swap = values[:, 1] > values[:, 0]
            top[swap], values[swap] = top[swap, ::-1], values[swap, ::-1]
        angles = np.arccos(np.minimum(values.astype(np.float64) / (512.0 * 512.0), 1.0))
        ok = angles[:, 0] <= max_angle
        if angles.shape[1] > 1:
            ok &= angles[:, 0] < ratio * angles[:, 1]
        return top[:, 0], ok

    ab, ok_ab = best(dots)
    ba, ok_ba = best(dots.T)
    i = np.flatnonzero(ok_ab)
    j = ab[i]
    keep = ok_ba[j] & (ba[j] == i)
    return np.stack([i[keep], j[keep]], axis=1).astype(np.int64)


def match_views(features, ratio: float = 0.8) -> dict[tuple[int, int], np.ndarray]:
    """Mutual nearest-neighbour SIFT matches with a ratio test between every pair (a < b) of views
    (:func:`match_descriptors`): ``{(a, b): (K, 2) int indices into a's and b's keypoints}``."""
    return {(a, b): match_descriptors(features[a][1], features[b][1], ratio)
            for a in range(len(features)) for b in range(a + 1, len(features))}


#: The depth prior's point sources (``SparseDepthPrior.source``).
DEPTH_SOURCES = ("auto", "sift", "stereo", "sift+stereo")
#: What ``auto`` uses per scene type, from the ablation of 2026-11-29 (one seed each): stereo points added
#: +0.3 to +2.0 dB on three generated forward-facing rigs (3 views, 504x378); on lego (4 views 19-156 degrees
#: apart, 100x100) they cost 2.4 dB, on Beer (bounded, 3 views) they added 0.2-0.6.
AUTO_SOURCES = {"forward-facing": "sift+stereo", "bounded-360": "sift"}


def depth_source(prior: SparseDepthPrior, scene_type: str) -> str:
    """The point source a run uses: ``prior.source``, or for ``auto`` the one :data:`AUTO_SOURCES` gives."""
    if prior.source not in DEPTH_SOURCES:
        raise InputError(f"must be one of {DEPTH_SOURCES}, got {prior.source!r}", field="priors.depth.source")
    return AUTO_SOURCES.get(scene_type, "sift") if prior.source == "auto" else prior.source


def sparse_depth_points(views, prior: SparseDepthPrior) -> SparseDepthPoints:
    """The depth points of ``views`` (a :class:`~models.fields.data.views.Views`) from ``prior.source``:
    triangulated SIFT matches (the module doc), plane-sweep stereo (:mod:`models.fields.priors.stereo`) or both."""
    source = depth_source(prior, views.scene_type)
    view_l, xy_l, depth_l, err_l, counts = [], [], [], [], {}
    if "stereo" in source:
        for part, values in zip((view_l, xy_l, depth_l, err_l), consistent_depth_points(views, prior.stereo)):
            part.append(values)
        counts["stereo"] = int(len(view_l[0]))
    if "sift" in source:
        _sift_points(views, prior, view_l, xy_l, depth_l, err_l, counts)
    cat = (lambda parts, shape: np.concatenate(parts) if parts else np.zeros(shape))
    return SparseDepthPoints(cat(view_l, (0,)).astype(np.int64), cat(xy_l, (0, 2)), cat(depth_l, (0,)),
                             cat(err_l, (0,)), counts)


def _sift_points(views, prior: SparseDepthPrior, view_l, xy_l, depth_l, err_l, counts) -> None:
    features = sift_features(views.images, prior.max_features, cache_dir=feature_cache_dir())
    pairs = match_views(features, prior.ratio)
    for (a, b), idx in pairs.items():
        counts[f"{a}-{b}"] = int(len(idx))
        if len(idx) == 0:
            continue
        obs = np.stack([features[a][0][idx[:, 0]], features[b][0][idx[:, 1]]], axis=1)  # (K, 2, 2)
        keep, depths, errors = triangulate_checked([views.cameras[a], views.cameras[b]], obs,
                                                   prior.max_reprojection_error, prior.min_triangulation_angle)
        for slot, v in enumerate((a, b)):
            view_l.append(np.full(int(keep.sum()), v, np.int64))
            xy_l.append(obs[keep, slot])
            depth_l.append(depths[keep, slot])
            err_l.append(errors[keep, slot])


def _fingerprint(views, prior: SparseDepthPrior) -> dict[str, Any]:
    digest = hashlib.sha1(np.ascontiguousarray(views.images, np.float32).tobytes())
    for cam in views.cameras:
        digest.update(np.asarray(cam.intrinsics, np.float64).tobytes())
        digest.update(np.asarray(cam.world_to_camera, np.float64).tobytes())
    import pycolmap

    params = {k: v for k, v in asdict(prior).items() if k in ("max_reprojection_error", "ratio", "max_features",
                                                                 "min_triangulation_angle")}
    source = depth_source(prior, views.scene_type)
    if source != "sift":   # the key of a SIFT-only cache is the one it always was
        params.update(source=source, stereo=asdict(prior.stereo))
    return {"views": list(views.names), "size": [views.height, views.width], "sha1": digest.hexdigest(),
            "pycolmap": pycolmap.__version__, **params}


def load_or_compute_sparse_depth(views, prior: SparseDepthPrior, cache_dir: Optional[str | Path]) -> SparseDepthPoints:
    """:func:`sparse_depth_points`, cached as ``sparse_depth.npz`` + ``sparse_depth.json`` (the parameters
    and a hash of the images and cameras that made it) in ``cache_dir``; recomputed when they differ."""
    key = _fingerprint(views, prior)
    if cache_dir is not None:
        meta_file, data_file = Path(cache_dir) / "sparse_depth.json", Path(cache_dir) / "sparse_depth.npz"
        if meta_file.is_file() and data_file.is_file():
            meta = json.loads(meta_file.read_text())
            if meta.get("key") == key:
                data = np.load(data_file)
                return SparseDepthPoints(data["view"], data["xy"], data["depth"], data["error"], meta["matches"])
    points = sparse_depth_points(views, prior)
    if cache_dir is not None:
        Path(cache_dir).mkdir(parents=True, exist_ok=True)
        np.savez(data_file, view=points.view, xy=points.xy, depth=points.depth, error=points.error)
        per_view = np.bincount(points.view, minlength=len(views)).tolist()
        meta_file.write_text(json.dumps({"key": key, "matches": points.matches, "points": len(points),
                                         "points_per_view": per_view}, indent=2) + "\n")
    return points


def keypoint_rays(cameras: Sequence, view: np.ndarray, xy: np.ndarray) -> tuple[Tensor, Tensor]:
    """Rays through continuous pixel positions: origins (P, 3), directions (P, 3) with camera z = 1
    (``d = R^T K^-1 [x, y, 1]``, as :func:`~models.fields.components.sampling.camera_rays` for pixel centres)."""
    origins = np.zeros((len(view), 3))
    dirs = np.zeros((len(view), 3))
    for v in np.unique(view):
        sel = view == v
        cam = cameras[int(v)]
        rot = np.asarray(cam.world_to_camera, np.float64)[:3, :3]
        pix = np.concatenate([xy[sel], np.ones((int(sel.sum()), 1))], axis=1)
        dirs[sel] = (pix @ np.linalg.inv(np.asarray(cam.intrinsics, np.float64)).T) @ rot
        origins[sel] = cam.position
    return torch.as_tensor(origins, dtype=torch.float32), torch.as_tensor(dirs, dtype=torch.float32)


def scene_depth_scale(model) -> float:
    """The scene's depth scale, dividing depth errors: the box's half diagonal (bounded-360) or the near
    bound (forward-facing)."""
    if model.bounded:
        return float(model.half_size.norm())
    return float(model.scene.near)


class SparseDepthState:
    """The sparse-depth prior of one run: its points, and the extra keypoint rays it renders each step."""

    def __init__(self, views, prior: SparseDepthPrior, cache_dir: Optional[str | Path] = None):
        self.prior = prior
        self.cameras = list(views.cameras)
        self.points = load_or_compute_sparse_depth(views, prior, cache_dir)
        counts = np.bincount(self.points.view, minlength=len(views))
        if len(self.points) == 0:
            warnings.warn("sparse depth prior: no SIFT match survived triangulation; the prior adds nothing",
                          stacklevel=2)
        elif (counts == 0).any():
            names = [views.names[i] if i < len(views.names) else str(i) for i in np.flatnonzero(counts == 0)]
            warnings.warn(f"sparse depth prior: no triangulated point in view(s) {', '.join(names)}", stacklevel=2)
        self.origins, self.directions = keypoint_rays(self.cameras, self.points.view, self.points.xy)
        self.depth = torch.as_tensor(self.points.depth, dtype=torch.float32)

    def extras(self, model, generator: torch.Generator) -> dict[str, Any]:
        """Render ``prior.rays`` random keypoint rays: ``{"sift_depth": {"outputs", "depth", "scale"}}``
        (empty without points)."""
        if len(self.points) == 0:
            return {}
        idx = torch.randint(len(self.points), (self.prior.rays,), generator=generator)  # on the generator's device
        device = module_device(model)
        near = torch.full((len(idx),), float(model.scene.near), device=device)
        far = torch.full((len(idx),), float(model.scene.far), device=device)
        outputs = model.render_rays(self.origins[idx].to(device), self.directions[idx].to(device), near, far,
                                    jitter=True, generator=generator)
        return {"sift_depth": {"outputs": outputs, "depth": self.depth[idx].to(device),
                               "scale": scene_depth_scale(model),
                               "disparity": not model.bounded}}


@register_loss_term("sift_depth")
def sift_depth(inputs: LossInputs) -> Tensor:
    """DS-NeRF sparse depth (Eq. 3.13, as an L1) over the keypoint rays in ``extras["sift_depth"]``; 0 when
    there are none.

    Bounded scenes: ``mean |sum w t - z| / scale``. Forward-facing scenes compare disparities, as DS-NeRF
    does in NDC: ``mean |sum w near / t - near / z|`` (half the NDC depth difference; the unhit remainder
    of a ray counts as infinitely far, disparity 0), so points far away, whose depth the narrow baseline
    barely fixes, weigh little and a ray into the sky (t up to 1e10) cannot dominate."""
    entry = inputs.extras.get("sift_depth")
    if not entry:
        return inputs.outputs.color.new_zeros(())
    out = entry["outputs"]
    if entry.get("disparity"):
        near = entry["scale"]
        expected = (out.weights * (near / out.t.clamp_min(1e-6))).sum(dim=-1)
        return (expected - near / entry["depth"]).abs().mean()
    return (out.expected_depth - entry["depth"]).abs().mean() / entry["scale"]
