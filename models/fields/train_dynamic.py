"""Training and evaluation of dynamic fields (DeRF, SF-DeRF, the K-Planes-style baseline), and a command line.

``train_dynamic(views, config, out_dir)`` writes into the run directory, like ``train_field``:
``config.json`` (the :class:`DynamicTrainConfig`, with the time planes' resolved size), ``checkpoint.pt``
(model, scene, trained time range, optimiser, schedule, sampling generator state, step), ``log.jsonl`` and,
with the sparse flow prior, ``priors/sparse_flow.{npz,json}``. Seeded and resumable: an interrupted run
resumed with the same config ends bit-identical to an uninterrupted one; a larger ``steps`` extends a
finished run.

Variants (``--field.kind``, ``--priors``): ``kplanes`` (4D hex-plane field, no motion model), ``derf``
(canonical field + motion field), ``derf`` with ``--priors flow`` (SF-DeRF, thesis Eq. 5.8).

Command line (the measurement in ``docs/dynamic_fields.md``)::

    python -m models.fields.train_dynamic --scene /tmp/dyn/rig --steps 400 --threads 1 --out runs/dyn/derf
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Optional

import numpy as np
import torch

from engine.core.config import add_options, config_from_args
from engine.core.errors import InputError
from models.fields.components.encodings import plane_l1, plane_tv
from models.fields.components.render import render_image
from models.fields.data.select import (DYNAMIC_DATASETS, DYNAMIC_TEST_SPLITS, detect_dynamic_dataset,
                                       load_dynamic_run_views, select_dynamic_views)
from models.fields.data.timed import TimedViews, border_crossings, check_timed_views
from models.fields.dynamic.model import (AtTime, DynamicFieldConfig, DynamicFieldModel, auto_time_resolution,
                                         time_smoothness)
from models.fields.losses import LossInputs, LossTerm, RayBatch, plane_group, register_loss_term
from models.fields.priors.flow import DynamicPriorsConfig, build_dynamic_priors
from models.fields.static.model import RenderConfig, SceneBox
from models.fields.trainer import (RunConfig, add_renderer_option, apply_loss_weights, check_run,
                                   field_options_given, gl_view_renderer, json_safe, losses_given, resolve_renderer,
                                   run_config_from_file, run_eval_command, run_train_seconds, score_views, train_run,
                                   validate_run_config, view_list)
from models.trainer_cli import DEVICES, resolve_device

__all__ = ["DynamicTrainConfig", "default_dynamic_loss_terms", "MOTION_TERMS", "SLOT_SMOOTH_WEIGHT", "DYNAMIC",
           "train_dynamic", "build_dynamic_model", "load_dynamic_model", "evaluate_dynamic", "model_bytes",
           "canonical_limit", "select_dynamic_views", "load_dynamic_run_views", "detect_dynamic_dataset", "main",
           "eval_main", "FLOW_BINS", "choose_dynamic_priors", "choose_canonical_time", "choose_time_smoothness",
           "MONOCULAR_TIME_SMOOTHNESS", "views_per_time"]

#: Loss terms that act on a motion field; the K-Planes baseline has none and skips them.
MOTION_TERMS = frozenset({"motion_tv", "flow_l1", "sparse_flow", "slot_smooth"})
#: The weight of ``slot_smooth`` that a field with motion slots gets unless ``losses`` names the term (the
#: experiment's, docs/results/2026-11-30-dynamic-units.md).
SLOT_SMOOTH_WEIGHT = 1e-3
#: The weight of ``time_smoothness`` that a ``derf`` field on a monocular capture gets (``choose_time_smoothness``):
#: its motion's time planes pay 30x the default for bending in time, so that the motion continues from one time to
#: the next (docs/results/2026-12-01-monocular-time-smoothness.md).
MONOCULAR_TIME_SMOOTHNESS = 3e-2
#: Bin edges (contracted units) of the flow-magnitude histogram that ``evaluate_dynamic`` reports.
FLOW_BINS = (0.0, 1e-3, 3e-3, 1e-2, 3e-2, 0.1, 0.3, 1.0)


# ----------------------------------------------------------------------------------------------------
# Loss terms of the dynamic fields (plane groups by name, see models/fields/dynamic/model.py)


@register_loss_term("motion_tv")
def motion_tv(inputs: LossInputs) -> torch.Tensor:
    """Total variation of the named plane group (default ``motion_spatial``)."""
    return plane_tv(plane_group(inputs))


@register_loss_term("time_smoothness")
def time_smoothness_term(inputs: LossInputs) -> torch.Tensor:
    """K-Planes' temporal smoothness (second difference along time) of the named group (``temporal``)."""
    return time_smoothness(plane_group(inputs))


