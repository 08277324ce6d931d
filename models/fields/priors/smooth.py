"""RegNeRF's depth smoothness (Niemeyer et al. 2022) on patches seen from virtual cameras.

Each step ``patches`` square patches of ``patch_size`` x ``patch_size`` pixels are rendered from virtual
cameras between the training views (:func:`virtual_cameras`: the centre a random convex combination of the
training cameras' centres, the rotation the same combination of their rotations projected back onto SO(3),
the intrinsics of a random training camera), at random places in the image. The loss
(:func:`patch_smoothness`) is the mean squared difference of each pixel's depth with its right and lower
neighbour in the patch. Depth is the ray's planar depth in the virtual camera (the rays' directions have
camera z = 1), so a plane fronto-parallel to that camera costs nothing; bounded scenes divide it by the
scene's depth scale, forward-facing ones use the disparity ``sum_i w_i near / t_i`` as the depth prior does
(NDC depth, as RegNeRF on LLFF: the sky at disparity 0 cannot dominate).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from engine.core.errors import InputError
from models.fields.components.render import module_device
from models.fields.losses import LossInputs, register_loss_term
from models.fields.priors.depth import scene_depth_scale

__all__ = ["SmoothPrior", "patch_smoothness", "virtual_cameras", "patch_rays", "SmoothState"]


@dataclass
class SmoothPrior:
    """RegNeRF's depth smoothness on patches from virtual cameras between the training views."""

    enabled: bool = field(default=False, metadata={
        "help": "render depth patches from virtual cameras between the training views and penalise their roughness"})
    weight: float = field(default=0.1, metadata={"help": "its weight (mean squared neighbour difference)"})
    patches: int = field(default=4, metadata={"help": "patches rendered per step (one virtual camera each)"})
    patch_size: int = field(default=8, metadata={"help": "side of a patch in pixels (RegNeRF: 8)"})

    def validate(self) -> "SmoothPrior":
        """Raise InputError naming the first bad option; returns self."""
        if self.patches < 1:
            raise InputError(f"must be >= 1, got {self.patches}", field="priors.smooth.patches")
        if self.patch_size < 2:
            raise InputError(f"must be >= 2, got {self.patch_size}", field="priors.smooth.patch_size")
        return self


def patch_smoothness(depth: Tensor) -> Tensor:
    """Mean over patches of the mean squared difference between horizontally and vertically neighbouring
    depths (RegNeRF's depth smoothness), from (P, S, S) depths; a scalar."""
    if depth.ndim != 3 or depth.shape[1] != depth.shape[2] or depth.shape[1] < 2:
        raise InputError(f"must be (P, S, S) with S >= 2, got {tuple(depth.shape)}", field="depth")
    dx = (depth[:, :, 1:] - depth[:, :, :-1]).square().mean(dim=(1, 2))
    dy = (depth[:, 1:, :] - depth[:, :-1, :]).square().mean(dim=(1, 2))
    return (dx + dy).mean()


