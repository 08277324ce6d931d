"""Simple-RF augmentation (thesis Ch. 4): a lower-capacity augmented field trained in tandem.

The augmented model is a second :class:`~models.fields.static.model.StaticFieldModel` over the same scene with
fewer plane scales and channels (Simple-TensoRF's lower rank and resolution, Sec. 4.3.2.3) whose rays start
further from the camera (the near bound pushed away: a fraction ``near_shift`` of each ray's in-scene
interval for bounded-360, ``near / (1 - near_shift)`` for forward-facing, i.e. the same fraction of the NDC
z range, -1 -> -0.5 for 0.25 as Simple-TensoRF). It is trained on the photometric loss, the
mass-concentration loss (Eq. 4.15, :func:`mass_concentration`) and Eq. 4.9 with the main model; only the
main model is kept for inference and export (``load_model`` never sees it).

Reliable depths (Eq. 4.8): each ray's depth from the main and from the augmented model is used to reproject
a ``patch_size`` x ``patch_size`` patch around its pixel (the whole patch at the centre's planar depth) into
the nearest other training view (by camera centre); the patch MSE of display-encoded colours in [0, 1] is
``e_m`` / ``e_a`` (:func:`patch_reprojection_error`). The augmented depth supervises the main model where
``e_a <= e_m`` and ``e_a <= e_tau`` and vice versa (:func:`reliable_depth_masks`), with stop-gradient on the
supervising depth. Depths are the opacity-normalised ``depth`` of rays whose opacity is at least
``min_opacity`` in both models (white-background rays that hit nothing are never supervised), and the
squared difference is divided by the squared scene depth scale.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from engine.core.colorspace import display_encode
from engine.geometry import project, relative_transform
from models.fields.losses import LossInputs, register_loss_term, srgb_encode
from models.fields.priors.depth import scene_depth_scale
from models.fields.static.model import StaticFieldModel

__all__ = ["SimplePrior", "mass_concentration", "patch_reprojection_error", "reliable_depth_masks",
           "nearest_views", "augmented_near", "AugmentedState", "bilinear_sample"]


@dataclass
class SimplePrior:
    """Simple-RF's augmented lower-capacity model and its losses."""

    enabled: bool = field(default=False, metadata={"help": "train a Simple-RF augmented model in tandem"})
    resolutions: tuple[int, ...] = field(default=(16, 32), metadata={
        "help": "plane sides of the augmented field (lower than the main field's)"})
    feature_dim: int = field(default=4, metadata={"help": "feature channels per plane of the augmented field"})
    near_shift: float = field(default=0.25, metadata={
        "help": "fraction of each ray's depth range (disparity range for forward-facing) the augmented model skips"})
    photometric_weight: float = field(default=1.0, metadata={"help": "photometric loss of the augmented model"})
    mass_weight: float = field(default=1e-3, metadata={"help": "mass-concentration entropy (Eq. 4.15) weight"})
    mass_intervals: int = field(default=5, metadata={"help": "N_mc intervals of Eq. 4.15"})
    depth_weight: float = field(default=0.1, metadata={"help": "Eq. 4.9 mutual depth supervision weight"})
    depth_start_fraction: float = field(default=0.2, metadata={
        "help": "Eq. 4.9 starts after this fraction of the steps (5k of 25k in Simple-TensoRF)"})
    patch_size: int = field(default=5, metadata={"help": "side of the reprojected patch (odd)"})
    error_threshold: float = field(default=0.1, metadata={"help": "e_tau: largest patch MSE of a reliable depth"})
    min_opacity: float = field(default=0.5, metadata={"help": "rays below this opacity in either model get no Eq. 4.9"})


def mass_concentration(weights: Tensor, intervals: int = 5) -> Tensor:
    """Eq. 4.15: entropy ``-sum_j m_j log m_j`` of the mass ``m_j`` in ``intervals`` consecutive groups of
    samples, per ray (R,). ``0 log 0 = 0`` with a finite gradient: empty groups contribute nothing.

    Args:
        weights: (R, N) volume-rendering weights, split into ``intervals`` consecutive groups as equal as possible.
    """
    r, n = weights.shape
    bounds = torch.linspace(0, n, intervals + 1).round().long().tolist()
    mass = torch.stack([weights[:, a:b].sum(dim=1) for a, b in zip(bounds[:-1], bounds[1:])], dim=1)
    positive = mass > 1e-12
    safe = torch.where(positive, mass, torch.ones_like(mass))
    return -torch.where(positive, safe * torch.log(safe), torch.zeros_like(mass)).sum(dim=1)


def nearest_views(cameras) -> np.ndarray:
    """(N,) index of the other camera whose centre is nearest to each camera's."""
    centres = np.stack([c.position for c in cameras])
    dist = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    np.fill_diagonal(dist, np.inf)
    return dist.argmin(axis=1)