@register_loss_term("temporal_l1")
def temporal_l1(inputs: LossInputs) -> torch.Tensor:
    """Mean |1 - feature| of the named time planes (K-Planes: a point whose time planes are 1 is static)."""
    return plane_l1(plane_group(inputs), target=1.0)


@register_loss_term("flow_l1")
def flow_l1(inputs: LossInputs) -> torch.Tensor:
    """Mean L1 norm of the flow over the evaluated samples of the batch: motion costs, so the parts of the
    scene that do not move keep flow 0 (the static parts do not pay for motion). The outputs' flow is 0 where
    no sample was evaluated, so the sum runs over every sample: no gather by the mask, whose backward (an
    accumulating scatter) cost more than the term."""
    out = inputs.outputs
    count = int(out.evaluated.sum())
    if count == 0:
        return out.color.new_zeros(())
    return out.flow.abs().sum() / count


@register_loss_term("slot_smooth")
def slot_smooth(inputs: LossInputs) -> torch.Tensor:
    """Temporal smoothness of the motion slots' keys (``SlotMotion.key_smoothness``: mean squared second
    difference in time); 0 for a field without motion slots. On at :data:`SLOT_SMOOTH_WEIGHT` for a field with
    slots unless ``losses`` names it (``DynamicTrainConfig.loss_terms``)."""
    slots = getattr(getattr(inputs.model.field, "motion_field", None), "slot_motion", None)
    if slots is None:
        return inputs.outputs.color.new_zeros(())
    return slots.key_smoothness()


def default_dynamic_loss_terms() -> tuple[LossTerm, ...]:
    """Photometric loss, TV on the canonical and motion space planes, K-Planes' time smoothness and time-plane
    L1 on the ``temporal`` group, and the flow L1 (DeRF only)."""
    return (LossTerm("photometric", 1.0), LossTerm("plane_tv", 1e-3, planes="spatial"),
            LossTerm("motion_tv", 1e-3, planes="motion_spatial"), LossTerm("time_smoothness", 1e-3, planes="temporal"),
            LossTerm("temporal_l1", 1e-4, planes="temporal"), LossTerm("flow_l1", 1e-2))


# ----------------------------------------------------------------------------------------------------
# Config


@dataclass
class DynamicTrainConfig(RunConfig):
    """Everything that defines a dynamic training run (saved as ``config.json`` beside its outputs): the shared
    :class:`~models.fields.trainer.RunConfig` options, then the dynamic field's."""

    losses: tuple[LossTerm, ...] = field(default_factory=default_dynamic_loss_terms, metadata={
        "help": "named loss terms with weights; see models/fields/train_dynamic.py"})
    occupancy_warmup: int = field(default=64, metadata={"help": "steps before the first occupancy-grid update"})
    occupancy_every: int = field(default=16, metadata={"help": "steps between occupancy-grid updates"})
    occupancy_times: int = field(default=4, metadata={
        "help": "random trained times whose max density each occupancy update keeps"})
    checkpoint_every: int = field(default=500, metadata={"help": "steps between checkpoints (and at the end)"})
    log_every: int = field(default=50, metadata={"help": "steps between log.jsonl lines"})
    priors: DynamicPriorsConfig = field(default_factory=DynamicPriorsConfig, metadata={
        "help": "sparse flow prior (Eq. 5.7); see models/fields/priors/flow.py"})
    priors_choice: str = field(default="", metadata={
        "help": "why the flow prior is on or off, as 'interleave train dynamic' chose it ('auto: ...' from the "
                "field's kind, or 'explicit: ...'); a record, not an input"})
    canonical_time_choice: str = field(default="", metadata={
        "help": "why a derf field's canonical time planes are on or off, as 'interleave train dynamic' chose them "
                "('auto: ...' from the training views' cameras per time, or 'explicit: ...'); a record, not an input"})
    time_smoothness_choice: str = field(default="", metadata={
        "help": "why the time_smoothness loss has its weight, as 'interleave train dynamic' chose it ('auto: ...' "
                "from the training views' cameras per time, or 'explicit: ...'); a record, not an input"})
    render: RenderConfig = field(default_factory=RenderConfig, metadata={"help": "sampling and rendering"})
    # keep last: from here on the class body's name `field` is this attribute, not dataclasses.field
    field: DynamicFieldConfig = field(default_factory=DynamicFieldConfig, metadata={"help": "the dynamic field"})

    #: Fields that record how the run was set up rather than define it (a resumed run may differ in them).
    RECORDS: ClassVar[tuple[str, ...]] = ("priors_choice", "canonical_time_choice", "time_smoothness_choice")

    def validate(self) -> "DynamicTrainConfig":
        """Raise InputError naming the first bad option; returns self."""
        validate_run_config(self, ("steps", "rays_per_batch", "downscale", "occupancy_every", "occupancy_times",
                                   "checkpoint_every", "log_every"))
        if self.field.kind != "derf" and self.priors.enabled():
            raise InputError(f"the sparse flow prior needs a motion field: add --field.kind derf (got "
                             f"{self.field.kind!r})", field="priors.flow.enabled")
        return self

    def loss_terms(self) -> tuple[LossTerm, ...]:
        """``losses`` plus the enabled priors' terms, plus ``slot_smooth`` at :data:`SLOT_SMOOTH_WEIGHT` for a
        field with motion slots whose ``losses`` do not name it (``--loss slot_smooth=W`` sets it, 0 switches it
        off), less the motion terms when the field has no motion model."""
        terms = list(self.losses)
        if self.field.motion.slots and all(t.name != "slot_smooth" for t in terms):
            terms.append(LossTerm("slot_smooth", SLOT_SMOOTH_WEIGHT))
        if self.priors.flow.enabled:
            terms.append(self.priors.flow.loss_term())
        if self.field.kind != "derf":
            terms = [t for t in terms if t.name not in MOTION_TERMS]
        return tuple(terms)


