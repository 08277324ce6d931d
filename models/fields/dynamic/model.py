"""Dynamic radiance fields (thesis Ch. 5): a canonical field deformed by a hex-plane motion field (DeRF),
and the K-Planes-style 4D baseline without a motion model.

Layers as in the static module (``docs/fields.md``): components (:func:`sample_hex_planes`,
:class:`HexPlaneEncoding`) -> fields (:class:`CanonicalField`, :class:`MotionField`, :class:`DeRFField`,
:class:`KPlanesField`) -> model (:class:`DynamicFieldModel`: scene, sampling, rendering at a time). The design
note is ``docs/dynamic_fields.md``.

Conventions (written once here, named wherever they matter):

- **Coordinates.** Both fields work in the static model's *contracted* cube [-1, 1]^3 (box coordinates for
  ``bounded-360``, the NDC of the reference camera for ``forward-facing``; ``models/fields/components/sampling.py``).
  The motion field's flow is in contracted units and the canonical point is ``c' = c + flow(c, t)``
  (thesis Eq. 5.2, written in the contracted cube as K-Planes-based code does). A canonical point outside
  the cube reads the cube's border texels (clamped, as every plane lookup here): mapping content out of the
  canonical volume does not make it vanish, so the motion field cannot hide matched rays by emptying them
  (with zero density there, the sparse flow loss of Eq. 5.7 was minimised by pushing 16% of the samples out
  of the cube, halving the rendered opacity). How often it happens is a diagnostic
  (``DynamicRayOutputs.canonical_outside``).
- **Time.** Times are the data's own units (seconds for rgbd-rig captures, D-NeRF's [0, 1] for D-NeRF);
  the model holds the trained range [t_min, t_max] and normalises ``tau = 2 (t - t_min) / (t_max - t_min) - 1``
  (tau = 0 for a single trained time). A time outside the trained range (beyond a relative tolerance of
  :data:`TIME_TOLERANCE`) raises :class:`~engine.core.errors.InputError` naming it and the range.
- **Planes.** The spatial planes of one scale are stored (3, C, R, R) in the order xy, xz, yz (as
  :data:`~models.fields.components.encodings.PLANE_AXES`); the time planes (3, C, Rt, R) in the order xt, yt, zt, the
  spatial coordinate along the width (grid_sample's x) and time along the height (grid_sample's y). Plane
  groups are named: ``spatial`` (canonical tri-planes, or the 4D field's space planes), ``motion_spatial``
  (DeRF), ``temporal`` (the xt, yt, zt planes: the motion field's for DeRF, the 4D field's for K-Planes).
- **Motion slots** (``MotionConfig.slots`` > 0, :class:`SlotMotion`): the motion field is K affine motions
  mixed by a softmax of logit planes instead of hex-planes + MLP; its logit planes are the ``motion_spatial``
  group, its time keys no plane group (the ``slot_smooth`` loss smooths them).

Everything is plain torch (grid_sample, Linear, ReLU, tanh, exp, sigmoid): exportable to ONNX. One module
(~720 lines) because the three layers share the conventions above; rendering itself is the static model's
ray marcher (``StaticFieldModel.march``).

>>> model = DynamicFieldModel(SceneBox("bounded-360", 1.0, 5.0, [-1.0] * 3, [1.0] * 3), [1.0, 1.0, 1.0],
...                           (0.0, 1.0), DynamicFieldConfig(canonical=FieldConfig(resolutions=(8,))),
...                           time_resolution=4)
>>> o, d = torch.zeros(2, 3) - torch.tensor([0.0, 0.0, 3.0]), torch.tensor([[0.0, 0.0, 1.0]] * 2)
>>> model.render_rays(o, d, torch.ones(2), torch.full((2,), 5.0), torch.tensor([0.0, 0.5])).color.shape
torch.Size([2, 3])
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple, Optional, Sequence

import numpy as np
import torch
from torch import Tensor, nn

from engine.core.checks import check_range, check_shape
from engine.core.errors import InputError
from models.fields.components.encodings import (MLP, DirectionEncoding, TriPlaneEncoding, fourier_encoding, plane_grid,
                                                read_planes)
from models.fields.static.field import FieldConfig, density_activation, shade_pixels
from models.fields.static.model import PlacedSamples, RenderConfig, SceneBox, StaticFieldModel

__all__ = ["FIELD_KINDS", "TIME_TOLERANCE", "sample_time_planes", "time_grid", "sample_hex_planes", "time_smoothness",
           "HexPlaneEncoding", "SLOT_KEY_SIZE", "slot_motion", "SlotMotion", "MotionConfig", "DynamicFieldConfig",
           "CanonicalField", "MotionField",
           "DeRFField", "KPlanesField", "FieldSamples", "DynamicRayOutputs", "TimedSamples", "DynamicFieldModel",
           "auto_time_resolution", "normalize_times", "AtTime"]

#: ``DynamicFieldConfig.kind``: the canonical + motion model (DeRF, thesis Ch. 5) or the K-Planes-style 4D
#: field without a motion model.
FIELD_KINDS = ("derf", "kplanes")
#: A time may exceed the trained range by this fraction of the range (at least 1e-6 absolute) before it is
#: refused (float round-off of times read from files).
TIME_TOLERANCE = 1e-6


# ----------------------------------------------------------------------------------------------------
# Components: hex-planes


def sample_time_planes(planes: Sequence[Tensor], coords: Tensor, times: Tensor) -> Tensor:
    """Multi-resolution time-plane features: product across the xt, yt, zt planes, concatenated across scales.

    Args:
        planes: one tensor per scale, each (3, C, Rt, R): the xt, yt, zt planes, the spatial coordinate along
            the width and time along the height.
        coords: (..., 3) contracted coordinates in [-1, 1] (``align_corners=True``; outside reads the border).
        times: (...) normalised times in [-1, 1].

    Returns:
        (..., C * len(planes)).

    Example:
        >>> sample_time_planes([torch.ones(3, 2, 4, 8)], torch.zeros(5, 3), torch.zeros(5)).shape
        torch.Size([5, 2])
    """
    lead = coords.shape[:-1]
    grid = time_grid(coords.reshape(-1, 3), times.reshape(-1))
    out = torch.cat([read_planes(plane, grid) for plane in planes], dim=0).transpose(0, 1)
    return out.reshape(*lead, out.shape[-1])


def time_grid(coords: Tensor, times: Tensor) -> Tensor:
    """(N, 3) contracted coordinates and (N,) normalised times -> the (3, 1, N, 2) ``grid_sample`` grid of the
    xt, yt, zt planes (the spatial coordinate along the width, time along the height); contiguous, as
    :func:`~models.fields.components.encodings.plane_grid`'s."""
    return torch.stack([coords.t(), times.to(coords.dtype).expand(3, -1)], dim=-1).unsqueeze(1)


