"""Volume rendering (thesis Eq. 3.3-3.5, 4.2), computed stably, and chunked rendering of whole images.

For samples i = 1..N along a ray with densities ``sigma_i`` (per scene unit) and interval lengths
``delta_i`` (scene units), with optical depth ``tau_i = sigma_i delta_i``:

    T_i = exp(-sum_{j<i} tau_j)            (exclusive: T_1 = 1)
    w_i = T_i (1 - exp(-tau_i))             (Eq. 4.2)

computed in log space: the exclusive cumulative sum of ``tau`` is formed first and exponentiated once, and
``1 - exp(-tau)`` is ``-expm1(-tau)`` (exact for tiny tau). Huge optical depths make ``exp`` underflow to
exactly 0, never NaN; ``tau = inf`` gives alpha 1 and zero transmittance behind it. The sum runs in at least
float32 whatever the input dtype (fp16 inputs give fp16 outputs, finite). ``sum_i w_i = 1 - T_{N+1} <= 1``
(up to one rounding).

Outputs per ray (:class:`RayOutputs`):

- ``color = sum_i w_i c_i + (1 - opacity) * background`` (linear RGB; white for NeRF-synthetic, black
  otherwise),
- ``opacity = sum_i w_i`` (accumulated alpha),
- ``expected_depth = sum_i w_i t_i`` (the thesis's z, Eq. 3.13; 0 where nothing is hit) -- what depth
  losses use,
- ``depth = expected_depth / opacity`` where ``opacity >= OPACITY_EPS``, else ``+inf`` ("no surface",
  the project's sky convention). Sample positions ``t`` are planar depth (camera z, see
  ``models/fields/components/sampling.py``), so both depths are planar.
"""
from __future__ import annotations

import time
from typing import NamedTuple, Sequence

import numpy as np
import torch
from torch import Tensor

from engine.core.checks import check_shape
from engine.core.errors import InputError
from models.fields.components.sampling import camera_rays

__all__ = ["OPACITY_EPS", "RayOutputs", "volume_weights", "composite", "composite_samples", "render_image",
           "stack_outputs", "module_device"]

#: Opacity below which a ray has "no surface": its normalised depth is +inf.
from engine.fields.render import OPACITY_EPS  # noqa: E402  (shared with the engine)


class RayOutputs(NamedTuple):
    """Rendered rays. R rays, N samples each.

    Attributes:
        color: (R, 3) linear RGB composited on the background.
        depth: (R,) planar depth ``sum w t / opacity``; +inf where opacity < OPACITY_EPS.
        expected_depth: (R,) ``sum w t`` (unnormalised, finite, 0 for empty rays).
        opacity: (R,) ``sum w`` in [0, 1].
        weights: (R, N) w_i.
        transmittance: (R, N) T_i (exclusive).
        t: (R, N) sample positions (planar depth).
    """

    color: Tensor
    depth: Tensor
    expected_depth: Tensor
    opacity: Tensor
    weights: Tensor
    transmittance: Tensor
    t: Tensor


def _weights(sigma: Tensor, deltas: Tensor) -> tuple[Tensor, Tensor]:
    dtype = torch.promote_types(sigma.dtype, torch.float32)
    sigma_, deltas_ = sigma.to(dtype), deltas.to(dtype)
    empty = (sigma_ == 0) | (deltas_ == 0)  # 0 * inf is an empty interval, not NaN (a NaN density stays NaN)
    tau = torch.where(empty, torch.zeros_like(sigma_), sigma_ * deltas_)
    alpha = -torch.expm1(-tau)
    excl = torch.cumsum(tau, dim=-1)
    excl = torch.cat([torch.zeros_like(excl[..., :1]), excl[..., :-1]], dim=-1)
    trans = torch.exp(-excl)
    return (trans * alpha).to(sigma.dtype), trans.to(sigma.dtype)


def volume_weights(sigma: Tensor, deltas: Tensor) -> tuple[Tensor, Tensor]:
    """Rendering weights (Eq. 4.2) and transmittance, stably in log space.

    Args:
        sigma: (..., N) densities >= 0 (per scene unit), near to far.
        deltas: (..., N) interval lengths >= 0 (scene units). ``sigma * delta`` of ``0 * inf`` counts as 0.

    Returns:
        weights (..., N) in [0, 1], summing to <= 1 per ray; transmittance (..., N), T_1 = 1.

    Example:
        >>> w, t = volume_weights(torch.tensor([[0.0, 1e30, 5.0]]), torch.ones(1, 3))
        >>> w.tolist(), t.tolist()
        ([[0.0, 1.0, 0.0]], [[1.0, 1.0, 0.0]])
    """
    sizes: dict = {}
    check_shape(sigma, "sigma", ("...", "N"), sizes)
    check_shape(deltas, "deltas", ("...", "N"), sizes)
    if sigma.shape != deltas.shape:
        raise InputError(f"has shape {tuple(deltas.shape)}, sigma has {tuple(sigma.shape)}", field="deltas")
    return _weights(sigma, deltas)