def choose_dynamic_priors(config: DynamicTrainConfig, explicit: Optional[str] = None) -> DynamicTrainConfig:
    """``config`` with the flow prior of a command line and ``priors_choice`` saying why: ``explicit`` (the
    ``--priors`` text, ``''`` for none) wins, then a config that switches the prior on; otherwise it is on for
    a ``derf`` field (with it DeRF moves its objects and scores highest on the rigs and lego,
    docs/results/2026-11-25-dynamic-default.md) and off for ``kplanes``, which has no motion field for it."""
    if explicit is not None:
        names = [n.strip() for n in explicit.split(",") if n.strip()]
        unknown = sorted(set(names) - {"flow"})
        if unknown:
            raise InputError(f"unknown prior(s) {unknown}; choose from ['flow']", field="priors")
        choice = f"explicit: --priors '{','.join(names)}'"
        on = "flow" in names
    elif config.priors.enabled():
        return dataclasses.replace(config, priors_choice="explicit: the config enables flow")
    elif config.field.kind == "derf":
        choice, on = "auto: the sparse flow prior is what makes a DeRF field move its objects", True
    else:
        choice, on = f"auto: a {config.field.kind} field has no motion field for the flow prior", False
    flow = dataclasses.replace(config.priors.flow, enabled=on)
    return dataclasses.replace(config, priors=dataclasses.replace(config.priors, flow=flow), priors_choice=choice)


def views_per_time(views: TimedViews) -> float:
    """The median number of training views that share a time: 1 for a monocular capture (D-NeRF's one view a
    frame), the number of cameras for a synchronized rig."""
    _, counts = np.unique(np.asarray(views.times, np.float64), return_counts=True)
    return float(np.median(counts)) if counts.size else 0.0


def choose_canonical_time(config: DynamicTrainConfig, views: TimedViews, *, explicit: bool = False
                          ) -> DynamicTrainConfig:
    """``config`` with a ``derf`` field's canonical time planes chosen for ``views`` and ``canonical_time_choice``
    saying why. ``explicit`` (the command line or config file sets ``field.canonical_time``) keeps the config's.
    Otherwise they are on where some two views share a time (a synchronized rig: the time planes fit what the
    motion leaves, seen from several cameras at once) and off for a monocular capture (one view a time), where
    nothing but the motion ties one time's view to another's and the time planes fit part of it as appearance
    (D-NeRF lego, three seeds at 2000 and 10,000 steps; monocular cuts of two rigs: one win, one tie;
    docs/results/2026-12-01-dynamic-monocular.md). Times are compared exactly, as a rig's frames share theirs."""
    if config.field.kind != "derf":
        return dataclasses.replace(config, canonical_time_choice=f"a {config.field.kind} field has no canonical field")
    if explicit:
        on = config.field.canonical_time
        return dataclasses.replace(config, canonical_time_choice=f"explicit: {'on' if on else 'off'}")
    shared = views_per_time(views)
    on = shared >= 2
    choice = (f"auto: {'on' if on else 'off'}, "
              f"{'a synchronized capture' if on else 'a monocular capture'} ({shared:g} train "
              f"view{'' if shared == 1 else 's'} a time)")
    return dataclasses.replace(config, field=dataclasses.replace(config.field, canonical_time=on),
                               canonical_time_choice=choice)


