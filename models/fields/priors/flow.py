"""Sparse flow priors for dynamic fields (thesis Sec. 5.2.2, Eq. 5.7): SIFT matches across cameras and time.

Pipeline (once per run, cached in ``RUN/priors/``):

1. SIFT keypoints and descriptors of every training view (``priors_depth.sift_features``, cached per view
   across runs: ``pycolmap``'s CPU extractor on the display-encoded grey image; keypoints in continuous pixel
   coordinates, centres at +0.5).
2. Frame pairs (:func:`flow_pairs`): **across cameras**, every pair of views taken at the same time; **across
   time**, each view with every view at time ``s``, where ``s`` is the available time nearest to
   ``t - offset`` and to ``t + offset`` frames (the frame interval is the median gap between trained times;
   ``s`` stays on its side of ``t``; a side with no time is skipped), as the thesis's s in {t - 10, t + 10}.
3. Mutual nearest-neighbour matching with Lowe's ratio test (``priors_depth.match_descriptors``: COLMAP's
   CPU matcher, brute force in numpy).
4. Geometric verification (:func:`verify_matches`):
   - every pair: a match is kept only if it moves coherently with its neighbours: at least ``min_coherent``
     of its ``neighbours`` nearest matches (in the first image) have a displacement within ``coherence_px``
     px of its own (a local, multi-motion check in the spirit of GMS). Across time, moving objects break any
     single two-view geometry (COLMAP's own verification keeps the dominant motion only, i.e. drops exactly
     the moving points the prior is for), so this local check is the only one;
   - same time, in addition: the scene is frozen, so every true match obeys the epipolar geometry of the
     two KNOWN cameras: its Sampson distance to the known fundamental matrix must be at most
     ``max_epipolar_error`` px.

   On the measurement rig (160 x 90, 3 cameras, 24 frames) this keeps 8514 of 12113 raw matches, 1036 of
   them on moving objects; against the true depth and object motion, 97.7% of the same-time and 99.5% of
   the across-time matches with a finite depth land within 2 px (sky matches cannot be checked), against
   84% and 98% with the epipolar check alone and the looser 3 px / 2 neighbours coherence.

The loss term ``sparse_flow`` (Eq. 5.7) renders ``rays`` random matched pairs each step, each ray at its
view's time, and takes ``mean || sum_i w_i c'_i(t, v) - sum_i w_i c'_i(s, u) ||^2``: the weighted canonical
points of the two rays (contracted coordinates) must coincide. The weights keep their gradient (no
stop-gradient), as in the thesis. A pair without matches contributes nothing; with no match at all the
prior warns once and the term is 0.
"""
from __future__ import annotations

import hashlib
import json
import sys
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Optional

import cv2
import numpy as np
import torch
from torch import Tensor

from engine.core.checks import check_range
from engine.core.errors import InputError
from engine.predict import dis_calc, dis_estimator, luma8
from models.fields.data.timed import frame_step
from models.fields.components.render import module_device
from models.fields.losses import LossInputs, LossTerm, register_loss_term
from models.fields.priors.depth import feature_cache_dir, keypoint_rays, match_descriptors, sift_features

__all__ = ["SparseFlowPrior", "DynamicPriorsConfig", "FlowMatches", "flow_pairs", "fundamental_matrix",
           "sampson_distance", "coherent_matches", "verify_matches", "sparse_flow_matches",
           "load_or_compute_sparse_flow", "sparse_flow_loss", "SparseFlowState", "DynamicPriors",
           "build_dynamic_priors"]