def sample_hex_planes(spatial: Sequence[Tensor], temporal: Sequence[Tensor], coords: Tensor, times: Tensor) -> Tensor:
    """Hex-plane features (thesis Eq. 5.1): per scale the Hadamard product of the six planes xy, xz, yz,
    xt, yt, zt read at (p, t), concatenated across scales.

    Args:
        spatial: per scale (3, C, R, R) (xy, xz, yz; read with :func:`~models.fields.components.encodings.sample_planes`).
        temporal: per scale (3, C, Rt, R) (xt, yt, zt; :func:`sample_time_planes`), same C and R as ``spatial``.
        coords: (..., 3) contracted coordinates; times: (...) normalised times.

    Returns:
        (..., C * scales), scale 0 first.
    """
    lead = coords.shape[:-1]
    flat = coords.reshape(-1, 3)
    grid, tgrid = plane_grid(flat), time_grid(flat, times.reshape(-1))  # built once for every scale
    feats = [read_planes(s, grid) * read_planes(t, tgrid) for s, t in zip(spatial, temporal)]  # (C, N) each
    out = torch.cat(feats, dim=0).transpose(0, 1)
    return out.reshape(*lead, out.shape[-1])


def time_smoothness(planes: Sequence[Tensor]) -> Tensor:
    """K-Planes' temporal smoothness: mean squared second difference along the time axis (the height of
    each (3, C, Rt, R) time plane), summed over the tensors of the group; 0 for fewer than 3 time rows."""
    total = planes[0].new_zeros(()) if planes else torch.zeros(())
    for p in planes:
        if p.shape[-2] >= 3:
            total = total + (p[..., 2:, :] - 2.0 * p[..., 1:-1, :] + p[..., :-2, :]).square().mean()
    return total


class HexPlaneEncoding(nn.Module):
    """Thin module holding multi-resolution hex-planes, read by :func:`sample_hex_planes`.

    Args:
        resolutions: spatial plane side R per scale.
        time_resolution: rows Rt of every time plane (the same at every scale, as K-Planes).
        feature_dim: channels C per plane.
        init_range: spatial features start uniform in this range; time planes start at ``time_init``
            (K-Planes: 1, so that a fresh field is time-independent).
    """

    def __init__(self, resolutions: Sequence[int], time_resolution: int, feature_dim: int,
                 init_range: tuple[float, float] = (0.1, 0.5), time_init: float = 1.0):
        super().__init__()
        self.resolutions = tuple(int(r) for r in resolutions)
        self.time_resolution = int(time_resolution)
        self.feature_dim = int(feature_dim)
        lo, hi = init_range
        c = self.feature_dim
        self.spatial = nn.ParameterList(nn.Parameter(torch.empty(3, c, r, r).uniform_(lo, hi))
                                        for r in self.resolutions)
        self.temporal = nn.ParameterList(nn.Parameter(torch.full((3, c, self.time_resolution, r), float(time_init)))
                                         for r in self.resolutions)

    @property
    def output_dim(self) -> int:
        return self.feature_dim * len(self.resolutions)

    def spatial_planes(self) -> list[Tensor]:
        """The spatial group: one (3, C, R, R) tensor (xy, xz, yz) per scale, coarse to fine."""
        return list(self.spatial)

    def temporal_planes(self) -> list[Tensor]:
        """The temporal group: one (3, C, Rt, R) tensor (xt, yt, zt) per scale, coarse to fine."""
        return list(self.temporal)

    def forward(self, coords: Tensor, times: Tensor) -> Tensor:
        """(..., 3) contracted coordinates and (...) normalised times -> (..., C * scales)."""
        return sample_hex_planes(self.spatial_planes(), self.temporal_planes(), coords, times)


# ----------------------------------------------------------------------------------------------------
# Components: motion slots

#: Values per slot and time key in :class:`SlotMotion`'s key table: dA (3 x 3, row-major), then T (3).
SLOT_KEY_SIZE = 12


#: :func:`slot_motion` mixes the keys per distinct time (one small matrix product each) when a batch has at most this
#: many distinct times (a training batch has one per trained frame, a render one), and with hat weights otherwise.
SLOT_SEGMENT_TIMES = 64


