"""The sparse-input priors of thesis Ch. 3-4, switchable per run: ``depth`` (DS-NeRF sparse depth from
SIFT, ``priors_depth``), ``simple`` (Simple-RF augmented model, ``priors_simple``), ``vip`` (ViP-NeRF
visibility, ``priors_vip``), and ``distortion`` (mip-NeRF 360's distortion loss on the batch's own rays, no
state: ``models.fields.losses.ray_distortion``).

A run's :class:`PriorsConfig` (``FieldTrainConfig.priors``) says which are on and holds their knobs and
weights; :func:`prior_loss_terms` turns the enabled ones into named :class:`~models.fields.losses.LossTerm`
s appended to the run's loss, and :class:`Priors` (built by ``train_field``) holds their per-run state
(cached matches / visibility maps, the augmented model, the visibility head), whose parameters join the
optimiser (group ``priors``) and whose state is saved in the checkpoint under ``priors``. Each step
``Priors.extras`` renders what the terms need (keypoint rays, the augmented model's rays, secondary-view
visibilities) into ``LossInputs.extras``.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Sequence

import torch
from torch import nn

from engine.core.checks import check_range
from engine.core.errors import InputError
from models.fields.losses import LossTerm
from models.fields.priors.depth import DEPTH_SOURCES, SparseDepthPrior, SparseDepthState
from models.fields.priors.simple import AugmentedState, SimplePrior
from models.fields.priors.vip import VisibilityPrior, VisibilityState

__all__ = ["PRIOR_NAMES", "DistortionPrior", "PriorsConfig", "with_priors", "prior_loss_terms", "Priors", "build_priors",
           "PriorRule", "PRIORS_THAT_PAY", "auto_priors", "auto_loss_weights", "auto_field_options"]

PRIOR_NAMES = ("depth", "simple", "vip", "distortion")


@dataclass
class DistortionPrior:
    """Mip-NeRF 360's distortion loss (``models.fields.losses.ray_distortion``): each ray's weight pulled into
    one compact interval."""

    enabled: bool = field(default=False, metadata={"help": "add the distortion loss on the batch's rays"})
    weight: float = field(default=0.01, metadata={"help": "its weight (mean over the batch's rays)"})


@dataclass(frozen=True)
class PriorRule:
    """The priors that paid on one kind of scene up to ``max_views`` train views, the loss weights that paid
    there too (``(term, weight)``, as ``--loss TERM=WEIGHT``), the field options that did (``(name, value)``,
    as ``--field.NAME VALUE``), and the measurement."""

    max_views: int
    names: tuple[str, ...]
    evidence: str
    loss_weights: tuple[tuple[str, float], ...] = ()
    field_options: tuple[tuple[str, Any], ...] = ()


#: What paid in the prior ablation (``tools.field_ablation``, one seed; differences under ~0.6 dB are not
#: resolved), ``docs/results/2026-11-22-static-field-priors.md``, and on the forward-facing rigs since (two
#: seeds): per scene type, up to how many train views, which priors and which loss weights.
PRIORS_THAT_PAY: dict[str, PriorRule] = {
    "bounded-360": PriorRule(4, ("depth", "simple", "vip"),
                             "lego 100x100, 4 views: all three +2.7 dB (each alone +0.6 to +1.9); 8 views: none "
                             "pays (sparse depth -1.0 dB)"),
    "forward-facing": PriorRule(3, ("depth", "distortion"),
                                "generated forward-facing 320x180: sparse depth +2.7 / +1.5 dB at 2 / 3 views, all "
                                "three within 0.2 dB of it at 3-5x the time, Simple-RF and ViP alone -0.1 to "
                                "-1.7 dB; 4 views: every prior costs 0.4-1.7 dB; the distortion loss on top, three "
                                "504x378 rigs, 3 views, two seeds: +1.65 / +1.09 / -0.45 dB, "
                                "docs/results/2026-11-29-ff-distortion.md; the plane TV at 0.01 instead of 0.001 on "
                                "top, same rigs and seeds: +0.37 / +0.51 / +0.59 dB, "
                                "docs/results/2026-11-29-ff-ablations.md; a fourth plane scale (256) on top, same "
                                "rigs and the path-traced capture, two seeds: +0.41 to +1.63 dB on all 8 runs "
                                "(+0.99 mean) at 1.48x the training time, "
                                "docs/results/2026-11-30-ff-plane-scales.md",
                                loss_weights=(("plane_tv", 0.01),),
                                field_options=(("resolutions", (32, 64, 128, 256)),)),
}


def auto_priors(num_views: int, scene_type: str) -> tuple[tuple[str, ...], str]:
    """(priors to switch on, the reason in words) for a run with ``num_views`` train views of a ``scene_type``
    scene, from :data:`PRIORS_THAT_PAY`: the priors that paid with that few views, none with more.

    >>> auto_priors(3, "forward-facing")[0], auto_priors(4, "forward-facing")[0]
    (('depth', 'distortion'), ())
    """
    rule = _rule(num_views, scene_type)
    if num_views <= rule.max_views:
        weights = "".join(f" and {name}={weight:g}" for name, weight in rule.loss_weights)
        weights += "".join(f" and field.{name}={','.join(map(str, value)) if isinstance(value, tuple) else value}"
                           for name, value in rule.field_options)
        return rule.names, (f"{num_views} train views <= {rule.max_views} on a {scene_type} scene: "
                            f"{','.join(rule.names)}{weights} paid ({rule.evidence})")
    return (), (f"{num_views} train views > {rule.max_views} on a {scene_type} scene: no prior paid "
                f"({rule.evidence})")


def auto_loss_weights(num_views: int, scene_type: str) -> tuple[tuple[str, float], ...]:
    """The ``(term, weight)`` pairs :data:`PRIORS_THAT_PAY` sets for a run with ``num_views`` train views of a
    ``scene_type`` scene (none with more views than its rule's).

    >>> auto_loss_weights(3, "forward-facing"), auto_loss_weights(4, "forward-facing")
    ((('plane_tv', 0.01),), ())
    """
    rule = _rule(num_views, scene_type)
    return rule.loss_weights if num_views <= rule.max_views else ()


def auto_field_options(num_views: int, scene_type: str) -> tuple[tuple[str, Any], ...]:
    """The ``(name, value)`` field options :data:`PRIORS_THAT_PAY` sets for a run with ``num_views`` train views
    of a ``scene_type`` scene (none with more views than its rule's).

    >>> auto_field_options(3, "forward-facing"), auto_field_options(3, "bounded-360")
    ((('resolutions', (32, 64, 128, 256)),), ())
    """
    rule = _rule(num_views, scene_type)
    return rule.field_options if num_views <= rule.max_views else ()


def _rule(num_views: int, scene_type: str) -> PriorRule:
    """The rule of ``scene_type``, after checking both arguments."""
    if isinstance(num_views, bool) or not isinstance(num_views, int) or num_views < 1:
        raise InputError(f"must be a positive integer, got {num_views!r}", field="num_views")
    if scene_type not in PRIORS_THAT_PAY:
        raise InputError(f"must be one of {sorted(PRIORS_THAT_PAY)}, got {scene_type!r}", field="scene_type")
    return PRIORS_THAT_PAY[scene_type]


@dataclass
class PriorsConfig:
    """Which sparse-input priors a run uses, and their settings."""

    depth: SparseDepthPrior = field(default_factory=SparseDepthPrior, metadata={"help": "DS-NeRF sparse depth"})
    simple: SimplePrior = field(default_factory=SimplePrior, metadata={"help": "Simple-RF augmented model"})
    vip: VisibilityPrior = field(default_factory=VisibilityPrior, metadata={"help": "ViP-NeRF visibility"})
    distortion: DistortionPrior = field(default_factory=DistortionPrior, metadata={
        "help": "mip-NeRF 360 distortion loss"})

    def enabled(self) -> list[str]:
        """Names of the priors switched on."""
        return [name for name in PRIOR_NAMES if getattr(self, name).enabled]

    def validate(self) -> "PriorsConfig":
        """Raise InputError naming the first bad option; returns self."""
        check_range(self.depth.rays, "priors.depth.rays", low=1, integer=True)
        if self.depth.source not in DEPTH_SOURCES:
            raise InputError(f"must be one of {DEPTH_SOURCES}, got {self.depth.source!r}", field="priors.depth.source")
        self.depth.stereo.validate()
        check_range(self.simple.near_shift, "priors.simple.near_shift", low=0, high=1, high_open=True)
        if self.simple.patch_size < 1 or self.simple.patch_size % 2 == 0:
            raise InputError(f"must be odd and >= 1, got {self.simple.patch_size}", field="priors.simple.patch_size")
        check_range(self.simple.mass_intervals, "priors.simple.mass_intervals", low=1, integer=True)
        check_range(self.vip.num_planes, "priors.vip.num_planes", low=2, integer=True)
        check_range(self.vip.start_fraction, "priors.vip.start_fraction", low=0, high=1)
        check_range(self.vip.rays, "priors.vip.rays", low=1, integer=True)
        for name, value in (("depth.weight", self.depth.weight), ("simple.photometric_weight",
                            self.simple.photometric_weight), ("simple.mass_weight", self.simple.mass_weight),
                            ("simple.depth_weight", self.simple.depth_weight), ("vip.prior_weight",
                            self.vip.prior_weight), ("vip.consistency_weight", self.vip.consistency_weight),
                            ("distortion.weight", self.distortion.weight)):
            check_range(value, f"priors.{name}", low=0)
        return self


def with_priors(priors: PriorsConfig, names: Sequence[str]) -> PriorsConfig:
    """``priors`` with exactly ``names`` (a subset of ``PRIOR_NAMES``) switched on."""
    unknown = sorted(set(names) - set(PRIOR_NAMES))
    if unknown:
        raise InputError(f"unknown prior(s) {unknown}; choose from {list(PRIOR_NAMES)}", field="priors")
    return dataclasses.replace(priors, **{name: dataclasses.replace(getattr(priors, name), enabled=name in names)
                                          for name in PRIOR_NAMES})


def prior_loss_terms(priors: PriorsConfig, steps: int) -> tuple[LossTerm, ...]:
    """The loss terms of the enabled priors (their weights and start steps come from ``priors``)."""
    terms: list[LossTerm] = []
    if priors.depth.enabled:
        terms.append(LossTerm("sift_depth", priors.depth.weight, start_step=priors.depth.start_step))
    if priors.simple.enabled:
        s = priors.simple
        terms += [LossTerm("augmented_photometric", s.photometric_weight),
                  LossTerm("mass_concentration", s.mass_weight),
                  LossTerm("augmented_depth", s.depth_weight, start_step=int(s.depth_start_fraction * steps))]
    if priors.vip.enabled:
        v = priors.vip
        terms += [LossTerm("visibility_prior", v.prior_weight, start_step=int(v.start_fraction * steps)),
                  LossTerm("visibility_consistency", v.consistency_weight)]
    if priors.distortion.enabled:
        terms.append(LossTerm("distortion", priors.distortion.weight))
    return tuple(terms)


class Priors(nn.Module):
    """Per-run state of the enabled priors (see the module doc); ``None`` slots for disabled ones."""

    def __init__(self, views, config, model, cache_dir: Optional[str | Path] = None):
        super().__init__()
        p = config.priors
        self.depth = SparseDepthState(views, p.depth, cache_dir) if p.depth.enabled else None
        self.simple = AugmentedState(views, config, p.simple, model) if p.simple.enabled else None
        self.vip = VisibilityState(views, config, p.vip, cache_dir) if p.vip.enabled else None

    def update_occupancy(self, generator: torch.Generator) -> None:
        """The augmented model's occupancy-grid callback (the main model's is the training loop's)."""
        if self.simple is not None:
            self.simple.model.update_occupancy(generator)

    def extras(self, model, batch, outputs, step: int, generator: torch.Generator) -> dict[str, Any]:
        """Everything the enabled priors' loss terms read this step."""
        extras: dict[str, Any] = {}
        if self.depth is not None:
            extras.update(self.depth.extras(model, generator))
        if self.simple is not None:
            extras.update(self.simple.extras(model, batch, outputs, generator))
        if self.vip is not None:
            extras.update(self.vip.extras(model, batch, outputs, step, generator))
        return extras


def build_priors(views, config, model, cache_dir: Optional[str | Path] = None) -> Optional[Priors]:
    """The run's :class:`Priors`, or None when no prior is enabled."""
    if not config.priors.enabled():
        return None
    return Priors(views, config, model, cache_dir)