def choose_time_smoothness(config: DynamicTrainConfig, views: TimedViews, *, explicit: bool = False
                            ) -> DynamicTrainConfig:
    """``config`` with the ``time_smoothness`` weight chosen for ``views`` and ``time_smoothness_choice`` saying
    why; call it after :func:`choose_canonical_time`. ``explicit`` (the command line or config file names the term)
    keeps the config's weight. Otherwise a ``derf`` field without canonical time planes on a monocular capture (one
    view a time) gets :data:`MONOCULAR_TIME_SMOOTHNESS`: the term then acts on the motion's time planes alone, and
    with one view a time nothing else keeps the motion from bending between times. On D-NeRF lego (five seeds,
    2000 steps) its vectors come 0.65 dB from ``oracle`` at k = 2 instead of 0.77, ``mvec`` gains 0.51 dB and val
    0.53; the monocular cuts of four rigs gain 0.19 dB on the mean of nine runs, none losing more than 0.10
    (docs/results/2026-12-01-monocular-time-smoothness.md, 2026-12-01-field-vectors-seeds.md). Every other run
    keeps the config's weight."""
    weight = next((t.weight if t.enabled else 0.0 for t in config.losses if t.name == "time_smoothness"), 0.0)
    if explicit:
        return dataclasses.replace(config, time_smoothness_choice=f"explicit: {weight:g}")
    shared = views_per_time(views)
    kept = (f"a {config.field.kind} field" if config.field.kind != "derf" else
            f"a synchronized capture ({shared:g} train views a time)" if shared >= 2 else
            "the canonical field has time planes" if config.field.canonical_time else None)
    if kept is not None:
        return dataclasses.replace(config, time_smoothness_choice=f"auto: {weight:g}, {kept}")
    config = apply_loss_weights(config, [f"time_smoothness={MONOCULAR_TIME_SMOOTHNESS!r}"])
    return dataclasses.replace(config, time_smoothness_choice=(
        f"auto: {MONOCULAR_TIME_SMOOTHNESS:g}, a monocular capture's motion ({shared:g} train view a time)"))


def _resolved(config: DynamicTrainConfig, views: TimedViews) -> DynamicTrainConfig:
    """The config with the time planes' rows fixed from the views (what ``config.json`` records)."""
    rows = auto_time_resolution(config.field, len(np.unique(views.times)))
    return dataclasses.replace(config, field=dataclasses.replace(config.field, time_resolution=rows))


# ----------------------------------------------------------------------------------------------------
# Model


def build_dynamic_model(views: TimedViews, config: DynamicTrainConfig) -> DynamicFieldModel:
    """A fresh model for ``views`` (seeded by ``config.seed``): scene and time range from the views."""
    config = _resolved(config, views)
    torch.manual_seed(config.seed)
    return DynamicFieldModel(SceneBox.from_views(views), views.background, views.time_range, config.field,
                             config.render, time_resolution=config.field.time_resolution,
                             occupancy_times=config.occupancy_times)


def _model_from_state(state: dict, config: DynamicTrainConfig) -> DynamicFieldModel:
    return DynamicFieldModel(SceneBox.from_dict(state["scene"]), state["background"], tuple(state["time_range"]),
                             config.field, config.render, time_resolution=int(state["time_resolution"]),
                             occupancy_times=config.occupancy_times)


def load_dynamic_model(run_dir: str | Path) -> DynamicFieldModel:
    """The trained model of a run directory (``config.json`` + ``checkpoint.pt``), in eval mode."""
    run = Path(run_dir)
    for name in ("config.json", "checkpoint.pt"):
        if not (run / name).is_file():
            raise InputError("file does not exist (not a dynamic run directory?)", file=run / name)
    config = DynamicTrainConfig.from_dict(json.loads((run / "config.json").read_text()))
    state = torch.load(run / "checkpoint.pt", map_location="cpu", weights_only=True)
    if "time_range" not in state:
        raise InputError("has no time range: not a dynamic field run", file=run / "checkpoint.pt")
    model = _model_from_state(state, config)
    model.load_state_dict(state["model"])
    return model.eval()