def slot_motion(logits: Tensor, still_bias: Tensor, keys: Tensor, coords: Tensor, times: Tensor) -> Tensor:
    """The motion of K affine slots mixed by a softmax over K + 1 slots (slot 0 still), before the flow bound.

    ``w = softmax(l(c) + still_bias)`` with ``l(c)`` the sum of the xy, xz, yz logit planes read bilinearly
    (``align_corners=True``, border) at c; slot k >= 1 moves c by ``dA_k(tau) c + T_k(tau)``, its 12 values
    linear in tau between the Rt keys (key i at ``tau = -1 + 2 i / (Rt - 1)``; tau clamped to [-1, 1]); the
    still slot adds nothing: ``m = sum_k w_k (dA_k c + T_k)``. :class:`MotionField` bounds it,
    ``flow = max_flow * tanh(m)``.

    Two evaluations of the same sum (equal to float rounding, tests/fields/test_motion_slots.py): with at most
    :data:`SLOT_SEGMENT_TIMES` distinct times the keys are interpolated once per time and mixed by one small matrix
    product per time (:func:`_slot_mix_by_time`, 4-12x fewer products); otherwise, and while exporting, by hat
    weights over the keys (:func:`_slot_mix_hat`).

    Args:
        logits: (3, K + 1, R, R) logit planes, xy, xz, yz; channel 0 is the still slot.
        still_bias: (K + 1,) added to the summed logits (the still slot's bias, zeros elsewhere).
        keys: (Rt, K, 12) per time key and moving slot: dA row-major (9), then T (3); Rt >= 2.
        coords: (..., 3) contracted coordinates; times: (...) normalised times (broadcast to ``coords``' lead).

    Returns:
        (..., 3) in contracted units.

    Example:
        >>> slot_motion(torch.zeros(3, 3, 4, 4), torch.zeros(3), torch.ones(2, 2, 12), torch.zeros(5, 3),
        ...             torch.zeros(5))[0]
        tensor([0.6667, 0.6667, 0.6667])
    """
    lead = coords.shape[:-1]
    flat = coords.reshape(-1, 3)
    rows = keys.shape[0]
    taus = torch.broadcast_to(times.to(flat.dtype), lead).reshape(-1)
    f = torch.nn.functional.grid_sample(logits, plane_grid(flat).to(logits.dtype), mode="bilinear",
                                        padding_mode="border", align_corners=True)  # (3, K + 1, 1, N)
    # summed and reshaped, not indexed: a selection's gradient fills a zero tensor of f's size
    weights = torch.softmax(f.sum(dim=0).reshape(f.shape[1], -1) + still_bias[:, None], dim=0)
    weights = weights[1:].t().contiguous()  # (N, K)
    x = (taus.clamp(-1.0, 1.0) + 1.0) * (0.5 * (rows - 1))  # key coordinate, in [0, Rt - 1]
    exporting = torch.compiler.is_compiling() or torch.onnx.is_in_onnx_export() or torch.jit.is_tracing()
    mix = None if exporting or not x.numel() else _slot_mix_by_time(weights, keys, x, SLOT_SEGMENT_TIMES)
    if mix is None:
        mix = _slot_mix_hat(weights, keys, x)
    out = (mix[:, :9].reshape(-1, 3, 3) * flat[:, None, :]).sum(dim=-1) + mix[:, 9:]  # (N, 3)
    return out.reshape(*lead, 3)


def _hat(x: Tensor, rows: int) -> Tensor:
    """(Rt, N) linear-interpolation weights of key coordinates x (N,) in [0, Rt - 1] (two nonzero per point)."""
    return (1.0 - (x[None, :] - torch.arange(rows, dtype=x.dtype, device=x.device)[:, None]).abs()).clamp_min(0.0)


def _slot_mix_hat(weights: Tensor, keys: Tensor, x: Tensor) -> Tensor:
    """(N, 12) ``sum_k w_k key_k(x)`` of weights (N, K): the keys' interpolation as hat weights (Rt, N), so that the
    mixing is one matrix product and its gradient no scatter (2.3x faster than gathering each point's two keys)."""
    rows, slots = keys.shape[0], keys.shape[1]
    mixing = (weights.t().contiguous()[:, None, :] * _hat(x, rows)[None, :, :]).reshape(slots * rows, -1)  # (K Rt, N)
    # (12, N) transposed, not mixing.t() @ keys: 8 % faster with its backward (65536 points, K 8, Rt 25, 1 thread)
    return (keys.permute(1, 0, 2).reshape(slots * rows, SLOT_KEY_SIZE).t() @ mixing).t()


def _slot_mix_by_time(weights: Tensor, keys: Tensor, x: Tensor, limit: int) -> Optional[Tensor]:
    """(N, 12) ``sum_k w_k key_k(x)`` of weights (N, K) for points with at most ``limit`` distinct key coordinates
    x (N,), else None: the keys at each distinct value (U, K, 12) by one product with hat weights, then the points of
    each value (sorted together) mixed by one (n_u, K) x (K, 12) product. The point order is undone by
    ``index_copy``, whose gradient is a gather."""
    rows, slots = keys.shape[0], keys.shape[1]
    ordered, order = torch.sort(x)
    values, counts = torch.unique_consecutive(ordered, return_counts=True)
    if values.numel() > limit:
        return None
    at = (_hat(values, rows).t() @ keys.reshape(rows, -1)).reshape(-1, slots, SLOT_KEY_SIZE)  # (U, K, 12)
    parts = [w @ k for w, k in zip(torch.split(weights.index_select(0, order), counts.tolist()), at.unbind(0))]
    return torch.index_copy(weights.new_empty(weights.shape[0], SLOT_KEY_SIZE), 0, order, torch.cat(parts))


class SlotMotion(nn.Module):
    """Thin module holding K affine motion slots and a still slot, read by :func:`slot_motion`.

    Conventions: coordinates are the contracted cube [-1, 1]^3, times the normalised tau in [-1, 1], the output
    (the slots' mixed motion, before :class:`MotionField`'s ``max_flow * tanh``) contracted units. Every key
    starts at zero, so the motion (and the flow) is exactly zero at step 0; the logit planes start at
    ``randn / sqrt(3)`` (their sum over the three planes has unit variance); the still slot's bias is a buffer.

    Args:
        slots: K >= 1 moving slots.
        time_resolution: Rt >= 2 time keys (the motion field's time resolution).
        resolution: side R of the logit planes.
        still_bias: logit bias of the still slot.
    """

    def __init__(self, slots: int, time_resolution: int, resolution: int = 32, still_bias: float = 2.0):
        super().__init__()
        self.slots, self.time_resolution, self.resolution = int(slots), int(time_resolution), int(resolution)
        if self.slots < 1 or self.time_resolution < 2 or self.resolution < 2:
            raise InputError(f"needs slots >= 1, time_resolution >= 2 and resolution >= 2, got {self.slots}, "
                             f"{self.time_resolution}, {self.resolution}", field="field.motion.slots")
        k, r = self.slots, self.resolution
        self.logits = nn.Parameter(torch.randn(3, k + 1, r, r) / math.sqrt(3.0))
        bias = torch.zeros(k + 1)
        bias[0] = float(still_bias)
        self.register_buffer("still_bias", bias)
        self.keys = nn.Parameter(torch.zeros(self.time_resolution, k, SLOT_KEY_SIZE))

    def forward(self, coords: Tensor, times: Tensor) -> Tensor:
        """(..., 3) contracted coordinates, (...) normalised times -> (..., 3) motion (contracted units)."""
        return slot_motion(self.logits, self.still_bias, self.keys, coords, times)

    def key_smoothness(self) -> Tensor:
        """:func:`time_smoothness` of the key table: the mean squared second difference of the keys in time."""
        return time_smoothness([self.keys.reshape(self.time_resolution, -1)])