def _composite(weights: Tensor, colors: Tensor, t: Tensor, background: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    opacity = weights.sum(dim=-1)
    color = (weights[..., None] * colors).sum(dim=-2) + (1.0 - opacity)[..., None] * background
    expected = (weights * t).sum(dim=-1)
    hit = opacity >= OPACITY_EPS
    depth = torch.where(hit, expected / opacity.clamp_min(OPACITY_EPS), torch.full_like(expected, float("inf")))
    return color, depth, expected, opacity


def composite(weights: Tensor, colors: Tensor, t: Tensor, background: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Composite samples front to back onto a background (Eq. 3.5 plus the background term).

    Args:
        weights: (R, N) from :func:`volume_weights`.
        colors: (R, N, 3) linear RGB per sample.
        t: (R, N) sample positions (planar depth).
        background: (3,) or (R, 3) linear RGB.

    Returns:
        color (R, 3), depth (R,) (+inf where opacity < OPACITY_EPS), expected_depth (R,) (``sum w t``),
        opacity (R,).
    """
    sizes: dict = {}
    check_shape(weights, "weights", ("R", "N"), sizes)
    check_shape(colors, "colors", ("R", "N", 3), sizes)
    check_shape(t, "t", ("R", "N"), sizes)
    return _composite(weights, colors, t, background)


def composite_samples(sigma: Tensor, colors: Tensor, lengths: Tensor, t: Tensor, background: Tensor) -> RayOutputs:
    """Volume-render samples (the last step of every ray marcher): :func:`volume_weights` of ``sigma`` (R, N)
    over interval ``lengths`` (R, N, scene units), then :func:`composite` of ``colors`` (R, N, 3) at planar
    depths ``t`` (R, N) onto ``background``. The marchers call it with checked shapes, so it checks none."""
    weights, trans = _weights(sigma, lengths)
    color, depth, expected, opacity = _composite(weights, colors, t, background)
    return RayOutputs(color, depth, expected, opacity, weights, trans, t)


def module_device(module) -> torch.device:
    """The device of a module's first parameter (or buffer); for a wrapper that is no module (a dynamic
    field's time slice), that of the ``model`` it wraps; the CPU otherwise."""
    if isinstance(module, torch.nn.Module):
        for tensor in module.parameters():
            return tensor.device
        for tensor in module.buffers():
            return tensor.device
        return torch.device("cpu")
    inner = getattr(module, "model", None)
    return module_device(inner) if inner is not None else torch.device("cpu")


@torch.no_grad()
def render_image(model, intrinsics, world_to_camera, height: int, width: int, near: float, far: float, *,
                 chunk: int = 8192) -> dict[str, np.ndarray]:
    """Render a full image in chunks of rays with a model's ``render_rays`` (no gradients, eval samples).

    Args:
        model: anything with ``render_rays(origins, directions, near, far) -> RayOutputs`` (e.g.
            :class:`models.fields.static.model.StaticFieldModel`).
        intrinsics, world_to_camera: the camera (OpenCV conventions).
        near, far: planar-depth bounds of the rays.

    Returns:
        ``color`` (H, W, 3) float32 linear RGB, ``depth`` (H, W) float32 planar (+inf: no surface),
        ``opacity`` (H, W) float32, ``seconds`` (wall time of the rendering, excluding ray generation).
    """
    device = module_device(model)
    origins, directions = (x.to(device) for x in camera_rays(intrinsics, world_to_camera, height, width))
    n = origins.shape[0]
    near_t = torch.full((n,), float(near), device=device)
    far_t = torch.full((n,), float(far), device=device)
    colors, depths, opacities = [], [], []
    start = time.perf_counter()
    for i in range(0, n, chunk):
        out = model.render_rays(origins[i:i + chunk], directions[i:i + chunk], near_t[i:i + chunk], far_t[i:i + chunk])
        colors.append(out.color)
        depths.append(out.depth)
        opacities.append(out.opacity)
    seconds = time.perf_counter() - start
    return {"color": torch.cat(colors).reshape(height, width, 3).float().cpu().numpy(),
            "depth": torch.cat(depths).reshape(height, width).float().cpu().numpy(),
            "opacity": torch.cat(opacities).reshape(height, width).float().cpu().numpy(),
            "seconds": np.float64(seconds)}


def stack_outputs(parts: Sequence[RayOutputs]) -> RayOutputs:
    """Concatenate chunks of rendered rays (same N)."""
    return RayOutputs(*(torch.cat(items, dim=0) for items in zip(*parts)))

