"""Rays, samples along them, scene contraction and the occupancy grid.

Conventions (``engine/core/frames.py``): OpenCV cameras (x right, y down, z forward), rigid ``world_to_camera``
4x4, pixel (u, v) centred at (u + 0.5, v + 0.5) in the coordinates K maps to.

**Ray parameter = planar depth.** :func:`camera_rays` returns directions ``R^T K^-1 [u + 0.5, v + 0.5, 1]``,
whose camera-space z is exactly 1, so the point ``o + t d`` lies at camera depth ``t``: sample positions,
near/far bounds and rendered depth are all *planar* depth (camera z), the project's depth convention, and
directly comparable with rgbd-seq depth maps. Densities are per scene unit, so rendering multiplies
``t`` intervals by ``|d|`` (see ``models/fields/components/render.py``).

**Contraction** maps world points into the field's cube [-1, 1]^3:

- ``bounded-360``: an axis-aligned box, ``(p - center) / half_size``. Rays are clipped to the box (slab
  test); rays that miss it get zero-length intervals, so zero weight (pure background). A camera inside
  the box starts its rays at ``near``.
- ``forward-facing``: the NDC of a reference camera (the mean training pose): ``x = 2 (fx X/Z + cx) / W - 1``,
  ``y = 2 (fy Y/Z + cy) / H - 1`` (both divided by ``1 + margin`` so views beside the reference fit),
  ``z = 1 - 2 near / Z``, which maps ``Z = near`` to -1 and ``Z = inf`` to +1 (NeRF's LLFF NDC, written
  for OpenCV axes and any pose instead of re-parameterising rays). Samples are placed uniformly in inverse
  depth (disparity) between ``near`` and ``far`` along each ray's own camera z; an infinite ``far`` is
  replaced by :data:`FAR_AT_INFINITY` (the last interval then absorbs whatever is left, like NeRF's 1e10).
"""
from __future__ import annotations

from typing import Callable, Optional

import numpy as np
import torch
from torch import Tensor, nn

__all__ = ["FAR_AT_INFINITY", "camera_rays", "ray_box_intersection", "sample_intervals", "contract_box",
           "contract_ndc", "OccupancyGrid"]

#: Smallest near bound used when sampling in disparity (keeps 1 / near finite).
#: Stand-in for an infinite far bound in disparity sampling (scene units along camera z).
from engine.fields.render import FAR_AT_INFINITY  # noqa: E402  (shared with the engine)
from engine.fields.render import MIN_NEAR  # noqa: E402
from engine.fields.render import camera_rays_np  # noqa: E402  (one implementation, shared with the engine)

#: "Unbounded" ray parameter of a slab a ray runs parallel to (finite, so no inf - inf).
_NO_LIMIT = 1e30


def camera_rays(intrinsics, world_to_camera, height: int, width: int, *,
                dtype: torch.dtype = torch.float32) -> tuple[Tensor, Tensor]:
    """Rays through every pixel centre, row-major (row v, then column u).

    Args:
        intrinsics: (3, 3) pinhole K (numpy or torch).
        world_to_camera: (4, 4) rigid transform (numpy or torch).

    Returns:
        origins (H * W, 3) (the camera centre, world), directions (H * W, 3): world directions whose
        camera-space z is 1 (unnormalised), so ``t`` along them is planar depth.

    Example:
        >>> o, d = camera_rays(np.array([[2., 0, 2], [0, 2, 1], [0, 0, 1]]), np.eye(4), 2, 4)
        >>> d[1].tolist()  # pixel (u=1, v=0): centre (1.5, 0.5)
        [-0.25, -0.25, 1.0]
    """
    k = np.asarray(intrinsics.detach().cpu() if isinstance(intrinsics, Tensor) else intrinsics, dtype=np.float64)
    t = np.asarray(world_to_camera.detach().cpu() if isinstance(world_to_camera, Tensor) else world_to_camera,
                   dtype=np.float64)
    origin, dirs = camera_rays_np(k, t, height, width)
    origins = np.broadcast_to(origin, dirs.shape)
    return torch.as_tensor(np.ascontiguousarray(origins), dtype=dtype), torch.as_tensor(dirs, dtype=dtype)


