"""ViP-NeRF visibility prior (thesis Ch. 3, Eq. 3.7-3.12).

**Prior** (Sec. 3.3.2, computed once per run and cached): for every ordered pair (primary i, secondary j)
of training views, the secondary image is warped into the primary view on ``num_planes`` fronto-parallel
planes uniform in inverse depth between the primary view's near and far bounds (far = inf gives the plane
at infinity; the warp is ``engine.geometry.reproject`` of a constant depth map), the error of each plane
is the L1 norm over colour channels of display-encoded 0-255 values (Eq. 3.9; planes that warp a pixel
outside the secondary image give no match), and a pixel is visible in j where
``exp(-min_k E_k / gamma) > threshold`` (Eq. 3.10; gamma = 10, threshold 0.5, i.e. min error < 6.93 on the
0-255 scale). :func:`plane_sweep_visibility` is the pure function.

**Visibility head** (Eq. 3.11): a one-hidden-layer MLP on the field's latent ``h_i`` and the encoded view
direction, with a sigmoid, predicts the transmittance ``T_hat`` of sample i seen along a direction. For the
first ``rays`` rays of a batch (random pixels of random views) a secondary view j != i is drawn per ray, the
field's F1 is re-evaluated on the ray's samples that are inside the scene (and in occupied cells) to get
``h_i`` (with gradient), and the head gives ``T_hat_i`` along the ray's own direction and ``T_hat'_i`` along
the direction from camera j's centre to the sample. The background a ray composites (weight
``1 - opacity``, at infinity) counts as visible from every view, so background rays of bounded scenes
(white in NeRF-synthetic, where the plane sweep finds white matching white) are not pushed to be opaque.

**Losses**: ``visibility_prior`` (Eq. 3.8): ``mean(max(tau' - t', 0))`` with ``t' = sum_i w_i T_hat'_i``
(Eq. 3.7) and tau' the prior of the ray's pixel in pair (i, j) (pixels without a match, tau' = 0, add
nothing); ``visibility_consistency`` (Eq. 3.12): ``(SG(T_i) - T_hat_i)^2 + (T_i - SG(T_hat_i))^2``
averaged over the evaluated samples (a mean rather than the sum over N, so the weight does not depend on
the number of samples). Until ``start_fraction`` of the steps only the head learns (``SG(T) - T_hat``):
an untrained head's ``T_hat`` ~ 0.5 pulled the field's transmittance down everywhere and filled the
occupancy grid (measured: 100% occupied on lego, against ~20% without the prior); Eq. 3.8 starts then too.
The head lives beside the model (saved in the checkpoint under ``priors``), not in it: inference and
export use the field alone.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch
from torch import Tensor, nn

from engine.core.colorspace import display_encode
from engine.geometry import reproject
from models.fields.components.encodings import MLP, DirectionEncoding
from models.fields.losses import LossInputs, register_loss_term
from models.fields.priors.simple import bilinear_sample
from models.fields.priors.stereo import plane_depths_inverse

__all__ = ["VisibilityPrior", "plane_depths_inverse", "plane_sweep_visibility", "visibility_maps",
           "load_or_compute_visibility", "VisibilityHead", "VisibilityState"]


@dataclass
class VisibilityPrior:
    """ViP-NeRF's plane-sweep visibility prior and visibility head."""

    enabled: bool = field(default=False, metadata={"help": "use the ViP-NeRF visibility prior"})
    num_planes: int = field(default=64, metadata={"help": "plane-sweep planes, uniform in inverse depth"})
    gamma: float = field(default=10.0, metadata={"help": "gamma of exp(-min error / gamma) (errors on 0-255)"})
    threshold: float = field(default=0.5, metadata={"help": "visible where exp(-min error / gamma) exceeds this"})
    prior_weight: float = field(default=0.01, metadata={"help": "weight of Eq. 3.8 (visibility_prior)"})
    consistency_weight: float = field(default=0.01, metadata={"help": "weight of Eq. 3.12 (visibility_consistency)"})
    rays: int = field(default=256, metadata={"help": "rays per step that carry the visibility losses"})
    hidden: int = field(default=32, metadata={"help": "hidden width of the visibility head"})
    start_fraction: float = field(default=0.2, metadata={
        "help": "Eq. 3.8 and the T <- SG(T_hat) half of Eq. 3.12 start after this fraction of the steps (the "
                "head learns T_hat <- SG(T) from the start)"})


