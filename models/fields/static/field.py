"""The static radiance field: tri-plane features -> density MLP (F1) -> colour MLP (F2).

Thesis Eq. 4.1: ``sigma_i, h_i = F1(p_i)``, ``c_i = F2(h_i, v)``. Here ``F1`` is the K-Planes-style
multi-resolution tri-plane encoding (features multiplied across the xy, xz, yz planes and concatenated
across scales) followed by a tiny MLP, and ``F2`` a tiny MLP on ``h_i`` and the encoded view direction.

Inputs are *contracted* coordinates in [-1, 1]^3 (the model maps world points there, see
``models/fields/components/sampling.py``) and unit view directions in world axes. Colour is linear RGB in [0, 1]
(sigmoid); density is ``exp`` of the MLP output, clamped before the exponential (``MAX_LOG_DENSITY``) so
it is always finite. Plain torch only (grid_sample, Linear, ReLU, exp, sigmoid): exportable to ONNX.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import torch
from torch import Tensor, nn

from engine.core.checks import check_range
from engine.core.errors import InputError
from models.fields.components.encodings import MLP, DirectionEncoding, TriPlaneEncoding

__all__ = ["FieldConfig", "TriPlaneField", "MAX_LOG_DENSITY", "SHADINGS", "bounded_tanh", "density_activation",
           "shade_pixels"]

#: Density is exp(min(raw, MAX_LOG_DENSITY)): at most ~3.3e6 per scene unit, so sigma * delta never
#: overflows float32 and rendering needs no NaN guards.
MAX_LOG_DENSITY = 15.0

DIRECTION_ENCODINGS = ("sh", "fourier", "none")
#: How colour is made: ``per-sample`` (the colour MLP at every sample, NeRF) or ``deferred`` (SNeRG / MERF: the
#: features composited with the weights, the colour MLP once per pixel; see :meth:`TriPlaneField.shade_pixels`).
SHADINGS = ("per-sample", "deferred")


@dataclass
class FieldConfig:
    """Size of the tri-plane field (one per component, saved with every run)."""

    resolutions: tuple[int, ...] = field(default=(32, 64, 128), metadata={
        "help": "plane side per scale, coarse to fine (K-Planes multi-resolution)"})
    feature_dim: int = field(default=8, metadata={"help": "feature channels per plane and scale"})
    init_range: tuple[float, float] = field(default=(0.1, 0.5), metadata={
        "help": "plane features start uniform in this range (K-Planes space planes)"})
    density_hidden: int = field(default=32, metadata={"help": "hidden width of the density MLP (F1)"})
    density_layers: int = field(default=1, metadata={"help": "hidden layers of the density MLP (F1)"})
    geo_feature_dim: int = field(default=15, metadata={"help": "latent h passed from F1 to the colour MLP"})
    color_hidden: int = field(default=32, metadata={"help": "hidden width of the colour MLP (F2)"})
    color_layers: int = field(default=1, metadata={"help": "hidden layers of the colour MLP"})
    direction_encoding: str = field(default="sh", metadata={
        "help": "view-direction encoding: sh (spherical harmonics), fourier, or none (Lambertian colour)"})
    direction_degree: int = field(default=3, metadata={
        "help": "SH bands (1-4) or Fourier frequencies of the direction encoding"})
    density_bias: float = field(default=0.0, metadata={
        "help": "added to the raw density before exp (negative: start emptier)"})
    residual_density_grad: bool = field(default=True, metadata={
        "help": "deferred: let the view-dependent residual's gradient reach the densities (default); off, it "
                "reads the same composited features but its gradient stops at the weights, so the geometry is "
                "fitted through the diffuse colour alone (the render is the same; -2.2 dB on lego 8 views, "
                "docs/results/2026-11-28-baked-fields.md)"})
    residual_bound: float = field(default=2.0, metadata={
        "help": "deferred: in training, the colour MLP's outputs past +-this are pulled back (tanh's gradient plus "
                "that of mean(relu(|x| - bound)^2)), so the residual cannot stick where tanh is flat and the "
                "colour out of range; renders are unchanged; 0 turns it off "
                "(docs/results/2026-11-28-baked-features.md)"})
    shading: str = field(default="per-sample", metadata={
        "help": "per-sample: the colour MLP at every sample; deferred: sigmoid features (the first 3 a diffuse "
                "RGB) composited with the volume-rendering weights and the colour MLP once per pixel on them and "
                "the view direction (SNeRG/MERF), what a baked asset renders exactly"})

    def validate(self) -> "FieldConfig":
        """Raise InputError naming the first bad option; returns self."""
        if not self.resolutions or any(int(r) < 2 for r in self.resolutions):
            raise InputError(f"must be a non-empty list of sizes >= 2, got {self.resolutions}",
                             field="field.resolutions")
        for name in ("feature_dim", "density_hidden", "density_layers", "geo_feature_dim", "color_hidden"):
            check_range(getattr(self, name), f"field.{name}", low=1, integer=True)
        if self.direction_encoding not in DIRECTION_ENCODINGS:
            raise InputError(f"must be one of {DIRECTION_ENCODINGS}, got {self.direction_encoding!r}",
                             field="field.direction_encoding")
        if self.shading not in SHADINGS:
            raise InputError(f"must be one of {SHADINGS}, got {self.shading!r}", field="field.shading")
        if self.shading == "deferred" and int(self.geo_feature_dim) < 3:
            raise InputError(f"must be >= 3 with deferred shading (the first 3 are the diffuse colour), got "
                             f"{self.geo_feature_dim}", field="field.geo_feature_dim")
        check_range(self.residual_bound, "field.residual_bound", low=0)
        if self.direction_encoding == "sh" and not 1 <= self.direction_degree <= 4:
            raise InputError(f"SH bands must be in 1..4, got {self.direction_degree}", field="field.direction_degree")
        return self


class _BoundedTanh(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor, bound: float) -> Tensor:
        y = torch.tanh(x)
        ctx.save_for_backward(x, y)
        ctx.bound = bound
        return y

    @staticmethod
    def backward(ctx, grad: Tensor):
        x, y = ctx.saved_tensors
        pull = torch.relu(x.abs() - ctx.bound) * torch.sign(x) * (2.0 / x.numel())
        return grad * (1.0 - y * y) + pull, None


def bounded_tanh(x: Tensor, bound: float) -> Tensor:
    """``tanh(x)``, whose gradient also carries that of ``mean(relu(|x| - bound)^2)`` (weight 1, mean over every
    element of ``x``): logits past ``+-bound`` are pulled back even where tanh is flat and the loss has none.
    The value is tanh's exactly; ``bound`` <= 0 is plain ``torch.tanh``."""
    if bound <= 0.0 or not (torch.is_grad_enabled() and x.requires_grad):
        return torch.tanh(x)
    return _BoundedTanh.apply(x, float(bound))