@dataclass
class SparseFlowPrior:
    """Sparse flow prior (thesis Eq. 5.7) from SIFT matches across cameras and time."""

    enabled: bool = field(default=False, metadata={"help": "use the sparse flow prior (loss sparse_flow)"})
    weight: float = field(default=1.0, metadata={"help": "lambda_sf of Eq. 5.8 (the thesis's 1)"})
    rays: int = field(default=64, metadata={
        "help": "matched pairs rendered per step, two rays each (the thesis: 256; 64 costs a quarter of that and "
                "keeps the default ahead of K-Planes, 32 did not on lego: docs/results/2026-11-28-dynamic-cost.md)"})
    time_offset: int = field(default=10, metadata={
        "help": "frames between matched times (s in {t - offset, t + offset}, or the nearest available)"})
    across_cameras: bool = field(default=True, metadata={"help": "match views of different cameras at one time"})
    across_time: bool = field(default=True, metadata={"help": "match views at times t and s"})
    max_features: int = field(default=2048, metadata={"help": "SIFT features per view at most"})
    ratio: float = field(default=0.8, metadata={"help": "Lowe ratio test of the SIFT matcher"})
    max_epipolar_error: float = field(default=1.5, metadata={
        "help": "same-time pairs: largest Sampson distance (px) to the known cameras' epipolar geometry"})
    neighbours: int = field(default=6, metadata={"help": "neighbours of the coherence check"})
    min_coherent: int = field(default=3, metadata={"help": "neighbours that must move like the match"})
    coherence_px: float = field(default=2.0, metadata={
        "help": "largest displacement difference (px) of a coherent neighbour"})
    start_step: int = field(default=0, metadata={"help": "first step at which the flow loss is applied"})
    fade_start: int = field(default=2000, metadata={
        "help": "step from which the prior's weight falls linearly to fade_to over fade_steps: the prior finds "
                "the geometry early, and at full weight to the end it cost 0.3 dB on a path-traced rig at 10,000 "
                "steps (docs/results/2026-11-29-dynamic-prior-fade.md); runs of <= 2000 steps are unchanged"})
    fade_steps: int = field(default=4000, metadata={"help": "steps of that fall (0: the prior never fades)"})
    fade_to: float = field(default=0.1, metadata={
        "help": "fraction of the weight left after the fade (0: from the fade's end no matched ray is rendered; "
                "it lost lego's val split and rasterized rig 3 at 10,000 steps)"})
    source: str = field(default="sift", metadata={
        "help": "where matches come from: sift (sparse, the thesis's prior) or dis (dense OpenCV DIS optical flow "
                "on a grid, forward-backward checked: the dense-prior comparison)"})
    dense_stride: int = field(default=4, metadata={"help": "dis: one match per this many pixels along x and y"})
    dense_consistency: float = field(default=1.0, metadata={
        "help": "dis: largest forward-backward flow disagreement (px) of a kept match"})

    def validate(self) -> "SparseFlowPrior":
        if self.source not in ("sift", "dis"):
            raise InputError(f"must be sift or dis, got {self.source!r}", field="priors.flow.source")
        check_range(self.dense_stride, "priors.flow.dense_stride", low=1, integer=True)
        check_range(self.dense_consistency, "priors.flow.dense_consistency", low=0, low_open=True)
        for name in ("rays", "time_offset", "max_features", "neighbours", "min_coherent"):
            check_range(getattr(self, name), f"priors.flow.{name}", low=1, integer=True)
        if self.min_coherent > self.neighbours:
            raise InputError(f"must be <= neighbours ({self.neighbours}), got {self.min_coherent}",
                             field="priors.flow.min_coherent")
        for name in ("weight", "max_epipolar_error", "coherence_px"):
            check_range(getattr(self, name), f"priors.flow.{name}", low=0)
        check_range(self.ratio, "priors.flow.ratio", low=0, high=1, low_open=True)
        for name in ("start_step", "fade_start", "fade_steps"):
            check_range(getattr(self, name), f"priors.flow.{name}", low=0, integer=True)
        check_range(self.fade_to, "priors.flow.fade_to", low=0, high=1)
        return self

    def loss_term(self) -> LossTerm:
        """The run's ``sparse_flow`` loss term: the weight, start and fade of this prior."""
        return LossTerm("sparse_flow", self.weight, start_step=int(self.start_step), fade_start=int(self.fade_start),
                        fade_steps=int(self.fade_steps), fade_to=float(self.fade_to))


@dataclass
class DynamicPriorsConfig:
    """Which priors a dynamic run uses."""

    flow: SparseFlowPrior = field(default_factory=SparseFlowPrior, metadata={"help": "sparse flow (Eq. 5.7)"})

    def enabled(self) -> list[str]:
        return ["flow"] if self.flow.enabled else []

    def validate(self) -> "DynamicPriorsConfig":
        self.flow.validate()
        return self


