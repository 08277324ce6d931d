"""The model: field + scene contraction + sampler + renderer (nerfstudio's "model" layer).

:class:`StaticFieldModel` turns rays into :class:`~models.fields.components.render.RayOutputs`: clip each ray to the
scene (box or NDC frustum, ``models/fields/components/sampling.py``), place stratified samples (linear in depth for
``bounded-360``, linear in disparity for ``forward-facing``), drop samples outside the cube or in empty
occupancy cells, query the field on the rest only, and volume-render (``models/fields/components/render.py``).
Losses live in ``models/fields/losses.py`` and the training loop in ``models/fields/train_static.py``.

The scene description (:class:`SceneBox`) and the background colour are part of the model, saved with its
checkpoint, so a run directory renders without the data it was trained on.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, NamedTuple, Optional

import numpy as np
import torch
from torch import Tensor, nn

from engine.core.checks import check_shape
from engine.core.errors import InputError
from models.fields.components.render import RayOutputs, composite_samples
from models.fields.components.sampling import (OccupancyGrid, contract_box, contract_ndc, ray_box_intersection,
                                               sample_intervals)
from models.fields.data.views import box_from_cameras
from models.fields.static.field import FieldConfig, TriPlaneField

__all__ = ["SCENE_TYPES", "RenderConfig", "SceneBox", "PlacedSamples", "StaticFieldModel"]

SCENE_TYPES = ("bounded-360", "forward-facing")


class PlacedSamples(NamedTuple):
    """Samples placed along R rays by :meth:`StaticFieldModel.place_samples`, N a ray.

    Attributes:
        t: (R, N) sample positions (planar depth); lengths: (R, N) interval lengths (scene units).
        coords: (R, N, 3) contracted sample points; keep: (R, N) bool, the samples the field is evaluated at.
        idx: ``keep.nonzero(as_tuple=True)``, the kept samples' (ray, sample) indices, ray-major.
        unit: (R, 3) unit ray directions.
    """

    t: Tensor
    lengths: Tensor
    coords: Tensor
    keep: Tensor
    idx: tuple[Tensor, Tensor]
    unit: Tensor


@dataclass
class RenderConfig:
    """How rays are sampled and rendered."""

    num_samples: int = field(default=64, metadata={"help": "stratified samples per ray (before empty-space skipping)"})
    occupancy: Optional[bool] = field(default=None, metadata={
        "help": "use an occupancy grid to skip empty space (default: on for bounded-360, off for forward-facing)"})
    occupancy_resolution: int = field(default=64, metadata={"help": "occupancy grid cells per axis"})
    occupancy_alpha: float = field(default=0.01, metadata={
        "help": "a cell is occupied when one typical sample step through it has alpha above this"})
    occupancy_decay: float = field(default=0.95, metadata={
        "help": "decay of the grid's running max density per update"})
    ndc_margin: float = field(default=0.25, metadata={
        "help": "forward-facing: widen the reference frustum by this fraction so side views fit"})


@dataclass
class SceneBox:
    """Where the field lives, in world units (JSON-serialisable).

    Attributes:
        kind: ``bounded-360`` (an axis-aligned box) or ``forward-facing`` (NDC of a reference camera).
        near, far: planar-depth bounds of every ray (far may be inf for forward-facing).
        box_min, box_max: the box (bounded-360).
        ndc_intrinsics, ndc_world_to_camera, ndc_size: the reference camera (forward-facing); size (W, H).
    """

    kind: str
    near: float
    far: float
    box_min: Optional[list[float]] = None
    box_max: Optional[list[float]] = None
    ndc_intrinsics: Optional[list[list[float]]] = None
    ndc_world_to_camera: Optional[list[list[float]]] = None
    ndc_size: Optional[list[float]] = None

    def to_dict(self) -> dict[str, Any]:
        return {k: (None if v is None else (v if k == "kind" else _jsonable(v))) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "SceneBox":
        return cls(**data)

    @classmethod
    def from_views(cls, views) -> "SceneBox":
        """The scene of a :class:`~models.fields.data.views.Views`: its box (or one fitted to the cameras) for
        bounded-360, its mean pose as the NDC reference for forward-facing; near/far over all views."""
        near = float(np.min(views.near_far[:, 0]))
        far = float(np.max(views.near_far[:, 1]))
        if views.scene_type == "bounded-360":
            bounds = views.bounds if views.bounds is not None else box_from_cameras(
                views.cameras, views.height, views.width)
            return cls("bounded-360", near, far, box_min=[float(x) for x in bounds[0]],
                       box_max=[float(x) for x in bounds[1]])
        centers = np.stack([c.position for c in views.cameras])
        rotations = np.stack([c.world_to_camera[:3, :3] for c in views.cameras])
        u, _, vt = np.linalg.svd(rotations.mean(axis=0))
        rot = u @ vt
        if np.linalg.det(rot) < 0:
            rot = u @ np.diag([1.0, 1.0, -1.0]) @ vt
        w2c = np.eye(4)
        w2c[:3, :3] = rot
        w2c[:3, 3] = -rot @ centers.mean(axis=0)
        k = views.cameras[0].intrinsics
        return cls("forward-facing", near, far, ndc_intrinsics=k.tolist(), ndc_world_to_camera=w2c.tolist(),
                   ndc_size=[float(views.width), float(views.height)])


def _jsonable(value):
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return float(value)


class StaticFieldModel(nn.Module):
    """A tri-plane field with its scene, sampler and renderer.

    Args:
        scene: where the field lives.
        background: (3,) linear RGB composited behind every ray (white for NeRF-synthetic).
        field_config, render_config: component configs.
    """

    def __init__(self, scene: SceneBox, background, field_config: Optional[FieldConfig] = None,
                 render_config: Optional[RenderConfig] = None):
        super().__init__()
        if scene.kind not in SCENE_TYPES:
            raise InputError(f"must be one of {SCENE_TYPES}, got {scene.kind!r}", field="scene_type")
        self.scene = scene
        self.render_config = rc = render_config or RenderConfig()
        self.field = TriPlaneField(field_config or FieldConfig())
        self.register_buffer("background", torch.as_tensor(np.asarray(background, np.float32)).reshape(3))
        self.bounded = scene.kind == "bounded-360"
        if self.bounded:
            lo = torch.tensor(scene.box_min, dtype=torch.float32)
            hi = torch.tensor(scene.box_max, dtype=torch.float32)
            self.register_buffer("box_min", lo)
            self.register_buffer("box_max", hi)
            self.register_buffer("center", (lo + hi) / 2)
            self.register_buffer("half_size", (hi - lo) / 2)
        else:
            self.register_buffer("ndc_intrinsics", torch.tensor(scene.ndc_intrinsics, dtype=torch.float32))
            self.register_buffer("ndc_world_to_camera", torch.tensor(scene.ndc_world_to_camera, dtype=torch.float32))
        use_grid = rc.occupancy if rc.occupancy is not None else self.bounded
        self.occupancy = OccupancyGrid(rc.occupancy_resolution) if use_grid else None

    # scene ------------------------------------------------------------------------------------------------
    def contract(self, points: Tensor) -> Tensor:
        """World points (..., 3) -> the field's cube coordinates (..., 3) (inside = all in [-1, 1])."""
        if self.bounded:
            return contract_box(points, self.center, self.half_size)
        w, h = self.scene.ndc_size
        return contract_ndc(points, self.ndc_intrinsics, self.ndc_world_to_camera, w, h, self.scene.near,
                            self.render_config.ndc_margin)

    def occupancy_threshold(self) -> float:
        """Density at which one typical sample step has alpha ``occupancy_alpha``."""
        rc = self.render_config
        if self.bounded:
            step = 2.0 * float(self.half_size.norm()) / rc.num_samples
        else:
            step = (min(self.scene.far, 100.0 * self.scene.near) - self.scene.near) / rc.num_samples
        return -math.log(1.0 - rc.occupancy_alpha) / max(step, 1e-9)

    def update_occupancy(self, generator: Optional[torch.Generator] = None) -> float:
        """Re-evaluate the occupancy grid (a training callback); returns the occupied fraction (1 without grid)."""
        if self.occupancy is None:
            return 1.0
        return self.occupancy.update(lambda c: self.field.get_density(c)[0], self.occupancy_threshold(),
                                     decay=self.render_config.occupancy_decay, generator=generator)

    # rendering --------------------------------------------------------------------------------------------
    def ray_bounds(self, origins: Tensor, directions: Tensor, near: Tensor, far: Tensor) -> tuple[Tensor, Tensor]:
        """Per-ray planar-depth interval inside the scene; empty (far <= near) for rays that miss the box."""
        if not self.bounded:
            return near, far
        t_enter, t_exit = ray_box_intersection(origins, directions, self.box_min, self.box_max)
        return torch.maximum(near, t_enter), torch.minimum(far, t_exit)

    def render_rays(self, origins: Tensor, directions: Tensor, near: Tensor, far: Tensor, *,
                    jitter: bool = False, generator: Optional[torch.Generator] = None) -> RayOutputs:
        """Render R rays.

        Args:
            origins: (R, 3) world.
            directions: (R, 3) world, camera-z = 1 (from :func:`~models.fields.components.sampling.camera_rays`), so t is
                planar depth.
            near, far: (R,) planar-depth bounds.
            jitter: stratified random sample positions (training) instead of bin centres.

        Returns:
            :class:`~models.fields.components.render.RayOutputs` (colour composited on the model's background).
        """
        sizes: dict = {}
        check_shape(origins, "origins", ("R", 3), sizes)
        check_shape(directions, "directions", ("R", 3), sizes)
        check_shape(near, "near", ("R",), sizes)
        check_shape(far, "far", ("R",), sizes)
        if not self.field.deferred:
            return self.march(origins, directions, near, far, self._query, jitter=jitter, generator=generator)[0]
        channels = self.field.config.geo_feature_dim
        samples: list = []

        def query(coords: Tensor, idx: tuple[Tensor, Tensor], unit: Tensor) -> tuple[Tensor, Tensor]:
            sigma, features = self.field(coords, unit)
            samples.append((idx, features))
            return sigma, features
        out = self.march(origins, directions, near, far, query, jitter=jitter, generator=generator,
                         channels=channels, background=self.background.new_zeros(channels))[0]
        unit = torch.nn.functional.normalize(directions, dim=-1)
        return out._replace(color=self.shade_rays(out, unit, samples[0] if samples else None))

    def shade_rays(self, out: RayOutputs, unit: Tensor, samples: Optional[tuple[tuple[Tensor, Tensor], Tensor]],
                   **inputs) -> Tensor:
        """Deferred shading of R composited rays (the static and the dynamic model's): ``out.color`` (R, G) holds
        the features composited on zeros, ``unit`` (R, 3) the unit view directions -> linear RGB (R, 3) by the
        field's ``shade_pixels`` (``inputs``: its further per-ray inputs, a dynamic field's ``times``).

        ``samples``: ``(idx, features (K, G))`` of the kept samples, or None; in training with
        ``residual_density_grad`` off they are composited again with the weights' gradient stopped, for the
        view-dependent residual alone (the same values: the residual cannot shape the geometry)."""
        residual_inputs = None
        if samples is not None and torch.is_grad_enabled() and not self.field.config.residual_density_grad:
            idx, features = samples
            dense = features.new_zeros(*out.weights.shape, features.shape[-1]).index_put(idx, features)
            weights = out.weights.detach()
            residual_inputs = ((weights[..., None] * dense).sum(dim=-2), weights.sum(dim=-1))
        return self.field.shade_pixels(out.color, out.opacity, unit, self.background, residual_inputs, **inputs)

    def _query(self, coords: Tensor, idx: tuple[Tensor, Tensor], unit: Tensor) -> tuple[Tensor, Tensor]:
        return self.field(coords, unit)

    def march(self, origins: Tensor, directions: Tensor, near: Tensor, far: Tensor, query, *, jitter: bool = False,
              generator: Optional[torch.Generator] = None, channels: int = 3, background: Optional[Tensor] = None
              ) -> tuple[RayOutputs, Tensor, Tensor, tuple[Tensor, Tensor]]:
        """The ray marcher of the static and the dynamic field (shapes as :meth:`render_rays`, unchecked here):
        :meth:`place_samples`, ``query(coords, idx, unit_directions) -> (sigma, rgb)`` on the kept samples only
        (``idx``: their (ray, sample) indices; not called when none is kept), then :meth:`composite_placed`.
        ``query`` gives ``channels`` values a sample (RGB, or a deferred field's features), composited on
        ``background`` (default: the model's).

        Returns:
            (outputs, contracted sample coordinates (R, N, 3), kept samples (R, N) bool, ``idx``).
        """
        placed = self.place_samples(origins, directions, near, far, jitter=jitter, generator=generator)
        kept = None
        if placed.idx[0].numel() > 0:
            kept = query(placed.coords[placed.idx], placed.idx, placed.unit[placed.idx[0]])
        out = self.composite_placed(placed, kept, channels, background)
        return out, placed.coords, placed.keep, placed.idx

    def place_samples(self, origins: Tensor, directions: Tensor, near: Tensor, far: Tensor, *, jitter: bool = False,
                      generator: Optional[torch.Generator] = None) -> "PlacedSamples":
        """Where a ray marcher evaluates the field (shapes as :meth:`render_rays`, unchecked here).

        Samples ``num_samples`` intervals per ray between the scene bounds (linear in t for bounded scenes, in
        1/t for forward-facing ones; jittered with ``jitter``: the only random draw), contracts them and keeps
        the samples inside the cube, in a non-empty interval and (once the grid has been updated) in an
        occupied cell. Interval lengths are ``delta t |d|`` (densities are per unit length, t is camera z).
        """
        rc = self.render_config
        t_near, t_far = self.ray_bounds(origins, directions, near, far)
        spacing = "linear" if self.bounded else "disparity"
        t, deltas = sample_intervals(t_near, t_far, rc.num_samples, spacing=spacing, jitter=jitter,
                                     generator=generator)
        points = origins[:, None, :] + t[..., None] * directions[:, None, :]
        coords = self.contract(points)
        keep = (coords.abs() <= 1.0).all(dim=-1) & (deltas > 0)
        if self.occupancy is not None and int(self.occupancy.updates) > 0:
            keep = keep & self.occupancy.query(coords)
        idx = keep.nonzero(as_tuple=True)
        unit = torch.nn.functional.normalize(directions, dim=-1)
        lengths = deltas * directions.norm(dim=-1, keepdim=True)
        return PlacedSamples(t, lengths, coords, keep, idx, unit)

    def composite_placed(self, placed: "PlacedSamples", kept: Optional[tuple[Tensor, Tensor]], channels: int = 3,
                         background: Optional[Tensor] = None) -> RayOutputs:
        """Volume-render placed samples (:func:`~models.fields.components.render.composite_samples`): ``kept``
        is ``(sigma (K,), values (K, channels))`` of the kept samples in ``placed.idx`` order (None: none kept);
        the others are empty. ``background`` defaults to the model's."""
        r, n = placed.t.shape
        sigma = placed.coords.new_zeros(r, n)
        rgb = placed.coords.new_zeros(r, n, channels)
        if kept is not None:
            sigma = sigma.index_put(placed.idx, kept[0])
            rgb = rgb.index_put(placed.idx, kept[1])
        background = self.background if background is None else background
        return composite_samples(sigma, rgb, placed.lengths, placed.t, background)

    def forward(self, origins: Tensor, directions: Tensor, near: Tensor, far: Tensor) -> RayOutputs:
        return self.render_rays(origins, directions, near, far)