def density_activation(raw: Tensor, bias: float = 0.0) -> Tensor:
    """``exp(min(raw + bias, MAX_LOG_DENSITY))``: positive, finite, exportable."""
    return torch.exp(torch.clamp(raw + bias, max=MAX_LOG_DENSITY))


def shade_pixels(field: nn.Module, features: Tensor, opacity: Tensor, directions: Tensor, background: Tensor,
                 residual_inputs: Optional[tuple[Tensor, Tensor]] = None, extra: Optional[Tensor] = None) -> Tensor:
    """Deferred shading (SNeRG / MERF), shared by the static and the dynamic fields: a ray's composited features
    ``F = sum_i w_i sigmoid(h_i)`` (..., G), its opacity ``A = sum_i w_i`` (...) and unit view direction (..., 3)
    -> linear RGB (..., 3): ``F[:3] + (1 - A) background + A tanh(F2([F, enc(d), extra]))`` (a diffuse colour
    composited as usual plus a view-dependent residual that vanishes where nothing is hit).

    Args:
        field: holds ``color_mlp`` (F2), ``direction_encoding`` and ``config.residual_bound``.
        residual_inputs: (F, A) for the residual term, equal in value but composited with other gradients
            (``residual_density_grad``).
        extra: (..., E) further per-pixel inputs of F2 after the direction encoding (a dynamic field's encoded
            time), or None.
    """
    res_features, res_opacity = residual_inputs if residual_inputs is not None else (features, opacity)
    inputs = [res_features, field.direction_encoding(directions)] + ([] if extra is None else [extra])
    residual = bounded_tanh(field.color_mlp(torch.cat(inputs, dim=-1)), field.config.residual_bound)
    return features[..., :3] + (1.0 - opacity)[..., None] * background + res_opacity[..., None] * residual


