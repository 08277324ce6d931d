"""Loss assembly: a list of named, weighted, switchable terms.

A run's loss is ``sum(term.weight * term.factor(step) * LOSS_TERMS[term.name](inputs))`` over the enabled
terms of its config whose ``start_step`` has been reached (``factor`` also fades a term out, as the dynamic
fields' flow prior is). Each term is a pure function of :class:`LossInputs` (the model, the
ray batch, the rendered outputs, the step, the term's own config and an ``extras`` dict for outputs of
other models), registered by name with :func:`register_loss_term`. The priors of the thesis slot in as
further terms without touching the training loop:

- ``sparse_depth`` (DS-NeRF, thesis Eq. 3.13) is here already: ``(sum_i w_i t_i - z)^2`` on rays whose
  batch carries a finite depth ``z``;
- Simple-RF's augmented-model depth loss (Eq. 4.9) would read the augmented model's outputs from
  ``extras["augmented"]`` and the reliability masks;
- ViP-NeRF's visibility prior (Eq. 3.8, 3.12) would read the secondary-view visibilities from ``extras``.

Plane regularisers name the plane group they act on (``term.planes``, e.g. ``"spatial"``), resolved with
the field's ``plane_groups()``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Optional

import torch
from torch import Tensor

from engine.core.checks import check_range
from engine.core.errors import InputError
from models.fields.components.encodings import plane_l1, plane_tv
from models.fields.components.render import RayOutputs

__all__ = ["LossTerm", "RayBatch", "LossInputs", "LOSS_TERMS", "register_loss_term", "assemble_loss",
           "default_loss_terms", "srgb_encode", "plane_group", "ray_distortion"]


@dataclass
class LossTerm:
    """One weighted loss term of a run."""

    name: str = field(metadata={"help": "a registered term: photometric, photometric_linear, plane_tv, plane_l1, "
                                        "sparse_depth, distortion (the priors add theirs, "
                                        "models/fields/priors/config.py)"})
    weight: float = field(default=1.0, metadata={"help": "multiplier of the term"})
    enabled: bool = field(default=True, metadata={"help": "switch the term off without losing its settings"})
    planes: str = field(default="spatial", metadata={"help": "plane group a plane regulariser acts on"})
    start_step: int = field(default=0, metadata={"help": "first training step at which the term is applied"})
    fade_start: int = field(default=0, metadata={
        "help": "step from which the weight falls linearly to fade_to over fade_steps (with fade_steps > 0)"})
    fade_steps: int = field(default=0, metadata={"help": "steps of the fall to fade_to (0: the weight never fades)"})
    fade_to: float = field(default=0.0, metadata={"help": "fraction of the weight left after the fade, in [0, 1]"})

    def factor(self, step: int) -> float:
        """The multiplier of ``weight`` at ``step``: 0 when disabled or before ``start_step``, 1 until
        ``fade_start``, then linearly to ``fade_to`` over ``fade_steps`` (``fade_to`` from
        ``fade_start + fade_steps`` on)."""
        if not self.enabled or step < self.start_step:
            return 0.0
        if self.fade_steps <= 0 or step <= self.fade_start:
            return 1.0
        left = max(0.0, 1.0 - (step - self.fade_start) / self.fade_steps)
        return self.fade_to + (1.0 - self.fade_to) * left


def default_loss_terms() -> tuple[LossTerm, ...]:
    """Photometric loss plus a light TV on the spatial planes; L1 and sparse depth present but off."""
    return (LossTerm("photometric", 1.0), LossTerm("plane_tv", 1e-3, planes="spatial"),
            LossTerm("plane_l1", 1e-4, enabled=False, planes="spatial"),
            LossTerm("sparse_depth", 0.1, enabled=False))


@dataclass
class RayBatch:
    """Training rays and what is known about them.

    Attributes:
        origins, directions: (R, 3) world (directions with camera z = 1).
        near, far: (R,) planar-depth bounds.
        color: (R, 3) true linear RGB.
        depth: (R,) true planar depth (NaN or inf where unknown), or None.
        view: (R,) long, index of the training view of each ray.
        pixel: (R,) long, row-major pixel index ``v * W + u`` of each ray in its view, or None.
    """

    origins: Tensor
    directions: Tensor
    near: Tensor
    far: Tensor
    color: Tensor
    depth: Optional[Tensor] = None
    view: Optional[Tensor] = None
    pixel: Optional[Tensor] = None


@dataclass
class LossInputs:
    """Everything a loss term may read."""

    model: Any
    batch: RayBatch
    outputs: RayOutputs
    step: int
    term: LossTerm
    extras: dict[str, Any] = field(default_factory=dict)


LossFn = Callable[[LossInputs], Tensor]
#: name -> term function; add to it with :func:`register_loss_term`.
LOSS_TERMS: dict[str, LossFn] = {}
#: names of terms that need true depth in the batch.
NEEDS_DEPTH: set[str] = set()


def register_loss_term(name: str, *, needs_depth: bool = False) -> Callable[[LossFn], LossFn]:
    """Decorator registering a loss term under ``name`` (a config's ``LossTerm.name``)."""
    def wrap(fn: LossFn) -> LossFn:
        LOSS_TERMS[name] = fn
        if needs_depth:
            NEEDS_DEPTH.add(name)
        return fn
    return wrap


def srgb_encode(linear: Tensor) -> Tensor:
    """Differentiable sRGB transfer function of linear values clipped to [0, 1] (``display_encode`` in torch)."""
    c = linear.clamp(0.0, 1.0)
    curve = 1.055 * c.clamp_min(0.0031308) ** (1.0 / 2.4) - 0.055
    return torch.where(c <= 0.0031308, 12.92 * c, curve)


@register_loss_term("photometric")
def photometric(inputs: LossInputs) -> Tensor:
    """MSE of display-encoded (sRGB) colours: what PSNR measures and what NeRF trains on (Eq. 3.6)."""
    return (srgb_encode(inputs.outputs.color) - srgb_encode(inputs.batch.color)).square().mean()


@register_loss_term("photometric_linear")
def photometric_linear(inputs: LossInputs) -> Tensor:
    """MSE of linear colours."""
    return (inputs.outputs.color - inputs.batch.color).square().mean()


def plane_group(inputs: LossInputs) -> list[Tensor]:
    """The planes of the group the term names (``term.planes``, e.g. ``spatial``); InputError if the field has none."""
    groups = inputs.model.field.plane_groups()
    if inputs.term.planes not in groups:
        raise InputError(f"unknown plane group {inputs.term.planes!r}; the field has {sorted(groups)}",
                         field=f"losses[{inputs.term.name}].planes")
    return groups[inputs.term.planes]


@register_loss_term("plane_tv")
def plane_tv_term(inputs: LossInputs) -> Tensor:
    """Total variation of the named plane group (K-Planes' plane TV)."""
    return plane_tv(plane_group(inputs))


@register_loss_term("plane_l1")
def plane_l1_term(inputs: LossInputs) -> Tensor:
    """Mean |feature| of the named plane group (sparsity: empty space)."""
    return plane_l1(plane_group(inputs))


@register_loss_term("sparse_depth", needs_depth=True)
def sparse_depth(inputs: LossInputs) -> Tensor:
    """DS-NeRF depth supervision (Eq. 3.13): mean of (sum w t - z)^2 over rays with a finite true depth z."""
    z = inputs.batch.depth
    if z is None:
        return inputs.outputs.expected_depth.new_zeros(())
    known = torch.isfinite(z)
    if not bool(known.any()):
        return inputs.outputs.expected_depth.new_zeros(())
    return (inputs.outputs.expected_depth[known] - z[known]).square().mean()


def ray_distortion(weights: Tensor) -> Tensor:
    """Mip-NeRF 360's distortion (its Eq. 15) of each ray's weights (R, N), in the sampler's own normalised
    coordinate: sample i is the interval [i/N, (i+1)/N) (the samples are uniform in t for bounded scenes and in
    1/t for forward-facing ones, so that coordinate is the one they are spread evenly in) ->
    (R,) ``sum_ij w_i w_j |m_i - m_j| + sum_i w_i^2 / (3N)``, m the intervals' midpoints. O(N) per ray: the pairs
    are ``2 sum_i w_i (m_i W_<i - (wm)_<i)`` with exclusive prefix sums."""
    n = weights.shape[-1]
    mid = (torch.arange(n, dtype=weights.dtype, device=weights.device) + 0.5) / n
    wm = weights * mid
    before_w = torch.cumsum(weights, dim=-1) - weights
    before_wm = torch.cumsum(wm, dim=-1) - wm
    pairs = 2.0 * (weights * (mid * before_w - before_wm)).sum(dim=-1)
    return pairs + weights.square().sum(dim=-1) / (3.0 * n)


@register_loss_term("distortion")
def distortion(inputs: LossInputs) -> Tensor:
    """Mean :func:`ray_distortion` over the batch: pulls each ray's weight into one compact interval (fewer
    floaters and smears in depth from few views)."""
    return ray_distortion(inputs.outputs.weights).mean()


def check_loss_terms(terms, has_depth: bool) -> None:
    """Raise InputError for unknown names, negative weights, or depth terms without depth."""
    for term in terms:
        if term.name not in LOSS_TERMS:
            raise InputError(f"unknown loss term {term.name!r}; registered: {sorted(LOSS_TERMS)}", field="losses")
        check_range(term.weight, f"losses[{term.name}].weight", low=0)
        for name in ("start_step", "fade_start", "fade_steps"):
            check_range(getattr(term, name), f"losses[{term.name}].{name}", low=0, integer=True)
        check_range(term.fade_to, f"losses[{term.name}].fade_to", low=0, high=1)
        if term.enabled and term.name in NEEDS_DEPTH and not has_depth:
            raise InputError(f"term {term.name!r} needs true depth, and these views have none",
                             field=f"losses[{term.name}]")


def assemble_loss(terms, model, batch: RayBatch, outputs: RayOutputs, step: int,
                  extras: Optional[dict[str, Any]] = None) -> tuple[Tensor, dict[str, float]]:
    """Weighted sum of the active terms, and each active term's unweighted value (for logs)."""
    total = outputs.color.new_zeros(())
    values: dict[str, float] = {}
    for term in terms:
        scale = term.weight * term.factor(step)
        if scale == 0:
            continue
        value = LOSS_TERMS[term.name](LossInputs(model, batch, outputs, step, term, extras or {}))
        total = total + scale * value
        values[term.name] = float(value.detach())
    return total, values
