"""Depth smoothness from unseen viewpoints (RegNeRF, Niemeyer et al. 2022, Sec. 3.2): a geometry-only prior.

Each step renders ``patches`` square patches of ``patch_size`` x ``patch_size`` pixel-centre rays from virtual
cameras between the training cameras and penalises the squared difference of neighbouring pixels' depths,
across and down (:func:`patch_depth_smoothness`). It acts on the density alone (the weights along each ray),
so unlike the plane TV it leaves the colour features, i.e. the texture, free.

Virtual cameras (:func:`virtual_cameras`): two training cameras ``a != b`` drawn at random (``a`` alone when there
is one), ``s`` uniform in [0, 1]; the centre is ``(1 - s) c_a + s c_b``, the camera-to-world rotation
``C_a exp(s log(C_a^T C_b))`` (geodesic), the intrinsics ``a``'s. A patch's top-left pixel is uniform over the
image, so the patch lies inside it; pixel (u, v)'s centre is at (u + 0.5, v + 0.5) (``engine/core/frames.py``).

Depth is compared as in the sparse depth prior (``priors/depth.py``): forward-facing scenes in disparity
``sum_i w_i near / t_i`` (RegNeRF smooths NDC depth, an affine function of it; empty remainder = disparity 0),
bounded ones as ``sum_i w_i t_i / scale``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
import torch
from torch import Tensor

from engine.core.errors import InputError
from engine.geometry.rigid import rotation_exp, rotation_log
from models.fields.components.render import module_device
from models.fields.losses import LossInputs, register_loss_term
from models.fields.priors.depth import scene_depth_scale

__all__ = ["DepthSmoothPrior", "virtual_cameras", "patch_rays", "patch_depth_smoothness", "SmoothState"]


@dataclass
class DepthSmoothPrior:
    """RegNeRF's depth smoothness on patches rendered from virtual cameras between the training ones."""

    enabled: bool = field(default=False, metadata={
        "help": "render patches from virtual cameras and smooth their depth (loss depth_smoothness)"})
    weight: float = field(default=0.1, metadata={"help": "weight of the mean squared neighbour depth difference"})
    patches: int = field(default=8, metadata={"help": "patches rendered per step"})
    patch_size: int = field(default=8, metadata={"help": "side of a patch in pixels (>= 2)"})
    start_step: int = field(default=0, metadata={"help": "first step at which the loss is applied"})