def model_bytes(model: DynamicFieldModel) -> dict[str, int]:
    """float32 bytes of all parameters (``model_bytes``) and of the motion field's (``motion_bytes``)."""
    total = sum(p.numel() for p in model.field.parameters()) * 4
    motion = sum(p.numel() for p in model.field.motion_field.parameters()) * 4 if model.has_motion else 0
    return {"model_bytes": int(total), "motion_bytes": int(motion)}


def _plane_params(model: DynamicFieldModel) -> tuple[list, list]:
    planes, mlps = [], []
    for name, p in model.field.named_parameters():
        (planes if name.startswith("encoding.") or ".encoding." in name else mlps).append(p)
    return planes, mlps


# ----------------------------------------------------------------------------------------------------
# Training


class DynamicKind:
    """The dynamic field's part of the shared training loop (``models.fields.trainer.FieldKind``): time-stamped
    views, the time planes' size fixed from them, ray times, the sparse flow prior (no parameters), the time
    range in the checkpoint and the mean flow in the log."""

    def prepare(self, views: TimedViews, config: DynamicTrainConfig):
        views, config, terms = check_run(views, config, check_timed_views, views.depth is not None)
        return views, _resolved(config, views), terms

    def new_model(self, views: TimedViews, config: DynamicTrainConfig) -> DynamicFieldModel:
        return build_dynamic_model(views, config)

    def model_from_state(self, state: dict, config: DynamicTrainConfig) -> DynamicFieldModel:
        return _model_from_state(state, config)

    def ray_inputs(self, views: TimedViews, model: DynamicFieldModel) -> torch.Tensor:
        ray_times = torch.from_numpy(np.repeat(views.times, views.height * views.width).astype(np.float32))
        model.normalize_times(ray_times)  # the views must lie in the model's range (a resumed run's own range)
        return ray_times

    def build_priors(self, views: TimedViews, config: DynamicTrainConfig, model, cache_dir: Path):
        return build_dynamic_priors(views, config.priors, cache_dir)

    def param_groups(self, model: DynamicFieldModel) -> list[dict]:
        planes, mlps = _plane_params(model)
        return [{"params": planes, "name": "planes"}, {"params": mlps, "name": "mlps"}]

    def render_step(self, priors, model: DynamicFieldModel, batch: RayBatch, inputs: torch.Tensor, step: int,
                    generator: torch.Generator):
        """The batch, then the sparse flow prior's matched rays (drawn after the batch's samples, as a
        separate ``render_rays`` call would draw them), rendered in one pass (``render_placed``)."""
        batch_samples = model.place_timed(batch.origins, batch.directions, batch.near, batch.far, inputs,
                                          jitter=True, generator=generator)
        flow = priors.flow if priors is not None else None
        matched = flow.draw(model, generator) if flow is not None and flow.active(step) else None
        if matched is None:
            return model.render_placed([batch_samples])[0], {}
        outputs, matched_out = model.render_placed(
            [batch_samples, model.place_timed(*matched, jitter=True, generator=generator, color=False)])
        return outputs, flow.entry(matched_out)

    def checkpoint_fields(self, model: DynamicFieldModel) -> dict:
        return {"time_range": list(model.time_range), "time_resolution": model.time_resolution}

    def log_fields(self, outputs) -> dict:
        flow = outputs.flow[outputs.evaluated].detach()
        return {"flow_mean": float(flow.norm(dim=-1).mean()) if flow.numel() else 0.0}


#: The dynamic specifics of the training loop.
DYNAMIC = DynamicKind()


def train_dynamic(views: TimedViews, config: DynamicTrainConfig, out_dir: str | Path, progress: bool = True, *,
                  extras_fn=None, device: str = "auto") -> Path:
    """Train a dynamic field on time-stamped ``views`` and write the run into ``out_dir``; returns ``out_dir``.

    Args:
        views: training views (:class:`~models.fields.data.timed.TimedViews`; every frame of every train
            camera), reduced to ``config.downscale`` if loaded at a finer one.
        config: the run's settings.
        out_dir: the run directory (created; an existing run there with the same config is resumed).
        progress: show a tqdm bar.
        extras_fn: optional ``(model, batch, outputs, step) -> dict`` feeding ``LossInputs.extras``.
        device: ``cpu``, ``cuda`` or ``auto`` (``cuda`` when torch sees a GPU); the same seed draws the same
            rays and samples on either (``models.fields.trainer.train_run``).

    Raises:
        InputError: bad views, config or device, or ``out_dir`` holding a run with a different config.
    """
    return train_run(DYNAMIC, views, config, out_dir, progress, extras_fn=extras_fn, device=device)


# ----------------------------------------------------------------------------------------------------
# Evaluation