def ray_box_intersection(origins: Tensor, directions: Tensor, box_min: Tensor, box_max: Tensor
                         ) -> tuple[Tensor, Tensor]:
    """Slab test: ray parameters where rays enter and leave an axis-aligned box.

    Args:
        origins, directions: (R, 3).
        box_min, box_max: (3,).

    Returns:
        t_enter, t_exit (R,): the ray misses the box where ``t_exit <= t_enter`` (or ``t_exit < 0``).
        ``t_enter`` is negative when the origin is inside. Zero direction components are handled without
        NaN or inf: such a slab holds the ray for every t (origin between its faces, faces included) or for
        none. Computed in at least float32.
    """
    dtype = torch.promote_types(directions.dtype, torch.float32)
    o, d = origins.to(dtype), directions.to(dtype)
    lo, hi = box_min.to(dtype), box_max.to(dtype)
    parallel = d == 0
    inv = 1.0 / torch.where(parallel, torch.ones_like(d), d)
    t0, t1 = (lo - o) * inv, (hi - o) * inv
    # a ray parallel to a slab is inside it for all t (origin within, faces included) or for none
    inside = (o >= lo) & (o <= hi)
    big = torch.full_like(d, _NO_LIMIT)
    t_lo = torch.where(parallel, torch.where(inside, -big, big), torch.minimum(t0, t1))
    t_hi = torch.where(parallel, torch.where(inside, big, -big), torch.maximum(t0, t1))
    t_enter = t_lo.amax(dim=-1).to(origins.dtype)
    t_exit = t_hi.amin(dim=-1).to(origins.dtype)
    return t_enter, t_exit


def sample_intervals(t_near: Tensor, t_far: Tensor, num_samples: int, *, spacing: str = "linear",
                     jitter: bool = False, generator: Optional[torch.Generator] = None) -> tuple[Tensor, Tensor]:
    """Stratified samples: ``num_samples`` equal bins between near and far, one sample per bin.

    Args:
        t_near, t_far: (R,) ray-parameter bounds; ``t_far <= t_near`` gives zero-length bins (zero weight).
        spacing: ``"linear"`` in t, or ``"disparity"`` (uniform in 1 / t; needs t_near > 0).
        jitter: place each sample uniformly at random inside its bin (training); else at the bin centre
            (in the spacing's own variable).

    Returns:
        t (R, N) sample positions, increasing along each ray; deltas (R, N) >= 0, the length of the bin
        each sample stands for (they tile [t_near, max(t_near, t_far)] exactly).
    """
    r = t_near.shape[0]
    t_far = torch.maximum(t_far, t_near)
    steps = torch.linspace(0.0, 1.0, num_samples + 1, dtype=t_near.dtype, device=t_near.device)
    if jitter:
        offsets = torch.rand((r, num_samples), generator=generator, dtype=t_near.dtype).to(t_near.device)
    else:
        offsets = torch.full((r, num_samples), 0.5, dtype=t_near.dtype, device=t_near.device)
    u_samples = (torch.arange(num_samples, dtype=t_near.dtype, device=t_near.device) + offsets) / num_samples
    if spacing == "linear":
        edges = torch.lerp(t_near[:, None].expand(-1, num_samples + 1), t_far[:, None].expand(-1, num_samples + 1),
                           steps.expand(r, -1))
        t = torch.lerp(t_near[:, None].expand(-1, num_samples), t_far[:, None].expand(-1, num_samples), u_samples)
    elif spacing == "disparity":
        near = t_near.clamp_min(MIN_NEAR)[:, None]
        far = torch.clamp(t_far[:, None], max=FAR_AT_INFINITY)
        far = torch.maximum(far, near)
        s_near, s_far = 1.0 / near, 1.0 / far
        edges = 1.0 / torch.lerp(s_near, s_far, steps.expand(r, -1))  # lerp is exact at both ends
        t = 1.0 / torch.lerp(s_near.expand(-1, num_samples), s_far.expand(-1, num_samples), u_samples)
    else:
        raise ValueError(f"spacing must be 'linear' or 'disparity', got {spacing!r}")
    deltas = (edges[:, 1:] - edges[:, :-1]).clamp_min(0.0)
    return t, deltas