# ----------------------------------------------------------------------------------------------------
# Configs


@dataclass
class MotionConfig:
    """Size of the hex-plane motion field (DeRF's F_f = G_f o M_f)."""

    resolutions: tuple[int, ...] = field(default=(16, 32), metadata={
        "help": "motion plane side per scale, coarse to fine"})
    feature_dim: int = field(default=4, metadata={"help": "feature channels per motion plane and scale"})
    init_range: tuple[float, float] = field(default=(0.1, 0.5), metadata={
        "help": "spatial motion features start uniform in this range (time planes start at 1)"})
    hidden: int = field(default=32, metadata={"help": "hidden width of the flow MLP (M_f)"})
    layers: int = field(default=1, metadata={"help": "hidden layers of the flow MLP (0: one linear layer, as RF-DeRF)"})
    max_flow: float = field(default=1.0, metadata={
        "help": "flow = max_flow * tanh(MLP output), in contracted units (RF-DeRF: linear + tanh, bound 1)"})
    zero_init: bool = field(default=True, metadata={
        "help": "start with flow exactly 0 (the flow MLP's last layer starts at zero)"})
    slots: int = field(default=0, metadata={
        "help": "0: the hex-plane motion field and flow MLP; K > 0: K affine motion slots and a still slot instead "
                "(SlotMotion; the hex-plane and MLP options above are then unused; "
                "docs/results/2026-11-30-dynamic-units.md)"})
    slot_resolution: int = field(default=32, metadata={"help": "side of the slots' logit planes (slots > 0)"})
    slot_still_bias: float = field(default=2.0, metadata={
        "help": "logit bias of the still slot (slot 0, no motion) at every point (slots > 0)"})

    def validate(self) -> "MotionConfig":
        if not self.resolutions or any(int(r) < 2 for r in self.resolutions):
            raise InputError(f"must be a non-empty list of sizes >= 2, got {self.resolutions}",
                             field="field.motion.resolutions")
        for name in ("feature_dim", "hidden"):
            check_range(getattr(self, name), f"field.motion.{name}", low=1, integer=True)
        check_range(self.layers, "field.motion.layers", low=0, integer=True)
        check_range(self.max_flow, "field.motion.max_flow", low=0, low_open=True)
        check_range(self.slots, "field.motion.slots", low=0, integer=True)
        check_range(self.slot_resolution, "field.motion.slot_resolution", low=2, integer=True)
        check_range(self.slot_still_bias, "field.motion.slot_still_bias")
        return self


@dataclass
class DynamicFieldConfig:
    """Which dynamic field, and its size."""

    kind: str = field(default="derf", metadata={
        "help": "derf (canonical tri-plane field + hex-plane motion field; with the sparse flow prior, which "
                "'interleave train dynamic' switches on for it, the best on the rigs and lego: "
                "docs/results/2026-11-25-dynamic-default.md) or kplanes (4D hex-plane field, no motion model)"})
    canonical: FieldConfig = field(default_factory=FieldConfig, metadata={
        "help": "the canonical field (derf) or the 4D field's planes and MLPs (kplanes)"})
    motion: MotionConfig = field(default_factory=MotionConfig, metadata={"help": "the motion field (derf only)"})
    time_resolution: int = field(default=0, metadata={
        "help": "rows of every time plane; 0: half the number of trained times, at least 2"})
    time_frequencies: int = field(default=2, metadata={
        "help": "Fourier frequencies of the time fed to the canonical colour MLP (Eq. 5.4; derf only)"})
    canonical_time: bool = field(default=True, metadata={
        "help": "derf only: the canonical tri-planes get time planes too (hex-planes read at the deformed point "
                "and time, starting time-independent): K-Planes' 4D capacity for what the motion does not explain "
                "(docs/results/2026-11-28-dynamic-canonical-time.md)"})

    def validate(self) -> "DynamicFieldConfig":
        if self.kind not in FIELD_KINDS:
            raise InputError(f"must be one of {FIELD_KINDS}, got {self.kind!r}", field="field.kind")
        if self.time_resolution < 0 or self.time_resolution == 1:
            raise InputError(f"must be 0 (auto) or >= 2, got {self.time_resolution}", field="field.time_resolution")
        check_range(self.time_frequencies, "field.time_frequencies", low=0, integer=True)
        self.canonical.validate()
        # the static field's options that the dynamic fields do not build: refused rather than ignored
        if self.canonical.density_layers != 1:
            raise InputError(f"dynamic fields have one hidden layer in the density MLP, got "
                             f"{self.canonical.density_layers}", field="field.canonical.density_layers")
        self.motion.validate()
        return self