class TriPlaneField(nn.Module):
    """K-Planes-style static field (nerfstudio's ``Field``: ``get_density`` then ``get_outputs``).

    >>> f = TriPlaneField(FieldConfig(resolutions=(8,), feature_dim=4))
    >>> sigma, h = f.get_density(torch.zeros(10, 3))
    >>> f.get_outputs(h, torch.nn.functional.normalize(torch.ones(10, 3), dim=-1)).shape
    torch.Size([10, 3])
    """

    def __init__(self, config: Optional[FieldConfig] = None):
        super().__init__()
        self.config = cfg = (config or FieldConfig()).validate()
        self.encoding = TriPlaneEncoding(cfg.resolutions, cfg.feature_dim, tuple(cfg.init_range))
        self.density_mlp = MLP(self.encoding.output_dim, cfg.density_hidden, 1 + cfg.geo_feature_dim,
                               layers=cfg.density_layers)
        self.direction_encoding = DirectionEncoding(cfg.direction_encoding, cfg.direction_degree)
        self.color_mlp = MLP(cfg.geo_feature_dim + self.direction_encoding.output_dim, cfg.color_hidden, 3,
                             layers=cfg.color_layers)

    # named plane groups -------------------------------------------------------------------------------
    def spatial_planes(self) -> list[Tensor]:
        """The spatial plane group (xy, xz, yz per scale); what plane regularisers act on."""
        return self.encoding.spatial_planes()

    def plane_groups(self) -> dict[str, list[Tensor]]:
        """Plane groups by name, for loss terms that name the group they act on."""
        return {"spatial": self.spatial_planes()}

    # F1, F2 -----------------------------------------------------------------------------------------
    def get_density(self, coords: Tensor) -> tuple[Tensor, Tensor]:
        """F1: (..., 3) contracted coordinates -> density (...) per scene unit, latent h (..., geo_feature_dim)."""
        out = self.density_mlp(self.encoding(coords))
        return density_activation(out[..., 0], self.config.density_bias), out[..., 1:]

    def get_outputs(self, geo_features: Tensor, directions: Tensor) -> Tensor:
        """F2: latent h (..., G) and unit view directions (..., 3) -> linear RGB (..., 3) in [0, 1]."""
        x = torch.cat([geo_features, self.direction_encoding(directions)], dim=-1)
        return torch.sigmoid(self.color_mlp(x))

    @property
    def deferred(self) -> bool:
        """True for deferred shading: :meth:`forward` gives features, :meth:`shade_pixels` the colour."""
        return self.config.shading == "deferred"

    def shade_pixels(self, features: Tensor, opacity: Tensor, directions: Tensor, background: Tensor,
                     residual_inputs: Optional[tuple[Tensor, Tensor]] = None) -> Tensor:
        """Deferred shading (:func:`shade_pixels`) with this field's colour MLP on ``[F, enc(d)]``."""
        return shade_pixels(self, features, opacity, directions, background, residual_inputs)

    def forward(self, coords: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        """(..., 3) contracted coordinates, (..., 3) unit directions -> density (...), linear RGB (..., 3); with
        deferred shading the second output is the sample's features ``sigmoid(h)`` (..., G) instead."""
        sigma, h = self.get_density(coords)
        if self.deferred:
            return sigma, torch.sigmoid(h)
        return sigma, self.get_outputs(h, directions)