def _project_to_rotation(matrix: np.ndarray) -> np.ndarray:
    """The rotation nearest (Frobenius) to a 3x3 matrix."""
    u, _, vt = np.linalg.svd(matrix)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def virtual_cameras(world_to_camera: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(P, 4, 4) world-to-camera of virtual cameras between N training cameras (N, 4, 4): camera p's centre
    is ``sum_n weights[p, n] c_n`` and its rotation the nearest rotation to ``sum_n weights[p, n] R_n``
    (``weights`` (P, N), rows convex: non-negative, summing to 1)."""
    w2c = np.asarray(world_to_camera, np.float64)
    weights = np.asarray(weights, np.float64)
    if w2c.ndim != 3 or w2c.shape[1:] != (4, 4):
        raise InputError(f"must be (N, 4, 4), got {w2c.shape}", field="world_to_camera")
    if weights.ndim != 2 or weights.shape[1] != len(w2c):
        raise InputError(f"must be (P, {len(w2c)}), got {weights.shape}", field="weights")
    rot = w2c[:, :3, :3]
    centres = -np.einsum("nji,nj->ni", rot, w2c[:, :3, 3])  # c = -R^T t
    out = np.tile(np.eye(4), (len(weights), 1, 1))
    for p, w in enumerate(weights):
        r = _project_to_rotation(np.einsum("n,nij->ij", w, rot))
        out[p, :3, :3] = r
        out[p, :3, 3] = -r @ (w @ centres)
    return out


def patch_rays(intrinsics: np.ndarray, world_to_camera: np.ndarray, corners: np.ndarray, size: int
               ) -> tuple[np.ndarray, np.ndarray]:
    """Rays through the pixel centres (+0.5) of P patches of ``size`` x ``size`` pixels whose top-left pixels
    are ``corners`` (P, 2) (u, v) in cameras ``world_to_camera`` (P, 4, 4) with ``intrinsics`` (P, 3, 3):
    origins (P, S, S, 3), directions (P, S, S, 3) with camera z = 1 (``d = R^T K^-1 [u, v, 1]``)."""
    du, dv = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5)  # (S, S), row = v
    pix = np.stack([corners[:, 0, None, None] + du, corners[:, 1, None, None] + dv,
                    np.ones((len(corners), size, size))], axis=-1)
    cam = np.einsum("pij,pabj->pabi", np.linalg.inv(intrinsics), pix)
    rot = world_to_camera[:, :3, :3]
    dirs = np.einsum("pji,pabj->pabi", rot, cam)  # R^T applied
    centres = -np.einsum("pji,pj->pi", rot, world_to_camera[:, :3, 3])
    return np.broadcast_to(centres[:, None, None], dirs.shape).copy(), dirs


class SmoothState:
    """The smoothness prior of one run: the training cameras it places virtual cameras between."""

    def __init__(self, views, prior: SmoothPrior):
        self.prior = prior.validate()
        self.w2c = np.stack([np.asarray(c.world_to_camera, np.float64) for c in views.cameras])
        self.intrinsics = np.stack([np.asarray(c.intrinsics, np.float64) for c in views.cameras])
        self.width, self.height = int(views.width), int(views.height)
        if self.width < prior.patch_size or self.height < prior.patch_size:
            raise InputError(f"{prior.patch_size} is larger than the {self.width}x{self.height} images",
                             field="priors.smooth.patch_size")

    def extras(self, model, generator: torch.Generator) -> dict[str, Any]:
        """Render this step's patches: ``{"smooth": {"outputs", "shape", "scale", "disparity"}}``."""
        p, s = self.prior.patches, self.prior.patch_size
        n = len(self.w2c)
        draw = torch.rand(p, n + 3, generator=generator, device=generator.device).cpu().numpy().astype(np.float64)
        weights = -np.log(np.clip(draw[:, :n], 1e-12, 1.0))  # Exp(1): normalised, uniform on the simplex
        weights /= weights.sum(axis=1, keepdims=True)
        cams = virtual_cameras(self.w2c, weights)
        intr = self.intrinsics[np.minimum((draw[:, n] * n).astype(np.int64), n - 1)]
        corners = np.stack([np.floor(draw[:, n + 1] * (self.width - s + 1)),
                            np.floor(draw[:, n + 2] * (self.height - s + 1))], axis=-1)
        origins, dirs = patch_rays(intr, cams, corners, s)
        device = module_device(model)
        count = p * s * s
        near = torch.full((count,), float(model.scene.near), device=device)
        far = torch.full((count,), float(model.scene.far), device=device)
        outputs = model.render_rays(torch.as_tensor(origins.reshape(-1, 3), dtype=torch.float32, device=device),
                                    torch.as_tensor(dirs.reshape(-1, 3), dtype=torch.float32, device=device),
                                    near, far, jitter=True, generator=generator)
        return {"smooth": {"outputs": outputs, "shape": (p, s, s), "scale": scene_depth_scale(model),
                           "disparity": not model.bounded}}


@register_loss_term("depth_smoothness")
def depth_smoothness(inputs: LossInputs) -> Tensor:
    """:func:`patch_smoothness` of the patches in ``extras["smooth"]`` (disparity ``sum w near / t`` for
    forward-facing scenes, expected depth / scale for bounded ones); 0 without them."""
    entry = inputs.extras.get("smooth")
    if not entry:
        return inputs.outputs.color.new_zeros(())
    out = entry["outputs"]
    if entry["disparity"]:
        depth = (out.weights * (entry["scale"] / out.t.clamp_min(1e-6))).sum(dim=-1)
    else:
        depth = out.expected_depth / entry["scale"]
    return patch_smoothness(depth.reshape(entry["shape"]))