def auto_time_resolution(config: DynamicFieldConfig, num_times: int) -> int:
    """The time planes' rows: ``config.time_resolution``, or half the number of trained times (>= 2)."""
    return int(config.time_resolution) if config.time_resolution else max(2, int(num_times) // 2)


# ----------------------------------------------------------------------------------------------------
# Fields


class FieldSamples(NamedTuple):
    """What a dynamic field returns for M samples.

    Attributes:
        sigma: (M,) density per scene unit.
        rgb: (M, 3) linear RGB in [0, 1]; with deferred shading (``canonical.shading``) the features
            ``sigmoid(h)`` (M, G) instead, which the renderer composites and shades once per pixel.
        canonical: (M, 3) canonical point c' (contracted; equal to c for K-Planes).
        flow: (M, 3) c' - c (zero for K-Planes).
    """

    sigma: Tensor
    rgb: Tensor
    canonical: Tensor
    flow: Tensor


class CanonicalField(nn.Module):
    """The canonical scene F_s (Eq. 5.3, 5.4): tri-planes (hex-planes with ``time_resolution`` > 0: the
    canonical point's features then vary in time, as a K-Planes field's) -> density and latent h; colour from
    h, the encoded view direction and the encoded (normalised) time."""

    def __init__(self, config: FieldConfig, time_frequencies: int, time_resolution: int = 0):
        super().__init__()
        self.config = cfg = config.validate()
        self.time_frequencies = int(time_frequencies)
        self.encoding = (HexPlaneEncoding(cfg.resolutions, time_resolution, cfg.feature_dim, tuple(cfg.init_range))
                         if time_resolution else TriPlaneEncoding(cfg.resolutions, cfg.feature_dim,
                                                                  tuple(cfg.init_range)))
        self.density_mlp = MLP(self.encoding.output_dim, cfg.density_hidden, 1 + cfg.geo_feature_dim)
        self.direction_encoding = DirectionEncoding(cfg.direction_encoding, cfg.direction_degree)
        self.time_dim = 2 * self.time_frequencies + 1
        self.color_mlp = MLP(cfg.geo_feature_dim + self.direction_encoding.output_dim + self.time_dim,
                             cfg.color_hidden, 3, layers=cfg.color_layers)

    def spatial_planes(self) -> list[Tensor]:
        return self.encoding.spatial_planes()

    def temporal_planes(self) -> list[Tensor]:
        """The time planes of a 4D canonical field (``canonical_time``); none for tri-planes."""
        return self.encoding.temporal_planes() if isinstance(self.encoding, HexPlaneEncoding) else []

    def get_density(self, coords: Tensor, times: Tensor) -> tuple[Tensor, Tensor]:
        """(..., 3) canonical coordinates, (...) normalised times -> density (...), latent h (..., G)."""
        feats = self.encoding(coords, times) if isinstance(self.encoding, HexPlaneEncoding) else self.encoding(coords)
        out = self.density_mlp(feats)
        return density_activation(out[..., 0], self.config.density_bias), out[..., 1:]

    def get_outputs(self, h: Tensor, directions: Tensor, times: Tensor) -> Tensor:
        """Latent h (..., G), unit directions (..., 3), normalised times (...) -> linear RGB (..., 3)."""
        t = fourier_encoding(times[..., None], self.time_frequencies)
        return torch.sigmoid(self.color_mlp(torch.cat([h, self.direction_encoding(directions), t], dim=-1)))

    def shade_pixels(self, features: Tensor, opacity: Tensor, directions: Tensor, background: Tensor,
                     residual_inputs: Optional[tuple[Tensor, Tensor]] = None, *, times: Tensor) -> Tensor:
        """Deferred shading (:func:`~models.fields.static.field.shade_pixels`): composited features (..., G),
        opacity (...), unit directions (..., 3), the rays' normalised times (...) -> linear RGB (..., 3); the
        colour MLP reads ``[F, enc(d), gamma(tau)]``, as :meth:`get_outputs` reads ``[h, enc(d), gamma(tau)]``."""
        t = fourier_encoding(times[..., None], self.time_frequencies)
        return shade_pixels(self, features, opacity, directions, background, residual_inputs, t)


class MotionField(nn.Module):
    """The motion field F_f (Eq. 5.1, 5.2): hex-planes -> tiny MLP -> flow = max_flow * tanh(.) from (c, t) to
    the canonical time, in contracted units. With ``config.slots`` > 0 the hex-planes and MLP are not built: a
    :class:`SlotMotion` gives the motion inside the tanh (``slot_motion``; ``encoding`` and ``flow_mlp`` are
    None), its logit planes the ``spatial`` group and no time planes."""

    def __init__(self, config: MotionConfig, time_resolution: int):
        super().__init__()
        self.config = cfg = config.validate()
        self.encoding: Optional[HexPlaneEncoding] = None
        self.flow_mlp: Optional[MLP] = None
        self.slot_motion: Optional[SlotMotion] = None
        if cfg.slots:
            self.slot_motion = SlotMotion(cfg.slots, time_resolution, cfg.slot_resolution, cfg.slot_still_bias)
            return
        self.encoding = HexPlaneEncoding(cfg.resolutions, time_resolution, cfg.feature_dim, tuple(cfg.init_range))
        self.flow_mlp = MLP(self.encoding.output_dim, cfg.hidden, 3, layers=cfg.layers)
        if cfg.zero_init:
            last = [m for m in self.flow_mlp.net if isinstance(m, nn.Linear)][-1]
            nn.init.zeros_(last.weight)
            nn.init.zeros_(last.bias)

    def spatial_planes(self) -> list[Tensor]:
        """The hex-planes' xy, xz, yz planes per scale, or the slots' one (3, K + 1, R, R) logit planes."""
        if self.slot_motion is not None:
            return [self.slot_motion.logits]
        return self.encoding.spatial_planes()

    def temporal_planes(self) -> list[Tensor]:
        """The hex-planes' xt, yt, zt planes per scale; none with slots (their keys are not planes)."""
        if self.slot_motion is not None:
            return []
        return self.encoding.temporal_planes()

    def forward(self, coords: Tensor, times: Tensor) -> Tensor:
        """(..., 3) contracted coordinates, (...) normalised times -> flow (..., 3) in contracted units."""
        if self.slot_motion is not None:
            return self.config.max_flow * torch.tanh(self.slot_motion(coords, times))
        return self.config.max_flow * torch.tanh(self.flow_mlp(self.encoding(coords, times)))


class _DynamicField(nn.Module):
    """What both dynamic fields share: deferred shading's switch, :meth:`colour` over the field's own
    per-sample colour (``_sample_colour``) and :meth:`forward` over :meth:`geometry`."""

    config: FieldConfig

    @property
    def deferred(self) -> bool:
        """Deferred shading: :meth:`colour` gives the features ``sigmoid(h)``, :meth:`shade_pixels` the colour."""
        return self.config.shading == "deferred"

    def colour(self, h: Tensor, directions: Tensor, times: Tensor) -> Tensor:
        """Latent h (..., G) of :meth:`geometry`, unit directions (..., 3), normalised times (...) -> RGB; with
        deferred shading the sample's features ``sigmoid(h)`` (..., G) instead."""
        if self.deferred:
            return torch.sigmoid(h)
        return self._sample_colour(h, directions, times)

    def forward(self, coords: Tensor, times: Tensor, directions: Optional[Tensor]) -> FieldSamples:
        """``directions`` None: geometry only (``rgb`` zero, the colour MLP not run)."""
        sigma, h, canonical, flow = self.geometry(coords, times)
        rgb = self.colour(h, directions, times) if directions is not None else h.new_zeros(h.shape[:-1] + (3,))
        return FieldSamples(sigma, rgb, canonical, flow)


class DeRFField(_DynamicField):
    """Canonical field + motion field (thesis Fig. 5.1): ``c' = c + F_f(c, t)``, ``sigma, h = G_s(c')``
    (``G_s(c', t)`` with ``canonical_time``: hex-planes at the canonical point), ``rgb = M_s(h, gamma(v),
    gamma(t))``; c' outside the canonical cube reads its border (clamped)."""

    kind = "derf"

    def __init__(self, config: DynamicFieldConfig, time_resolution: int):
        super().__init__()
        #: the canonical field's config (shading, latent size), as a static field's ``config``
        self.config = config.canonical
        self.canonical_field = CanonicalField(config.canonical, config.time_frequencies,
                                              time_resolution if config.canonical_time else 0)
        self.motion_field = MotionField(config.motion, time_resolution)

    def plane_groups(self) -> dict[str, list[Tensor]]:
        return {"spatial": self.canonical_field.spatial_planes(),
                "motion_spatial": self.motion_field.spatial_planes(),
                "temporal": self.motion_field.temporal_planes() + self.canonical_field.temporal_planes()}

    def deform(self, coords: Tensor, times: Tensor) -> tuple[Tensor, Tensor]:
        """(..., 3) contracted points at normalised times (...) -> canonical points (..., 3), flow (..., 3)."""
        flow = self.motion_field(coords, times)
        return coords + flow, flow

    def density(self, coords: Tensor, times: Tensor) -> Tensor:
        canonical, _ = self.deform(coords, times)
        return self.canonical_field.get_density(canonical.clamp(-1.0, 1.0), times)[0]

    def geometry(self, coords: Tensor, times: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(..., 3) contracted points at normalised times (...) -> density (...), latent h (..., G), canonical
        points (..., 3), flow (..., 3): :meth:`forward` without the colour."""
        canonical, flow = self.deform(coords, times)
        sigma, h = self.canonical_field.get_density(canonical.clamp(-1.0, 1.0), times)
        return sigma, h, canonical, flow

    def _sample_colour(self, h: Tensor, directions: Tensor, times: Tensor) -> Tensor:
        return self.canonical_field.get_outputs(h, directions, times)

    def shade_pixels(self, features: Tensor, opacity: Tensor, directions: Tensor, background: Tensor,
                     residual_inputs: Optional[tuple[Tensor, Tensor]] = None, *, times: Tensor) -> Tensor:
        """Deferred shading of composited rays (:meth:`CanonicalField.shade_pixels`)."""
        return self.canonical_field.shade_pixels(features, opacity, directions, background, residual_inputs,
                                                 times=times)


class KPlanesField(_DynamicField):
    """The K-Planes-style 4D baseline: hex-plane features of (c, t) -> density and latent h -> colour from h
    and the encoded view direction; no motion model (canonical = c, flow = 0)."""

    kind = "kplanes"

    def __init__(self, config: DynamicFieldConfig, time_resolution: int):
        super().__init__()
        self.config = cfg = config.canonical.validate()
        self.encoding = HexPlaneEncoding(cfg.resolutions, time_resolution, cfg.feature_dim, tuple(cfg.init_range))
        self.density_mlp = MLP(self.encoding.output_dim, cfg.density_hidden, 1 + cfg.geo_feature_dim)
        self.direction_encoding = DirectionEncoding(cfg.direction_encoding, cfg.direction_degree)
        self.color_mlp = MLP(cfg.geo_feature_dim + self.direction_encoding.output_dim, cfg.color_hidden, 3,
                             layers=cfg.color_layers)

    def plane_groups(self) -> dict[str, list[Tensor]]:
        return {"spatial": self.encoding.spatial_planes(), "temporal": self.encoding.temporal_planes()}

    def _density(self, coords: Tensor, times: Tensor) -> tuple[Tensor, Tensor]:
        out = self.density_mlp(self.encoding(coords, times))
        return density_activation(out[..., 0], self.config.density_bias), out[..., 1:]

    def density(self, coords: Tensor, times: Tensor) -> Tensor:
        return self._density(coords, times)[0]

    def geometry(self, coords: Tensor, times: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """As :meth:`DeRFField.geometry`: density, latent h, canonical points (= ``coords``), flow (zero)."""
        sigma, h = self._density(coords, times)
        return sigma, h, coords, torch.zeros_like(coords)

    def _sample_colour(self, h: Tensor, directions: Tensor, times: Tensor) -> Tensor:
        """The time is not an input of this colour MLP."""
        return torch.sigmoid(self.color_mlp(torch.cat([h, self.direction_encoding(directions)], dim=-1)))

    def shade_pixels(self, features: Tensor, opacity: Tensor, directions: Tensor, background: Tensor,
                     residual_inputs: Optional[tuple[Tensor, Tensor]] = None, *, times: Tensor) -> Tensor:
        """Deferred shading (:func:`~models.fields.static.field.shade_pixels`; ``times`` is not an input)."""
        return shade_pixels(self, features, opacity, directions, background, residual_inputs)


# ----------------------------------------------------------------------------------------------------
# Model


class DynamicRayOutputs(NamedTuple):
    """Rendered rays at given times: :class:`~models.fields.components.render.RayOutputs`' fields, then per sample the
    canonical point, the flow, whether the sample was evaluated and whether its canonical point left the
    cube. R rays, N samples each.

    Attributes:
        color (R, 3), depth (R,), expected_depth (R,), opacity (R,), weights (R, N), transmittance (R, N),
        t (R, N): as ``RayOutputs`` (planar depth, linear RGB on the model's background).
        canonical: (R, N, 3) canonical points c' (contracted); the contracted world point where not evaluated.
        flow: (R, N, 3) c' - c (0 where not evaluated).
        evaluated: (R, N) bool, samples inside the scene cube (and occupied cells) that the field evaluated.
        canonical_outside: (R, N) bool, evaluated samples whose canonical point left the cube (they read its
            border).
    """

    color: Tensor
    depth: Tensor
    expected_depth: Tensor
    opacity: Tensor
    weights: Tensor
    transmittance: Tensor
    t: Tensor
    canonical: Tensor
    flow: Tensor
    evaluated: Tensor
    canonical_outside: Tensor


class TimedSamples(NamedTuple):
    """Samples placed along rays at given times (:meth:`DynamicFieldModel.place_timed`).

    Attributes:
        placed: :class:`~models.fields.static.model.PlacedSamples` of the R rays.
        taus: (R,) the rays' normalised times.
        color: whether their colour is computed (else geometry only, as ``render_rays(color=False)``).
    """

    placed: PlacedSamples
    taus: Tensor
    color: bool


def normalize_times(times: Tensor, time_range: tuple[float, float]) -> Tensor:
    """Times in the data's units -> [-1, 1] over ``time_range`` (0 for a single trained time); raises
    InputError naming the first time outside the range (beyond :data:`TIME_TOLERANCE` of its length)."""
    t_min, t_max = float(time_range[0]), float(time_range[1])
    span = t_max - t_min
    tol = TIME_TOLERANCE * max(1.0, abs(span), abs(t_min), abs(t_max))
    if times.numel():
        lo, hi = float(times.min()), float(times.max())
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise InputError("must be finite", field="times")
        if lo < t_min - tol or hi > t_max + tol:
            bad = lo if lo < t_min - tol else hi
            raise InputError(f"time {bad:.6g} is outside the trained range [{t_min:.6g}, {t_max:.6g}]: the "
                             "field cannot extrapolate in time", field="times")
    if span <= 0:
        return torch.zeros_like(times)
    return (2.0 * (times - t_min) / span - 1.0).clamp(-1.0, 1.0)


def _placeholder_field_config() -> FieldConfig:
    # StaticFieldModel builds a TriPlaneField; the dynamic model replaces it at once, so keep it tiny
    return FieldConfig(resolutions=(2,), feature_dim=1, density_hidden=1, geo_feature_dim=1, color_hidden=1,
                       direction_encoding="none")


class DynamicFieldModel(StaticFieldModel):
    """A dynamic field with its scene, sampler and renderer; rays are rendered at given times.

    The scene (contraction, ray clipping, occupancy threshold) is :class:`StaticFieldModel`'s; ``field`` is a
    :class:`DeRFField` or a :class:`KPlanesField`. The occupancy grid (bounded scenes by default) is
    time-agnostic: each update keeps the running max of the density at ``occupancy_times`` random trained
    times, so a cell is empty only if it was empty at every time drawn recently.

    Args:
        scene: where the field lives (``SceneBox``).
        background: (3,) linear RGB.
        time_range: (t_min, t_max), the trained times in the data's units.
        config: which dynamic field and its size.
        render_config: sampling and rendering.
        time_resolution: rows of the time planes (default: ``config.time_resolution``, which must then be set).
    """

    def __init__(self, scene: SceneBox, background, time_range: tuple[float, float],
                 config: Optional[DynamicFieldConfig] = None, render_config: Optional[RenderConfig] = None, *,
                 time_resolution: Optional[int] = None, occupancy_times: int = 4):
        super().__init__(scene, background, _placeholder_field_config(), render_config)
        self.config = cfg = (config or DynamicFieldConfig()).validate()
        rows = int(time_resolution if time_resolution is not None else cfg.time_resolution)
        if rows < 2:
            raise InputError(f"must be >= 2, got {rows}", field="time_resolution")
        t0, t1 = (float(x) for x in time_range)
        if not (math.isfinite(t0) and math.isfinite(t1) and t1 >= t0):
            raise InputError(f"must be finite with t_min <= t_max, got {time_range}", field="time_range")
        self.time_range = (t0, t1)
        self.time_resolution = rows
        self.occupancy_times = int(occupancy_times)
        self.field = (DeRFField if cfg.kind == "derf" else KPlanesField)(cfg, rows)

    @property
    def has_motion(self) -> bool:
        return isinstance(self.field, DeRFField)

    def normalize_times(self, times: Tensor) -> Tensor:
        """Data times -> [-1, 1]; InputError outside the trained range (see :func:`normalize_times`)."""
        return normalize_times(times, self.time_range)

    def update_occupancy(self, generator: Optional[torch.Generator] = None) -> float:
        """Re-evaluate the (time-agnostic) occupancy grid; returns the occupied fraction (1 without grid)."""
        if self.occupancy is None:
            return 1.0
        taus = torch.rand(self.occupancy_times, generator=generator) * 2.0 - 1.0  # drawn on the generator's device
        if self.time_range[1] <= self.time_range[0]:
            taus = torch.zeros(1)

        def density(coords: Tensor) -> Tensor:
            return torch.stack([self.field.density(coords, coords.new_full(coords.shape[:-1], float(t)))
                                for t in taus]).amax(dim=0)

        return self.occupancy.update(density, self.occupancy_threshold(), decay=self.render_config.occupancy_decay,
                                     generator=generator)

    def query(self, points: Tensor, times: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        """World points (M, 3), data times (M,), view directions (M, 3) -> density (M,), linear RGB (M, 3).

        Density is 0 outside the scene cube (the renderer never samples there). Raises InputError for times
        outside the trained range.
        """
        sizes: dict = {}
        check_shape(points, "points", ("M", 3), sizes)
        check_shape(times, "times", ("M",), sizes)
        check_shape(directions, "directions", ("M", 3), sizes)
        return self._query(points, self.normalize_times(times), directions)

    def _query(self, points: Tensor, taus: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        coords = self.contract(points)
        inside = (coords.abs() <= 1.0).all(dim=-1)
        out = self.field(coords.clamp(-1.0, 1.0), taus, torch.nn.functional.normalize(directions, dim=-1))
        return torch.where(inside, out.sigma, torch.zeros_like(out.sigma)), out.rgb

    def render_rays(self, origins: Tensor, directions: Tensor, near: Tensor, far: Tensor, times: Tensor, *,
                    jitter: bool = False, generator: Optional[torch.Generator] = None, color: bool = True
                    ) -> DynamicRayOutputs:
        """Render R rays, ray r at time ``times[r]``.

        Args:
            origins, directions: (R, 3) world; directions with camera z = 1 (t is planar depth).
            near, far: (R,) planar-depth bounds.
            times: (R,) in the data's units, inside the trained range (else InputError naming the time).
            jitter: stratified random sample positions (training) instead of bin centres.
            color: False renders the geometry only (weights, depth, canonical points, flow): the samples'
                colour is not computed and ``color`` is the background (what the sparse flow prior's matched
                rays need, at the cost of the density alone).

        Returns:
            :class:`DynamicRayOutputs`.
        """
        return self.render_placed([self.place_timed(origins, directions, near, far, times, jitter=jitter,
                                                    generator=generator, color=color)])[0]

    def place_timed(self, origins: Tensor, directions: Tensor, near: Tensor, far: Tensor, times: Tensor, *,
                    jitter: bool = False, generator: Optional[torch.Generator] = None, color: bool = True
                    ) -> TimedSamples:
        """The samples :meth:`render_rays` would evaluate (same arguments, same random draws), for
        :meth:`render_placed`."""
        sizes: dict = {}
        check_shape(origins, "origins", ("R", 3), sizes)
        check_shape(directions, "directions", ("R", 3), sizes)
        check_shape(near, "near", ("R",), sizes)
        check_shape(far, "far", ("R",), sizes)
        check_shape(times, "times", ("R",), sizes)
        taus = self.normalize_times(times)
        return TimedSamples(self.place_samples(origins, directions, near, far, jitter=jitter, generator=generator),
                            taus, bool(color))

    def render_placed(self, sets: Sequence[TimedSamples]) -> list[DynamicRayOutputs]:
        """Render sets of placed samples (:meth:`place_timed`) with one evaluation of the field.

        The kept samples of every set are evaluated together (one pass through the motion field and the
        canonical density; the colour only for the sets placed with ``color``), then each set is composited
        on its own. One set gives exactly :meth:`render_rays`; several give what a call per set gives (each
        sample's values are the same; the parameters' gradients are the same sums, rounded in another
        order), at the cost of one larger pass instead of several small ones: the training step renders its
        batch and the sparse flow prior's matched rays so."""
        kept = [(s.placed.coords[s.placed.idx], s.taus[s.placed.idx[0]]) for s in sets]
        counts = [int(k[0].shape[0]) for k in kept]
        parts: list[Optional[tuple]] = [None] * len(sets)
        if sum(counts) > 0:
            coords, taus = ((kept[0][0], kept[0][1]) if len(sets) == 1 else
                            (torch.cat([k[0] for k in kept]), torch.cat([k[1] for k in kept])))
            sigma, h, canonical, flow = (x.split(counts) for x in self.field.geometry(coords, taus))
            lit = [i for i, s in enumerate(sets) if s.color and counts[i]]
            rgb = [h[i].new_zeros(counts[i], 3) for i in range(len(sets))]
            if lit:
                units = [sets[i].placed.unit[sets[i].placed.idx[0]] for i in lit]
                one = len(lit) == 1
                colours = self.field.colour(h[lit[0]] if one else torch.cat([h[i] for i in lit]),
                                            units[0] if one else torch.cat(units),
                                            kept[lit[0]][1] if one else torch.cat([kept[i][1] for i in lit]))
                for i, c in zip(lit, colours.split([counts[i] for i in lit])):
                    rgb[i] = c
            parts = [(sigma[i], rgb[i], canonical[i], flow[i]) if counts[i] else None for i in range(len(sets))]
        return [self._composite_timed(s, part) for s, part in zip(sets, parts)]

    def _composite_timed(self, samples: TimedSamples, part: Optional[tuple]) -> DynamicRayOutputs:
        placed = samples.placed
        if samples.color and self.field.deferred:  # features composited on zeros, shaded once per ray
            channels = int(self.field.config.geo_feature_dim)
            base = self.composite_placed(placed, None if part is None else part[:2], channels,
                                         self.background.new_zeros(channels))
            kept = None if part is None else (placed.idx, part[1])
            base = base._replace(color=self.shade_rays(base, placed.unit, kept, times=samples.taus))
        else:
            base = self.composite_placed(placed, None if part is None else part[:2])
        flow = placed.coords.new_zeros(placed.coords.shape)
        if part is not None:
            flow = flow.index_put(placed.idx, part[3])
        # both fields' canonical point is the sample plus its flow (K-Planes: plus 0), so the dense canonical
        # points are the samples plus the dense flow (0 where not evaluated): the values of an index_put of
        # the evaluated canonical points, for one add
        canonical = placed.coords.detach() + flow
        outside = placed.keep & ~(canonical.abs() <= 1.0).all(dim=-1)
        return DynamicRayOutputs(*base, canonical, flow, placed.keep, outside)

    def forward(self, origins: Tensor, directions: Tensor, near: Tensor, far: Tensor, times: Tensor
                ) -> DynamicRayOutputs:
        return self.render_rays(origins, directions, near, far, times)


class AtTime:
    """``model`` seen at one time: ``render_rays(origins, directions, near, far)`` renders every ray at
    ``time``, so :func:`~models.fields.components.render.render_image` renders dynamic fields too.

    With ``flow_bins`` (edges of |flow| bins, contracted units) it also accumulates, over every call, the
    number of evaluated samples and of those whose canonical point left the cube, and per bin the number of
    evaluated samples and their summed rendering weight (the visible mass)."""

    def __init__(self, model: DynamicFieldModel, time: float, *, flow_bins: Optional[Sequence[float]] = None):
        self.model, self.time = model, float(time)
        self.bins = None if flow_bins is None else np.asarray(flow_bins, np.float64)
        self.evaluated = 0
        self.outside = 0
        n = 0 if self.bins is None else len(self.bins) - 1
        self.flow_counts = np.zeros(n, np.int64)
        self.flow_mass = np.zeros(n, np.float64)

    def render_rays(self, origins: Tensor, directions: Tensor, near: Tensor, far: Tensor) -> DynamicRayOutputs:
        out = self.model.render_rays(origins, directions, near, far,
                                     torch.full((origins.shape[0],), self.time, device=origins.device))
        if self.bins is not None:
            self.evaluated += int(out.evaluated.sum())
            self.outside += int(out.canonical_outside.sum())
            mags = out.flow[out.evaluated].norm(dim=-1).double().cpu().numpy()
            weights = out.weights[out.evaluated].double().cpu().numpy()
            self.flow_counts += np.histogram(mags, bins=self.bins)[0]
            self.flow_mass += np.histogram(mags, bins=self.bins, weights=weights)[0]
        return out