@dataclass
class FlowMatches:
    """Verified matches: pixel ``xy_a`` of view ``view_a`` and pixel ``xy_b`` of view ``view_b`` see the same
    point of the scene (at their own times).

    Attributes:
        view_a, view_b: (M,) int64 training-view indices.
        xy_a, xy_b: (M, 2) float64 continuous pixel coordinates (centres at +0.5).
        across_time: (M,) bool, the two views are at different times.
        pairs: per frame pair ``"a-b"``: ``{"raw": n, "kept": m, "across_time": bool}``.
    """

    view_a: np.ndarray
    xy_a: np.ndarray
    view_b: np.ndarray
    xy_b: np.ndarray
    across_time: np.ndarray
    pairs: dict[str, dict[str, Any]]

    def __len__(self) -> int:
        return int(self.view_a.shape[0])


def flow_pairs(times: np.ndarray, prior: SparseFlowPrior) -> list[tuple[int, int]]:
    """Frame pairs (a < b) to match, for views at ``times`` (see the module doc, step 2)."""
    times = np.asarray(times, np.float64)
    unique = np.unique(times)
    pairs: set[tuple[int, int]] = set()
    if prior.across_cameras:
        for u in unique:
            same = np.flatnonzero(times == u)
            pairs.update((int(a), int(b)) for i, a in enumerate(same) for b in same[i + 1:])
    if prior.across_time and unique.size > 1:
        step = frame_step(times)
        for a, t in enumerate(times):
            for sign in (-1.0, 1.0):
                side = unique[sign * (unique - t) > 0]
                if side.size == 0:
                    continue
                s = side[np.argmin(np.abs(side - (t + sign * prior.time_offset * step)))]
                pairs.update((min(a, int(b)), max(a, int(b))) for b in np.flatnonzero(times == s))
    return sorted(pairs)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def fundamental_matrix(camera_a, camera_b) -> np.ndarray:
    """F (3, 3) with ``x_b^T F x_a = 0`` for pixels (+0.5 centres) of one world point in two OpenCV cameras."""
    ta, tb = np.asarray(camera_a.world_to_camera, np.float64), np.asarray(camera_b.world_to_camera, np.float64)
    rot = tb[:3, :3] @ ta[:3, :3].T
    trans = tb[:3, 3] - rot @ ta[:3, 3]
    ka_inv = np.linalg.inv(np.asarray(camera_a.intrinsics, np.float64))
    kb_inv = np.linalg.inv(np.asarray(camera_b.intrinsics, np.float64))
    return kb_inv.T @ _skew(trans) @ rot @ ka_inv


def sampson_distance(f: np.ndarray, xy_a: np.ndarray, xy_b: np.ndarray) -> np.ndarray:
    """First-order geometric distance (px) of matches (M, 2) <-> (M, 2) to the epipolar geometry F; inf where
    undefined (F = 0, e.g. the same camera centre)."""
    ha = np.concatenate([xy_a, np.ones((len(xy_a), 1))], axis=1)
    hb = np.concatenate([xy_b, np.ones((len(xy_b), 1))], axis=1)
    fa, fb = ha @ f.T, hb @ f
    num = np.einsum("ij,ij->i", hb, fa) ** 2
    den = fa[:, 0] ** 2 + fa[:, 1] ** 2 + fb[:, 0] ** 2 + fb[:, 1] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den > 1e-18, np.sqrt(num / np.where(den > 1e-18, den, 1.0)), np.inf)