def contract_box(points: Tensor, center: Tensor, half_size: Tensor) -> Tensor:
    """World points (..., 3) -> box coordinates (..., 3); the box is [-1, 1]^3."""
    return (points - center) / half_size


def contract_ndc(points: Tensor, intrinsics: Tensor, world_to_camera: Tensor, width: float, height: float,
                 near: float, margin: float = 0.0) -> Tensor:
    """World points (..., 3) -> NDC of a reference camera (..., 3); the visible frustum beyond ``near`` is
    [-1, 1]^3 (x, y shrunk by ``1 + margin``). Points at or behind the camera plane map to z < -1 (outside).
    """
    cam = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    z = cam[..., 2]
    z_safe = torch.where(z > 0, z, torch.full_like(z, torch.finfo(z.dtype).tiny))
    u = (intrinsics[0, 0] * cam[..., 0] + intrinsics[0, 1] * cam[..., 1]) / z_safe + intrinsics[0, 2]
    v = intrinsics[1, 1] * cam[..., 1] / z_safe + intrinsics[1, 2]
    x = (2.0 * u / width - 1.0) / (1.0 + margin)
    y = (2.0 * v / height - 1.0) / (1.0 + margin)
    nz = torch.where(z > 0, 1.0 - 2.0 * near / z_safe, torch.full_like(z, -2.0))
    out = torch.stack([x, y, nz], dim=-1)
    # behind the camera: push far outside the cube so the sample is dropped
    return torch.where((z > 0)[..., None], out, torch.full_like(out, -2.0))


class OccupancyGrid(nn.Module):
    """A binary occupancy grid over the contracted cube [-1, 1]^3 for empty-space skipping.

    ``density`` holds an exponential moving maximum of the field's density at jittered cell positions
    (instant-NGP / nerfacc style); ``occupied`` is ``density > min(threshold, mean density)`` (the mean
    keeps early updates from emptying the grid). Indexing is ``[ix, iy, iz]`` along contracted x, y, z.
    Updating is a training callback; querying is one gather.
    """

    def __init__(self, resolution: int = 64):
        super().__init__()
        self.resolution = int(resolution)
        r = self.resolution
        self.register_buffer("density", torch.zeros(r, r, r))
        self.register_buffer("occupied", torch.ones(r, r, r, dtype=torch.bool))
        self.register_buffer("updates", torch.zeros((), dtype=torch.long))

    def query(self, coords: Tensor) -> Tensor:
        """(..., 3) contracted coordinates -> (...) bool, False outside the cube."""
        r = self.resolution
        inside = (coords.abs() <= 1.0).all(dim=-1)
        idx = ((coords + 1.0) * (0.5 * r)).floor().long().clamp(0, r - 1)
        flat = (idx[..., 0] * r + idx[..., 1]) * r + idx[..., 2]
        return self.occupied.reshape(-1)[flat] & inside

    @torch.no_grad()
    def update(self, density_fn: Callable[[Tensor], Tensor], threshold: float, *, decay: float = 0.95,
               generator: Optional[torch.Generator] = None, chunk: int = 1 << 16) -> float:
        """Re-evaluate every cell at a jittered position; returns the occupied fraction.

        Args:
            density_fn: (M, 3) contracted coordinates -> (M,) density.
            threshold: density above which a cell is occupied (capped by the grid's mean density).
        """
        r = self.resolution
        axis = torch.arange(r, dtype=torch.float32)
        cells = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1).reshape(-1, 3)
        jitter = torch.rand(cells.shape, generator=generator)
        coords = ((cells + jitter) / r * 2.0 - 1.0).to(self.density.device)
        new = torch.cat([density_fn(coords[i:i + chunk]).float() for i in range(0, coords.shape[0], chunk)])
        self.density.copy_(torch.maximum(self.density * decay, new.reshape(r, r, r)))
        cut = min(float(threshold), float(self.density.mean()))
        self.occupied.copy_(self.density > cut)
        self.updates += 1
        return float(self.occupied.float().mean())