def canonical_limit(per_time: list[dict], crossings: dict, *, outside_excess: float = 0.02) -> dict[str, Any]:
    """Detect the canonical-volume limitation (thesis Sec. 5.3.4: objects entering or leaving the scene).

    A time is flagged when (a) moving content crosses the image border of a fixed camera at that time
    (``crossings`` from :func:`~models.fields.data.timed.border_crossings`: an object entering or leaving
    the views, which a single canonical volume holds only at some times), or (b) the model's share of
    evaluated samples whose canonical point left the canonical cube exceeds its median over the evaluated
    times by ``outside_excess`` (the motion field hiding content it cannot place in the canonical volume; a
    constant offset of every time does not count). A motion field that maps content out of the canonical
    volume at every time is reported separately: ``outside_everywhere`` when the mean outside fraction over
    the evaluated times exceeds ``outside_excess``.

    Returns:
        ``{"detected", "flagged_times", "reasons" (time -> list of reasons), "border_crossings" (the events,
        tested and skipped cameras), "outside_excess", "mean_outside_fraction", "outside_everywhere",
        "psnr_flagged", "psnr_unflagged"}``: the last two are
        the mean held-out PSNR at flagged and at other times (NaN where there are none), what flagging costs.
    """
    reasons: dict[float, list[str]] = {}
    for event in crossings.get("events", []):
        reasons.setdefault(float(event["time"]), []).append(f"border crossing in {event['camera']}")
    outside = np.array([p["canonical_outside_fraction"] for p in per_time], np.float64)
    if outside.size:
        excess = outside - np.median(outside)
        for p, e in zip(per_time, excess):
            if e > outside_excess:
                reasons.setdefault(float(p["time"]), []).append(
                    f"canonical outside fraction {p['canonical_outside_fraction']:.3f}")
    flagged = sorted(reasons)
    psnr_f = [p["psnr"] for p in per_time if float(p["time"]) in reasons]
    psnr_u = [p["psnr"] for p in per_time if float(p["time"]) not in reasons]
    return {"detected": bool(flagged), "flagged_times": flagged,
            "reasons": {f"{t:.6g}": reasons[t] for t in flagged},
            "border_crossings": {k: crossings.get(k) for k in ("events", "tested_cameras", "skipped_cameras")},
            "outside_excess": outside_excess,
            "mean_outside_fraction": float(outside.mean()) if outside.size else 0.0,
            "outside_everywhere": bool(outside.size and outside.mean() > outside_excess),
            "psnr_flagged": float(np.mean(psnr_f)) if psnr_f else float("nan"),
            "psnr_unflagged": float(np.mean(psnr_u)) if psnr_u else float("nan")}


#: With ``--renderer gl`` the motion diagnostics come from a torch render this many times smaller per side.
DIAGNOSTICS_STRIDE = 4