def plane_sweep_visibility(primary: np.ndarray, secondary: np.ndarray, cam_primary, cam_secondary,
                           near: float, far: float, *, num_planes: int = 64, gamma: float = 10.0,
                           threshold: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Binary visibility of every primary pixel in the secondary view (Eq. 3.9-3.10).

    Args:
        primary, secondary: (H, W, 3) and (H', W', 3) display-encoded colours on the 0-255 scale.
        cam_primary, cam_secondary: cameras (``intrinsics``, ``world_to_camera``).
        near, far: planar-depth range of the sweep in the primary view (far may be inf).

    Returns:
        visible (H, W) bool and the minimum error e (H, W) (inf where no plane lands inside the secondary).
    """
    h, w = primary.shape[:2]
    hs, ws = secondary.shape[:2]
    best = np.full((h, w), np.inf, np.float32)
    for z in plane_depths_inverse(near, far, num_planes):
        uv, _, valid = reproject(np.full((h, w), z, np.float32), cam_primary.intrinsics, cam_primary.world_to_camera,
                                 cam_secondary.intrinsics, cam_secondary.world_to_camera)
        inside = valid & (uv[..., 0] >= 0.5) & (uv[..., 0] <= ws - 0.5) & (uv[..., 1] >= 0.5) & (uv[..., 1] <= hs - 0.5)
        error = np.abs(primary - bilinear_sample(secondary, uv)).sum(axis=-1)
        best = np.minimum(best, np.where(inside, error, np.inf).astype(np.float32))
    return np.exp(-best / gamma) > threshold, best


def visibility_maps(views, prior: VisibilityPrior) -> np.ndarray:
    """(N, N, H, W) bool: ``[i, j]`` is the visibility of view i's pixels in view j (``[i, i]`` all True)."""
    n = len(views)
    images = display_encode(views.images).astype(np.float32) * 255.0
    maps = np.ones((n, n, views.height, views.width), bool)
    for i in range(n):
        for j in range(n):
            if i != j:
                maps[i, j] = plane_sweep_visibility(
                    images[i], images[j], views.cameras[i], views.cameras[j], float(views.near_far[i, 0]),
                    float(views.near_far[i, 1]), num_planes=prior.num_planes, gamma=prior.gamma,
                    threshold=prior.threshold)[0]
    return maps


def load_or_compute_visibility(views, prior: VisibilityPrior, cache_dir: Optional[str | Path]) -> np.ndarray:
    """:func:`visibility_maps`, cached as ``visibility.npz`` + ``visibility.json`` (parameters and a hash of
    the images, cameras and bounds) in ``cache_dir``."""
    digest = hashlib.sha1(np.ascontiguousarray(views.images, np.float32).tobytes())
    digest.update(np.asarray(views.near_far, np.float64).tobytes())
    for cam in views.cameras:
        digest.update(np.asarray(cam.intrinsics, np.float64).tobytes())
        digest.update(np.asarray(cam.world_to_camera, np.float64).tobytes())
    key = {"views": list(views.names), "sha1": digest.hexdigest(), "num_planes": prior.num_planes,
           "gamma": prior.gamma, "threshold": prior.threshold}
    if cache_dir is not None:
        meta_file, data_file = Path(cache_dir) / "visibility.json", Path(cache_dir) / "visibility.npz"
        if meta_file.is_file() and data_file.is_file() and json.loads(meta_file.read_text()).get("key") == key:
            return np.load(data_file)["visible"]
    maps = visibility_maps(views, prior)
    if cache_dir is not None:
        Path(cache_dir).mkdir(parents=True, exist_ok=True)
        np.savez_compressed(data_file, visible=maps)
        n = len(views)
        fractions = {f"{i}-{j}": float(maps[i, j].mean()) for i in range(n) for j in range(n) if i != j}
        meta_file.write_text(json.dumps({"key": key, "visible_fraction": fractions}, indent=2) + "\n")
    return maps


class VisibilityHead(nn.Module):
    """Eq. 3.11's visibility output of F2: latent h (..., G) and unit directions (..., 3) -> T_hat (...)."""

    def __init__(self, geo_feature_dim: int, direction_encoding: str, direction_degree: int, hidden: int = 32):
        super().__init__()
        self.direction_encoding = DirectionEncoding(direction_encoding, direction_degree)
        self.mlp = MLP(geo_feature_dim + self.direction_encoding.output_dim, hidden, 1)

    def forward(self, geo_features: Tensor, directions: Tensor) -> Tensor:
        x = torch.cat([geo_features, self.direction_encoding(directions)], dim=-1)
        return torch.sigmoid(self.mlp(x))[..., 0]


class VisibilityState(nn.Module):
    """The visibility prior of one run: cached maps, camera centres and the visibility head."""

    def __init__(self, views, config, prior: VisibilityPrior, cache_dir: Optional[str | Path] = None):
        super().__init__()
        self.prior = prior
        self.maps = torch.from_numpy(load_or_compute_visibility(views, prior, cache_dir))
        self.centres = torch.as_tensor(np.stack([c.position for c in views.cameras]), dtype=torch.float32)
        fc = config.field
        self.head = VisibilityHead(fc.geo_feature_dim, fc.direction_encoding, fc.direction_degree, prior.hidden)
        self.transfer_start = int(prior.start_fraction * config.steps)

    def extras(self, model, batch, outputs, step: int, generator: torch.Generator) -> dict[str, Any]:
        """``{"visibility": {"t_secondary", "prior", "trans", "trans_hat", "mask", "transfer"}}`` for the first ``rays``
        rays of the batch (empty with a single view or without pixel indices)."""
        n = self.maps.shape[0]
        if n < 2 or batch.pixel is None or batch.view is None:
            return {}
        r = min(self.prior.rays, batch.view.shape[0])
        device = batch.origins.device
        view, pixel = batch.view[:r].cpu(), batch.pixel[:r].cpu()  # the maps stay in host memory
        other = (view + 1 + torch.randint(n - 1, (r,), generator=generator)) % n
        w = self.maps.shape[-1]
        tau = self.maps[view, other, pixel // w, pixel % w].float().to(device)
        centres = self.centres[other].to(device)
        t = outputs.t[:r]
        points = batch.origins[:r, None, :] + t[..., None] * batch.directions[:r, None, :]
        coords = model.contract(points)
        keep = (coords.abs() <= 1.0).all(dim=-1)
        if model.occupancy is not None and int(model.occupancy.updates) > 0:
            keep = keep & model.occupancy.query(coords)
        idx = keep.nonzero(as_tuple=True)
        trans_hat = t.new_zeros(t.shape)
        trans_hat_secondary = t.new_zeros(t.shape)
        if idx[0].numel() > 0:
            _, h = model.field.get_density(coords[idx])
            primary_dir = torch.nn.functional.normalize(batch.directions[:r], dim=-1)[idx[0]]
            secondary_dir = torch.nn.functional.normalize(points[idx] - centres[idx[0]], dim=-1)
            trans_hat = trans_hat.index_put(idx, self.head(h, primary_dir))
            trans_hat_secondary = trans_hat_secondary.index_put(idx, self.head(h, secondary_dir))
        # Eq. 3.7 with T_hat'; the background (weight 1 - opacity, at infinity) counts as visible
        t_secondary = (outputs.weights[:r] * trans_hat_secondary).sum(dim=-1) + (1.0 - outputs.opacity[:r])
        return {"visibility": {"t_secondary": t_secondary, "prior": tau, "trans": outputs.transmittance[:r],
                               "trans_hat": trans_hat, "mask": keep, "transfer": step >= self.transfer_start}}


@register_loss_term("visibility_prior")
def visibility_prior(inputs: LossInputs) -> Tensor:
    """Eq. 3.8: mean over the visibility rays of ``max(tau' - t', 0)`` (from ``start_fraction`` of the steps)."""
    entry = inputs.extras.get("visibility")
    if not entry:
        return inputs.outputs.color.new_zeros(())
    return torch.relu(entry["prior"] - entry["t_secondary"]).mean()


@register_loss_term("visibility_consistency")
def visibility_consistency(inputs: LossInputs) -> Tensor:
    """Eq. 3.12 averaged over the evaluated samples: ``(SG(T) - T_hat)^2 + (T - SG(T_hat))^2``."""
    entry = inputs.extras.get("visibility")
    if not entry or not bool(entry["mask"].any()):
        return inputs.outputs.color.new_zeros(())
    mask, trans, trans_hat = entry["mask"], entry["trans"], entry["trans_hat"]
    per_sample = (trans.detach() - trans_hat).square()
    if entry["transfer"]:
        per_sample = per_sample + (trans - trans_hat.detach()).square()
    return per_sample[mask].mean()