def virtual_cameras(positions: np.ndarray, rotations: np.ndarray, pick: np.ndarray, other: np.ndarray,
                    s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cameras between training cameras: centres (P, 3) and camera-to-world rotations (P, 3, 3).

    Args:
        positions: (V, 3) training camera centres (world).
        rotations: (V, 3, 3) training camera-to-world rotations.
        pick, other: (P,) ints, the two cameras of each virtual one.
        s: (P,) in [0, 1], the step from ``pick`` (0) to ``other`` (1).
    """
    positions = np.asarray(positions, np.float64)
    rotations = np.asarray(rotations, np.float64)
    if positions.ndim != 2 or positions.shape[1] != 3 or rotations.shape != (len(positions), 3, 3):
        raise ValueError(f"positions (V, 3) and rotations (V, 3, 3) expected, got {positions.shape} and "
                         f"{rotations.shape}")
    centres = (1.0 - s)[:, None] * positions[pick] + s[:, None] * positions[other]
    rots = np.stack([rotations[a] @ rotation_exp(t * rotation_log(rotations[a].T @ rotations[b]))
                     for a, b, t in zip(pick, other, s)]) if len(pick) else np.zeros((0, 3, 3))
    return centres, rots


def patch_rays(centres: np.ndarray, rotations: np.ndarray, intrinsics: np.ndarray, corners: np.ndarray,
               size: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays of square pixel patches: origins and directions (P * size * size, 3), patch-major then row-major,
    directions with camera z = 1 (``C K^-1 [u + 0.5, v + 0.5, 1]``).

    Args:
        centres: (P, 3) camera centres; rotations: (P, 3, 3) camera-to-world; intrinsics: (P, 3, 3).
        corners: (P, 2) top-left pixel (u, v) of each patch; size: the patch side.
    """
    n = len(centres)
    grid_v, grid_u = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
    u = corners[:, 0, None, None] + grid_u + 0.5
    v = corners[:, 1, None, None] + grid_v + 0.5
    pix = np.stack([u, v, np.ones_like(u)], axis=-1).reshape(n, size * size, 3)
    cam = pix @ np.transpose(np.linalg.inv(intrinsics), (0, 2, 1))
    dirs = cam @ np.transpose(rotations, (0, 2, 1))
    origins = np.broadcast_to(centres[:, None, :], dirs.shape)
    return origins.reshape(-1, 3), dirs.reshape(-1, 3)


def patch_depth_smoothness(depth: Tensor) -> Tensor:
    """RegNeRF's depth smoothness of patches (P, S, S): the mean over patches of the summed squared
    differences of horizontal and of vertical neighbours, each averaged over its pairs."""
    if depth.ndim != 3 or depth.shape[1] != depth.shape[2] or depth.shape[1] < 2:
        raise ValueError(f"patches (P, S, S) with S >= 2 expected, got {tuple(depth.shape)}")
    across = (depth[:, :, 1:] - depth[:, :, :-1]).square().mean()
    down = (depth[:, 1:, :] - depth[:, :-1, :]).square().mean()
    return across + down


class SmoothState:
    """The depth-smoothness prior of one run: the training cameras, and the patches it renders each step."""

    def __init__(self, views, prior: DepthSmoothPrior):
        self.prior = prior
        cameras: Sequence = list(views.cameras)
        self.positions = np.stack([np.asarray(c.position, np.float64) for c in cameras])
        self.rotations = np.stack([np.asarray(c.world_to_camera, np.float64)[:3, :3].T for c in cameras])
        self.intrinsics = np.stack([np.asarray(c.intrinsics, np.float64) for c in cameras])
        self.height, self.width = int(views.images.shape[1]), int(views.images.shape[2])
        if prior.patch_size > min(self.height, self.width):
            raise InputError(f"must be at most the views' {self.width}x{self.height} pixels, got {prior.patch_size}",
                             field="priors.smooth.patch_size")

    def extras(self, model, generator: torch.Generator) -> dict[str, Any]:
        """Render this step's patches: ``{"depth_smoothness": {"outputs", "size", "scale", "disparity"}}``."""
        p, size = self.prior.patches, self.prior.patch_size
        n = len(self.positions)
        draw = torch.rand((p, 5), generator=generator, device=generator.device, dtype=torch.float64).cpu().numpy()
        pick = np.minimum((draw[:, 0] * n).astype(np.int64), n - 1)
        if n > 1:  # another camera, uniform over the other n - 1
            other = (pick + 1 + np.minimum((draw[:, 1] * (n - 1)).astype(np.int64), n - 2)) % n
        else:
            other = pick
        centres, rots = virtual_cameras(self.positions, self.rotations, pick, other, draw[:, 2])
        corners = np.stack([np.floor(draw[:, 3] * (self.width - size + 1)),
                            np.floor(draw[:, 4] * (self.height - size + 1))], axis=1).astype(np.int64)
        origins, dirs = patch_rays(centres, rots, self.intrinsics[pick], corners, size)
        device = module_device(model)
        rays = len(origins)
        near = torch.full((rays,), float(model.scene.near), device=device)
        far = torch.full((rays,), float(model.scene.far), device=device)
        outputs = model.render_rays(torch.as_tensor(origins, dtype=torch.float32, device=device),
                                    torch.as_tensor(dirs, dtype=torch.float32, device=device), near, far,
                                    jitter=True, generator=generator)
        return {"depth_smoothness": {"outputs": outputs, "size": size, "scale": scene_depth_scale(model),
                                     "disparity": not model.bounded}}


@register_loss_term("depth_smoothness")
def depth_smoothness(inputs: LossInputs) -> Tensor:
    """:func:`patch_depth_smoothness` of the patches in ``extras["depth_smoothness"]`` (disparity ``sum w near / t``
    for forward-facing scenes, ``sum w t / scale`` for bounded ones); 0 when there are none."""
    entry = inputs.extras.get("depth_smoothness")
    if not entry:
        return inputs.outputs.color.new_zeros(())
    out, size, scale = entry["outputs"], entry["size"], entry["scale"]
    if entry["disparity"]:
        depth = (out.weights * (scale / out.t.clamp_min(1e-6))).sum(dim=-1)
    else:
        depth = out.expected_depth / scale
    return patch_depth_smoothness(depth.reshape(-1, size, size))