def bilinear_sample(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Sample (H, W, C) at continuous pixel coordinates (..., 2) (pixel centres at +0.5, edge-clamped)."""
    h, w = image.shape[:2]
    x = np.clip(uv[..., 0] - 0.5, 0.0, w - 1.0)
    y = np.clip(uv[..., 1] - 0.5, 0.0, h - 1.0)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def patch_reprojection_error(images: np.ndarray, cameras, view: np.ndarray, pixel: np.ndarray, depth: np.ndarray,
                             target: np.ndarray, patch_size: int = 5) -> np.ndarray:
    """Patch MSE between each ray's source patch and its reprojection into a target view (Sec. 4.3.1.4).

    The ``patch_size`` x ``patch_size`` pixels around ``pixel`` in ``images[view]`` are lifted to the planar
    depth ``depth`` (the same for the whole patch), moved into camera ``target`` (``relative_transform``,
    ``project`` of ``engine.geometry``) and compared with ``images[target]`` sampled bilinearly there.

    Args:
        images: (N, H, W, C) colours (the caller's choice of encoding; Simple-RF: display-encoded [0, 1]).
        cameras: N cameras.
        view, target: (R,) int source and target views.
        pixel: (R, 2) int (u, v) pixel indices.
        depth: (R,) planar depths in the source view.

    Returns:
        (R,) mean squared error over the patch and channels; +inf where the depth is not finite and positive,
        the patch leaves the source image, or a reprojected pixel falls behind the target camera or outside
        its image.
    """
    n, h, w = images.shape[:3]
    half = patch_size // 2
    du, dv = np.meshgrid(np.arange(-half, half + 1), np.arange(-half, half + 1))
    offsets = np.stack([du.ravel(), dv.ravel()], axis=-1)  # (P, 2)
    errors = np.full(len(view), np.inf)
    depth = np.asarray(depth, np.float64)
    usable = np.isfinite(depth) & (depth > 0)
    for s, t in {(int(a), int(b)) for a, b in zip(view[usable], target[usable])}:
        sel = np.flatnonzero(usable & (view == s) & (target == t))
        src = pixel[sel, None, :] + offsets[None]  # (R', P, 2) integer pixels
        inside = ((src >= 0) & (src < [w, h])).all(axis=-1).all(axis=-1)
        src = np.clip(src, 0, [w - 1, h - 1])
        centres = src + 0.5
        k_inv = np.linalg.inv(np.asarray(cameras[s].intrinsics, np.float64))
        rays = np.concatenate([centres, np.ones(centres.shape[:-1] + (1,))], axis=-1) @ k_inv.T
        pts = np.concatenate([rays * depth[sel, None, None], np.ones(rays.shape[:-1] + (1,))], axis=-1)
        pts = pts @ relative_transform(cameras[s].world_to_camera, cameras[t].world_to_camera).T
        uv, _, valid = project(pts, cameras[t].intrinsics)
        in_target = valid & (uv[..., 0] >= 0) & (uv[..., 0] <= w) & (uv[..., 1] >= 0) & (uv[..., 1] <= h)
        ok = inside & in_target.all(axis=-1)
        ref = images[s][src[..., 1], src[..., 0]]
        warped = bilinear_sample(images[t], uv)
        mse = ((ref - warped) ** 2).mean(axis=(-1, -2))
        errors[sel] = np.where(ok, mse, np.inf)
    return errors


def reliable_depth_masks(error_main: Tensor, error_aug: Tensor, threshold: float) -> tuple[Tensor, Tensor]:
    """Eq. 4.8: ``m_a = (e_a <= e_m) & (e_a <= e_tau)`` and ``m_m = (e_m < e_a) & (e_m <= e_tau)``
    (ties go to the augmented model, so at most one mask is set per ray); inf errors are never reliable."""
    m_a = (error_aug <= error_main) & (error_aug <= threshold)
    m_m = (error_main < error_aug) & (error_main <= threshold)
    return m_a, m_m


def augmented_near(model: StaticFieldModel, origins: Tensor, directions: Tensor, near: Tensor, far: Tensor,
                   shift: float) -> Tensor:
    """The pushed-away near bound of the augmented model (see the module doc)."""
    if not model.bounded:
        return near / (1.0 - shift)
    t_near, t_far = model.ray_bounds(origins, directions, near, far)
    return torch.where(t_far > t_near, t_near + shift * (t_far - t_near), near)


class AugmentedState(nn.Module):
    """The augmented model of one run and what Eq. 4.8 needs (display-encoded train images, nearest views)."""

    def __init__(self, views, config, prior: SimplePrior, main: StaticFieldModel):
        super().__init__()
        self.prior = prior
        field_config = dataclasses.replace(config.field, resolutions=tuple(prior.resolutions),
                                           feature_dim=int(prior.feature_dim))
        self.model = StaticFieldModel(main.scene, main.background.tolist(), field_config, config.render)
        self.images = display_encode(views.images).astype(np.float32)
        self.cameras = list(views.cameras)
        self.nearest = nearest_views(self.cameras) if len(views) > 1 else np.zeros(1, np.int64)
        self.width = views.width

    def extras(self, main: StaticFieldModel, batch, outputs, generator: torch.Generator) -> dict[str, Any]:
        """Render the batch with the augmented model and compute the Eq. 4.8 masks:
        ``{"augmented": {"outputs", "mask_main", "mask_aug", "scale"}}``."""
        near = augmented_near(self.model, batch.origins, batch.directions, batch.near, batch.far,
                              self.prior.near_shift)
        aug = self.model.render_rays(batch.origins, batch.directions, near, batch.far, jitter=True,
                                     generator=generator)
        mask_main = mask_aug = torch.zeros_like(batch.near, dtype=torch.bool)
        if len(self.cameras) > 1 and batch.pixel is not None and batch.view is not None:
            with torch.no_grad():
                view = batch.view.cpu().numpy()
                pixel_index = batch.pixel.cpu().numpy()
                pixel = np.stack([pixel_index % self.width, pixel_index // self.width], axis=-1)
                target = self.nearest[view]
                solid = ((outputs.opacity >= self.prior.min_opacity)
                         & (aug.opacity >= self.prior.min_opacity)).cpu().numpy()
                z_m = np.where(solid, outputs.depth.cpu().numpy(), np.inf)
                z_a = np.where(solid, aug.depth.cpu().numpy(), np.inf)
                size = self.prior.patch_size
                e_m = patch_reprojection_error(self.images, self.cameras, view, pixel, z_m, target, size)
                e_a = patch_reprojection_error(self.images, self.cameras, view, pixel, z_a, target, size)
                mask_aug, mask_main = (m.to(batch.near.device) for m in reliable_depth_masks(
                    torch.from_numpy(e_m), torch.from_numpy(e_a), self.prior.error_threshold))
        return {"augmented": {"outputs": aug, "mask_main": mask_main, "mask_aug": mask_aug,
                              "scale": scene_depth_scale(main), "intervals": self.prior.mass_intervals,
                              "disparity": not main.bounded}}


@register_loss_term("augmented_photometric")
def augmented_photometric(inputs: LossInputs) -> Tensor:
    """The augmented model's photometric loss (display-encoded MSE, as ``photometric``)."""
    entry = inputs.extras.get("augmented")
    if not entry:
        return inputs.outputs.color.new_zeros(())
    return (srgb_encode(entry["outputs"].color) - srgb_encode(inputs.batch.color)).square().mean()


@register_loss_term("mass_concentration")
def mass_concentration_term(inputs: LossInputs) -> Tensor:
    """Eq. 4.15 on the augmented model's weights, mean over rays (intervals from ``extras["augmented"]``)."""
    entry = inputs.extras.get("augmented")
    if not entry:
        return inputs.outputs.color.new_zeros(())
    return mass_concentration(entry["outputs"].weights, entry.get("intervals", 5)).mean()


@register_loss_term("augmented_depth")
def augmented_depth(inputs: LossInputs) -> Tensor:
    """Eq. 4.9: ``m_a (z_m - SG(z_a))^2 + m_m (SG(z_m) - z_a)^2`` / scale^2, mean over the batch.

    Forward-facing scenes compare disparities ``near / z`` instead (Simple-NeRF works in NDC, whose depth
    is affine in disparity): a depth near infinity (the last sample's interval reaches 1e10) would
    otherwise give squared errors of ~1e20 and blow the run up."""
    entry = inputs.extras.get("augmented")
    if not entry:
        return inputs.outputs.color.new_zeros(())
    m_a, m_m = entry["mask_aug"], entry["mask_main"]
    if not bool((m_a | m_m).any()):
        return inputs.outputs.color.new_zeros(())
    z_m, z_a = inputs.outputs.depth, entry["outputs"].depth
    scale = entry["scale"]
    if entry.get("disparity"):  # near / z, in [0, 1] beyond the near plane; +inf depth -> 0
        z_m, z_a, scale = scale / z_m.clamp_min(1e-6), scale / z_a.clamp_min(1e-6), 1.0
    zeros = torch.zeros_like(z_m)
    main_term = torch.where(m_a, z_m - torch.where(m_a, z_a, zeros).detach(), zeros).square()
    aug_term = torch.where(m_m, torch.where(m_m, z_m, zeros).detach() - z_a, zeros).square()
    return (main_term + aug_term).sum() / (z_m.shape[0] * scale ** 2)