def coherent_matches(xy_a: np.ndarray, xy_b: np.ndarray, *, neighbours: int = 6, min_coherent: int = 2,
                     tolerance: float = 3.0) -> np.ndarray:
    """(M,) bool: matches with at least ``min_coherent`` of their ``neighbours`` nearest matches (in image a)
    displaced within ``tolerance`` px of their own displacement."""
    m = len(xy_a)
    if m <= min_coherent:
        return np.zeros(m, bool)
    disp = xy_b - xy_a
    d2 = ((xy_a[:, None, :] - xy_a[None, :, :]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    k = min(neighbours, m - 1)
    nn = np.argsort(d2, axis=1)[:, :k]
    agree = np.linalg.norm(disp[nn] - disp[:, None, :], axis=-1) <= tolerance
    return agree.sum(axis=1) >= min_coherent


def verify_matches(views, a: int, b: int, xy_a: np.ndarray, xy_b: np.ndarray, prior: SparseFlowPrior) -> np.ndarray:
    """(M,) bool: the geometric verification of the module doc (coherence; and epipolar at one time)."""
    if len(xy_a) == 0:
        return np.zeros(0, bool)
    keep = coherent_matches(xy_a, xy_b, neighbours=prior.neighbours, min_coherent=prior.min_coherent,
                            tolerance=prior.coherence_px)
    if views.times[a] == views.times[b]:
        keep &= sampson_distance(fundamental_matrix(views.cameras[a], views.cameras[b]), xy_a, xy_b) \
            <= prior.max_epipolar_error
    return keep


def dense_flow_matches(image_a: np.ndarray, image_b: np.ndarray, stride: int = 4, consistency: float = 1.0
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Dense matches from OpenCV DIS optical flow (no downloaded weights): pixel centres of image a on a grid
    of ``stride`` px and where the flow a -> b takes them, kept where the flow b -> a brings them back within
    ``consistency`` px and they land inside image b. Returns (xy_a (M, 2), xy_b (M, 2)), centres at +0.5."""

    ga, gb = luma8(image_a), luma8(image_b)
    dis = dis_estimator("medium")
    fwd = dis_calc(dis, ga, gb)
    bwd = dis_calc(dis, gb, ga)
    h, w = ga.shape
    v, u = np.mgrid[stride // 2:h:stride, stride // 2:w:stride]
    f = fwd[v, u]
    xb, yb = u + f[..., 0], v + f[..., 1]
    inside = (xb >= 0) & (xb <= w - 1) & (yb >= 0) & (yb <= h - 1)
    back = cv2.remap(bwd, xb.astype(np.float32), yb.astype(np.float32), cv2.INTER_LINEAR)
    keep = inside & (np.linalg.norm(f + back, axis=-1) <= consistency)
    xy_a = np.stack([u[keep], v[keep]], -1).astype(np.float64) + 0.5
    xy_b = np.stack([xb[keep], yb[keep]], -1).astype(np.float64) + 0.5
    return xy_a, xy_b


def sparse_flow_matches(views, prior: SparseFlowPrior) -> FlowMatches:
    """Verified matches of the training views (:class:`~models.fields.data.timed.TimedViews`): SIFT
    (``source="sift"``) or dense DIS optical flow (``source="dis"``), then the same verification."""
    features = (sift_features(views.images, prior.max_features, cache_dir=feature_cache_dir())
                if prior.source == "sift" else None)
    parts: dict[str, list] = {"va": [], "xa": [], "vb": [], "xb": [], "across": []}
    counts: dict[str, dict[str, Any]] = {}
    for a, b in flow_pairs(views.times, prior):
        if features is None:
            pa, pb = dense_flow_matches(views.images[a], views.images[b], prior.dense_stride,
                                        prior.dense_consistency)
            idx = pa
        else:
            (xa, da), (xb, db) = features[a], features[b]
            idx = match_descriptors(da, db, prior.ratio)
            pa, pb = xa[idx[:, 0]].reshape(-1, 2), xb[idx[:, 1]].reshape(-1, 2)
        keep = verify_matches(views, a, b, pa, pb, prior)
        across = bool(views.times[a] != views.times[b])
        counts[f"{a}-{b}"] = {"raw": int(len(idx)), "kept": int(keep.sum()), "across_time": across}
        n = int(keep.sum())
        parts["va"].append(np.full(n, a, np.int64))
        parts["vb"].append(np.full(n, b, np.int64))
        parts["xa"].append(pa[keep])
        parts["xb"].append(pb[keep])
        parts["across"].append(np.full(n, across))
    cat = (lambda key, shape, dtype: np.concatenate(parts[key]).astype(dtype) if parts[key] else np.zeros(shape, dtype))
    return FlowMatches(cat("va", (0,), np.int64), cat("xa", (0, 2), np.float64), cat("vb", (0,), np.int64),
                       cat("xb", (0, 2), np.float64), cat("across", (0,), bool), counts)


def _fingerprint(views, prior: SparseFlowPrior) -> dict[str, Any]:
    import pycolmap

    digest = hashlib.sha1(np.ascontiguousarray(views.images, np.float32).tobytes())
    digest.update(np.asarray(views.times, np.float64).tobytes())
    for cam in views.cameras:
        digest.update(np.asarray(cam.intrinsics, np.float64).tobytes())
        digest.update(np.asarray(cam.world_to_camera, np.float64).tobytes())
    params = {k: v for k, v in asdict(prior).items()
              if k not in ("enabled", "weight", "rays", "start_step", "fade_start", "fade_steps", "fade_to")}
    return {"views": list(views.names), "size": [views.height, views.width], "sha1": digest.hexdigest(),
            "pycolmap": pycolmap.__version__, **params}


def load_or_compute_sparse_flow(views, prior: SparseFlowPrior, cache_dir: Optional[str | Path]) -> FlowMatches:
    """:func:`sparse_flow_matches`, cached as ``sparse_flow.npz`` + ``sparse_flow.json`` in ``cache_dir``.

    The JSON holds the parameters and a SHA-1 of the images, times and cameras (``key``; recomputed when they
    differ), the command line that made the cache (``command``), and the match counts per frame pair.
    """
    key = _fingerprint(views, prior)
    meta_file = data_file = None
    if cache_dir is not None:
        meta_file, data_file = Path(cache_dir) / "sparse_flow.json", Path(cache_dir) / "sparse_flow.npz"
        if meta_file.is_file() and data_file.is_file():
            meta = json.loads(meta_file.read_text())
            if meta.get("key") == key:
                d = np.load(data_file)
                return FlowMatches(d["view_a"], d["xy_a"], d["view_b"], d["xy_b"], d["across_time"], meta["pairs"])
    matches = sparse_flow_matches(views, prior)
    if cache_dir is not None:
        Path(cache_dir).mkdir(parents=True, exist_ok=True)
        np.savez(data_file, view_a=matches.view_a, xy_a=matches.xy_a, view_b=matches.view_b, xy_b=matches.xy_b,
                 across_time=matches.across_time)
        pairs = matches.pairs.values()
        meta_file.write_text(json.dumps({
            "command": " ".join(sys.argv),
            "matches": len(matches), "matches_across_time": int(matches.across_time.sum()),
            "pairs_without_matches": sum(1 for p in pairs if p["kept"] == 0), "key": key,
            "pairs": matches.pairs}, indent=1) + "\n")
    return matches


def sparse_flow_loss(weights_a: Tensor, canonical_a: Tensor, weights_b: Tensor, canonical_b: Tensor) -> Tensor:
    """Eq. 5.7: ``mean_r || sum_i w_i(a) c'_i(a) - sum_i w_i(b) c'_i(b) ||^2`` over matched rays r.

    Args:
        weights_a, weights_b: (R, N) rendering weights (gradients kept: no stop-gradient).
        canonical_a, canonical_b: (R, N, 3) canonical points of the samples (contracted coordinates).

    Returns:
        scalar (0 for R = 0).
    """
    if weights_a.shape[0] == 0:
        return weights_a.new_zeros(())
    pa = (weights_a[..., None] * canonical_a).sum(dim=-2)
    pb = (weights_b[..., None] * canonical_b).sum(dim=-2)
    return (pa - pb).square().sum(dim=-1).mean()


class SparseFlowState:
    """The sparse flow prior of one run: its matches and the matched rays it renders each step."""

    def __init__(self, views, prior: SparseFlowPrior, cache_dir: Optional[str | Path] = None):
        self.prior = prior
        self.term = prior.loss_term()
        self.matches = load_or_compute_sparse_flow(views, prior, cache_dir)
        empty = sum(1 for p in self.matches.pairs.values() if p["kept"] == 0)
        if len(self.matches) == 0:
            warnings.warn(f"sparse flow prior: no verified match in any of {len(self.matches.pairs)} frame pairs; "
                          "the prior adds nothing", stacklevel=2)
        elif empty:
            warnings.warn(f"sparse flow prior: {empty} of {len(self.matches.pairs)} frame pairs have no verified "
                          f"match ({len(self.matches)} matches in the others)", stacklevel=2)
        m = self.matches
        self.origins_a, self.directions_a = keypoint_rays(views.cameras, m.view_a, m.xy_a)
        self.origins_b, self.directions_b = keypoint_rays(views.cameras, m.view_b, m.xy_b)
        self.times_a = torch.as_tensor(np.asarray(views.times, np.float64)[m.view_a], dtype=torch.float32)
        self.times_b = torch.as_tensor(np.asarray(views.times, np.float64)[m.view_b], dtype=torch.float32)

    def active(self, step: int) -> bool:
        """Whether the prior's loss counts at ``step`` (its matched rays are rendered only then)."""
        return self.term.factor(step) > 0

    def extras(self, model, generator: torch.Generator) -> dict[str, Any]:
        """Render ``prior.rays`` random matched pairs: ``{"sparse_flow": {"a": outputs, "b": outputs}}``
        (empty without matches).

        The two ends of every pair are rendered in one geometry-only call (``render_rays(color=False)``: the loss
        reads weights and canonical points only), rays ``a`` first: the same jitter draws, hence the same
        samples, as two calls ``a`` then ``b``. The training step renders the same rays (same draws) in one
        pass with its batch instead (:meth:`draw`, :meth:`entry`).
        """
        rays = self.draw(model, generator)
        if rays is None:
            return {}
        return self.entry(model.render_rays(*rays, jitter=True, generator=generator, color=False))

    def draw(self, model, generator: torch.Generator) -> Optional[tuple[Tensor, ...]]:
        """``prior.rays`` random matched pairs as ``(origins, directions, near, far, times)`` of 2R rays on the
        model's device, the ``a`` ends first (None without matches): the draw :meth:`extras` renders."""
        if len(self.matches) == 0:
            return None
        idx = torch.randint(len(self.matches), (self.prior.rays,), generator=generator)  # on the generator's device
        device = module_device(model)
        n = len(idx)
        bounds = torch.tensor([float(model.scene.near), float(model.scene.far)], device=device)
        return (torch.cat([self.origins_a[idx], self.origins_b[idx]]).to(device),
                torch.cat([self.directions_a[idx], self.directions_b[idx]]).to(device),
                bounds[0].expand(2 * n), bounds[1].expand(2 * n),
                torch.cat([self.times_a[idx], self.times_b[idx]]).to(device))

    @staticmethod
    def entry(out) -> dict[str, Any]:
        """The rendered rays of :meth:`draw` -> ``{"sparse_flow": {"a": outputs, "b": outputs}}``."""
        n = out.color.shape[0] // 2
        return {"sparse_flow": {"a": type(out)(*(x[:n] for x in out)), "b": type(out)(*(x[n:] for x in out))}}


@register_loss_term("sparse_flow")
def sparse_flow_term(inputs: LossInputs) -> Tensor:
    """Eq. 5.7 on the matched rays in ``extras["sparse_flow"]``; 0 when there are none."""
    entry = inputs.extras.get("sparse_flow")
    if not entry:
        return inputs.outputs.color.new_zeros(())
    a, b = entry["a"], entry["b"]
    return sparse_flow_loss(a.weights, a.canonical, b.weights, b.canonical)


class DynamicPriors:
    """Per-run state of the enabled dynamic priors (no parameters of their own)."""

    def __init__(self, views, config: DynamicPriorsConfig, cache_dir: Optional[str | Path] = None):
        self.flow = SparseFlowState(views, config.flow, cache_dir) if config.flow.enabled else None

    def extras(self, model, generator: torch.Generator) -> dict[str, Any]:
        return self.flow.extras(model, generator) if self.flow is not None else {}


def build_dynamic_priors(views, config: DynamicPriorsConfig, cache_dir: Optional[str | Path] = None
                         ) -> Optional[DynamicPriors]:
    """The run's :class:`DynamicPriors`, or None when no prior is enabled."""
    return DynamicPriors(views, config, cache_dir) if config.enabled() else None