def evaluate_dynamic(run_or_model: str | Path | DynamicFieldModel, views: TimedViews, *, chunk: int = 8192,
                     with_flip: bool = True, return_images: bool = False,
                     context_views: Optional[TimedViews] = None, renderer: str = "torch") -> dict[str, Any]:
    """Render every view at its time and score it; the keys of ``models.fields.train_static.evaluate_field`` plus
    the model's size, per-time diagnostics, the flow histogram and the canonical-volume check.

    Scores as ``evaluate_field``: PSNR / SSIM / FLIP on display-encoded images over the whole frame, depth
    MAE and rank correlation over pixels where both depths are finite, median render time per frame.
    Added: ``model_bytes`` / ``motion_bytes`` (float32 parameters); ``per_time``: per distinct time its PSNR
    and ``canonical_outside_fraction``; ``flow_histogram``: |flow| (contracted units) of the evaluated samples
    in ``FLOW_BINS``, by count and by rendering weight (the visible mass); ``flow_moving_fraction``: the share
    of the visible mass whose |flow| exceeds 0.01; ``canonical_limit``: :func:`canonical_limit`, with the
    border crossings found in ``views`` and ``context_views`` (e.g. the training views: they are not rendered).
    ``renderer`` as ``evaluate_field``'s: with ``gl`` the images are the GL renderer's and the motion
    diagnostics (which need the samples) come from a torch render of each view at 1/``DIAGNOSTICS_STRIDE`` of its
    width and height (the same rays' statistics, subsampled). ``psnr_objects`` / ``psnr_background``: the mean
    over views of the PSNR over the pixels that see the scene's objects / the rest (views with object ids:
    rgbd-rig captures; NaN otherwise): the split of the error between what moves and the static background.

    Raises:
        InputError: bad views, or a view whose time lies outside the model's trained range.
    """
    check_timed_views(views)
    model = run_or_model if isinstance(run_or_model, DynamicFieldModel) else load_dynamic_model(run_or_model)
    model.normalize_times(torch.as_tensor(views.times, dtype=torch.float32))  # refuse out-of-range times first
    edges = np.array(FLOW_BINS[:-1] + (max(FLOW_BINS[-1], math.sqrt(3.0) * model.config.motion.max_flow),))
    outside, evaluated = [], []
    counts, mass = np.zeros(len(edges) - 1, np.int64), np.zeros(len(edges) - 1)

    kind = resolve_renderer(renderer)
    gl = gl_view_renderer(model, views) if kind == "gl" else None
    stride = DIAGNOSTICS_STRIDE if gl is not None else 1

    def render_view(i: int, cam) -> dict:
        nonlocal counts, mass
        at = AtTime(model, float(views.times[i]), flow_bins=edges)
        k = np.diag([1.0 / stride, 1.0 / stride, 1.0]) @ np.asarray(cam.intrinsics, np.float64)
        out = render_image(at, k, cam.world_to_camera, max(1, views.height // stride),
                           max(1, views.width // stride), model.scene.near, model.scene.far, chunk=chunk)
        outside.append(at.outside)
        evaluated.append(at.evaluated)
        counts += at.flow_counts
        mass += at.flow_mass
        return out if gl is None else gl.render(cam.intrinsics, cam.world_to_camera, float(views.times[i]))

    try:
        regions = None if views.objects is None else {"objects": views.objects, "background": ~views.objects}
        scores, psnrs, images = score_views(model, views, render_view, with_flip=with_flip,
                                            return_images=return_images, regions=regions)
    finally:
        if gl is not None:
            gl.release()
    per_time = []
    for t in np.unique(views.times):
        sel = np.flatnonzero(views.times == t)
        ev = sum(evaluated[i] for i in sel)
        per_time.append({"time": float(t), "psnr": float(np.mean([psnrs[i] for i in sel])),
                         "canonical_outside_fraction": float(sum(outside[i] for i in sel) / ev) if ev else 0.0})
    scores.setdefault("psnr_objects", float("nan"))  # data without object ids
    scores.setdefault("psnr_background", float("nan"))
    scores.update({
        "train_seconds": (run_train_seconds(run_or_model) if not isinstance(run_or_model, DynamicFieldModel)
                          else float("nan")),
        **model_bytes(model),
        "kind": model.config.kind,
        "renderer": kind,
        "flow_histogram": {"edges": [float(e) for e in edges], "samples": [int(c) for c in counts],
                           "visible_mass": [float(m) for m in mass]},
        "flow_moving_fraction": float(mass[3:].sum() / mass.sum()) if mass.sum() > 0 else 0.0,
        "per_time": per_time,
        "canonical_limit": canonical_limit(per_time, _crossings(views, context_views)),
    })
    if return_images:
        scores["images"] = images
    return scores


def _crossings(views: TimedViews, context: Optional[TimedViews]) -> dict[str, Any]:
    found = [border_crossings(views)] + ([border_crossings(context)] if context is not None else [])
    return {"events": [e for f in found for e in f["events"]],
            "tested_cameras": [c for f in found for c in f["tested_cameras"]],
            "skipped_cameras": [c for f in found for c in f["skipped_cameras"]]}


# ----------------------------------------------------------------------------------------------------
# Command line


def main(argv: Optional[list[str]] = None, prog: str = "python -m models.fields.train_dynamic") -> int:
    """``interleave train dynamic``: train on a dynamic scene, evaluate the held-out views, print the scores."""
    parser = argparse.ArgumentParser(prog=prog, description="Train a dynamic radiance field (K-Planes-style 4D, "
                                                            "DeRF, or DeRF + sparse flow priors) and score it.")
    parser.add_argument("--scene", "--data", dest="data", required=True,
                        help="scene folder: an rgbd-rig video (rig.json) or a D-NeRF scene (layout detected)")
    parser.add_argument("--dataset", choices=list(DYNAMIC_DATASETS), default=None, help="the scene's layout")
    parser.add_argument("--out", default=None, help="run directory (default: runs/dynamic/<scene>-<kind>)")
    parser.add_argument("--cameras", type=int, default=None, help="rig: number of train cameras (spread)")
    parser.add_argument("--train-cameras", default=None, metavar="LIST", help="rig: train cameras, names or positions")
    parser.add_argument("--test-cameras", default=None, metavar="LIST", help="rig: held-out cameras")
    parser.add_argument("--frames", default=None, metavar="LIST", help="rig: frame positions to use (default: all)")
    parser.add_argument("--test-every", type=int, default=1, help="evaluate every k-th held-out view")
    parser.add_argument("--max-test-views", type=int, default=0, help="evaluate at most this many held-out views")
    parser.add_argument("--test-split", choices=list(DYNAMIC_TEST_SPLITS), default="test",
                        help="D-NeRF: the split held out and scored (its val split poses the shovel as in training)")
    parser.add_argument("--priors", dest="prior_names", default=None, metavar="NAMES",
                        help="comma-separated priors to switch on: flow (sparse flow, Eq. 5.7), '' for none (default: "
                             "flow for a derf field, none for kplanes; printed and saved as priors_choice)")
    parser.add_argument("--loss", action="append", default=[], metavar="NAME=WEIGHT",
                        help="set a loss term's weight (0 switches it off); repeatable")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    parser.add_argument("--device", default="auto", metavar="|".join(DEVICES),
                        help="where to train: cpu, cuda, or auto (cuda when torch sees a GPU; default)")
    parser.add_argument("--config", type=Path, default=None, metavar="FILE",
                        help="JSON with any DynamicTrainConfig fields; command-line options override it")
    parser.add_argument("--no-flip", action="store_true", help="skip FLIP in the final evaluation")
    add_renderer_option(parser)
    add_options(parser, DynamicTrainConfig, skip=DynamicTrainConfig.RECORDS)
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        device = resolve_device(args.device)
        config = apply_loss_weights(config_from_args(DynamicTrainConfig, args,
                                                     run_config_from_file(DynamicTrainConfig, args.config)), args.loss)
        config = choose_dynamic_priors(config, args.prior_names)
        print(f"priors: {', '.join(config.priors.enabled()) or 'none'} ({config.priors_choice})", file=sys.stderr)
        dataset = args.dataset or detect_dynamic_dataset(args.data)
        frames = view_list(args.frames, "frames")
        train, test, record = select_dynamic_views(
            dataset, args.data, config.downscale, cameras=args.cameras,
            train_cameras=view_list(args.train_cameras, "train_cameras"),
            test_cameras=view_list(args.test_cameras, "test_cameras"), frames=frames,
            test_every=args.test_every, max_test_views=args.max_test_views, test_split=args.test_split)
        config = choose_canonical_time(dataclasses.replace(config, downscale=record["downscale"]), train,
                                       explicit="canonical_time" in field_options_given(args))
        print(f"canonical time planes: {config.canonical_time_choice}", file=sys.stderr)
        config = choose_time_smoothness(config, train, explicit="time_smoothness" in losses_given(args))
        print(f"time smoothness: {config.time_smoothness_choice}", file=sys.stderr)
        kind = config.field.kind + ("+flow" if config.priors.flow.enabled else "")
        out = Path(args.out) if args.out else Path("runs/dynamic") / f"{Path(args.data).resolve().name}-{kind}"
        run = train_dynamic(train, config, out, device=str(device))
        (out / "data.json").write_text(json.dumps(record, indent=2) + "\n")
        scores = evaluate_dynamic(run, test, with_flip=not args.no_flip, context_views=train,
                                  renderer=args.renderer)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    scores = json_safe({"run": str(out), "dataset": dataset, "train_views": len(train), "test_views": len(test),
                          "image_size": [train.height, train.width], "steps": config.steps, "device": device.type,
                          **scores})
    text = json.dumps(scores, indent=2)
    (out / "scores.json").write_text(text + "\n")
    print(text)
    return 0


def eval_main(argv: Optional[list[str]] = None, prog: str = "interleave eval dynamic") -> int:
    """``interleave eval dynamic RUN_DIR [--json OUT.json] [--split test|val]``: render the run's held-out views
    (or, for D-NeRF, another split's) and score them."""
    return run_eval_command(
        argv, prog, "Render a trained dynamic field's held-out views at their times and print PSNR, SSIM, FLIP, "
                    "depth MAE, train and render time, model size and the motion diagnostics.",
        "interleave train dynamic", load_dynamic_run_views,
        lambda run, test, train, with_flip, images, renderer: evaluate_dynamic(
            run, test, with_flip=with_flip, return_images=images, context_views=train, renderer=renderer),
        lambda run, train, test: {"run": str(run), "train_views": len(train), "test_views": len(test),
                                  "image_size": [test.height, test.width]},
        splits=DYNAMIC_TEST_SPLITS)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
