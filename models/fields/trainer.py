"""The one training loop, run directory, log, checkpoint and evaluation of static and dynamic fields.

``train_run(kind, views, config, out_dir)`` trains the field that ``kind`` (a :class:`FieldKind`: what
differs between a static and a dynamic field, ``models.fields.train_static.STATIC`` and
``models.fields.train_dynamic.DYNAMIC``) builds and writes into the run directory ``out_dir``:

- ``config.json``: the run config that produced the run (nested configs included);
- ``checkpoint.pt``: model, scene, what the kind adds (a dynamic field's time range), optimiser, schedule,
  the sampling generator's state, the step and the enabled priors' state;
- ``log.jsonl``: one line per ``log_every`` steps (loss terms, learning rate, occupied fraction and what the
  kind adds).

Runs are seeded (parameter initialisation and every random choice come from ``config.seed``) and resumable:
training again on the same directory continues from the last checkpoint; a different config is refused,
except for ``steps``. An interrupted run resumed with the same config ends bit-identical to an
uninterrupted one (CPU). A larger ``steps`` extends a finished run, with the learning-rate schedule
stretched to the new length from the current step on (so not identical to a run planned that long).

:func:`score_views` is the shared evaluation (PSNR / SSIM / FLIP on display-encoded images, depth errors,
render time) and :func:`run_eval_command` the ``interleave eval field|dynamic`` command around it.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Protocol

import cv2
import numpy as np
import torch
from tqdm import tqdm

from engine.core.colorspace import display_encode
from engine.core.config import config_from_dict, config_from_file, config_to_dict
from engine.core.checks import check_range
from engine.core.errors import InputError
from engine.eval.metrics import flip_map, psnr, ssim_map
from models.fields.components.sampling import camera_rays
from models.trainer_cli import resolve_device
from models.fields.losses import LossTerm, RayBatch, assemble_loss, check_loss_terms

__all__ = ["LR_SCHEDULES", "rays_to", "RunConfig",
           "FieldKind", "train_run", "validate_run_config", "lr_factor", "matching_views",
           "check_run", "all_rays", "take_rays", "open_run_dir", "restore_training_state", "open_log", "run_config_to_dict",
           "run_config_from_dict", "run_config_from_file", "losses_given", "field_options_given", "apply_loss_weights",
           "view_list", "rank_correlation",
           "run_train_seconds", "score_views", "json_safe", "write_renders", "run_eval_command", "RENDERERS",
           "resolve_renderer", "add_renderer_option", "gl_view_renderer"]

LR_SCHEDULES = ("cosine", "exponential", "constant")

#: ``--renderer`` values of ``interleave eval field|dynamic``: who renders the held-out views.
RENDERERS = ("auto", "torch", "gl")


def resolve_renderer(name: str) -> str:
    """``torch`` or ``gl`` for a ``--renderer`` value (:data:`RENDERERS`). ``auto`` is ``gl`` where a headless
    GL context with compute shaders can be made (``engine.fields.gl.available``: a GPU, or Mesa's llvmpipe),
    else ``torch``. InputError for ``gl`` without such a context and for any other name."""
    if name not in RENDERERS:
        raise InputError(f"must be one of {', '.join(RENDERERS)}, got {name!r}", field="renderer")
    if name == "torch":
        return name
    from engine.fields.gl import available

    if available():
        return "gl"
    if name == "gl":
        raise InputError("gl: no headless OpenGL 4.3 context with compute shaders (EGL); use --renderer torch",
                         field="renderer")
    return "torch"


def add_renderer_option(parser: argparse.ArgumentParser) -> None:
    """``--renderer``: who renders the held-out views a command scores (:func:`resolve_renderer`)."""
    parser.add_argument("--renderer", choices=list(RENDERERS), default="auto",
                        help="who renders the held-out views: gl (the real-time renderer, exact filtering), torch "
                             "(the training code, the oracle), auto (gl where a headless GL context exists)")


def gl_view_renderer(model, views):
    """The GL renderer (``models.fields.assets.gl_renderer``) of a torch field at the views' size, with
    ``filtering="exact"`` (float32 bilinear interpolation in the shader, as torch's ``grid_sample``; a GPU's
    texture unit would interpolate with 8-bit weights). Its frames differ from torch's by the real-time
    renderer's early ray termination and skipped colour evaluations (bounded in ``engine.fields.gl``)."""
    from models.fields.assets import gl_renderer

    return gl_renderer(model, views.width, views.height, filtering="exact")


# ----------------------------------------------------------------------------------------------------
# Run configs (FieldTrainConfig, DynamicTrainConfig): validation and the JSON form


@dataclass
class RunConfig:
    """The options every training run has (seed, steps, learning-rate schedule, resolution); the static and
    dynamic run configs (``FieldTrainConfig``, ``DynamicTrainConfig``) add theirs after these, so
    ``config.json`` lists these first. Saved as ``config.json`` through :meth:`to_dict`."""

    seed: int = field(default=0, metadata={"help": "seed of parameter initialisation and ray/sample choice"})
    steps: int = field(default=2000, metadata={"help": "optimisation steps"})
    rays_per_batch: int = field(default=1024, metadata={"help": "rays per step, drawn uniformly from all train pixels"})
    lr: float = field(default=0.02, metadata={"help": "peak Adam learning rate (planes and MLPs)"})
    lr_schedule: str = field(default="cosine", metadata={
        "help": "decay after warm-up: cosine, exponential or constant"})
    lr_final_factor: float = field(default=0.05, metadata={"help": "learning rate at the last step / peak"})
    warmup_steps: int = field(default=50, metadata={"help": "linear learning-rate warm-up steps"})
    downscale: int = field(default=0, metadata={
        "help": "image resolution factor relative to the dataset's full-size images (views are reduced to it if "
                "needed); 0: auto, the views' own resolution (the dataset's images; for an LLFF capture the "
                "coarsest images_N folder it ships)"})

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON data (tuples become lists), as written to ``config.json``."""
        return run_config_to_dict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "RunConfig":
        return run_config_from_dict(cls, data)


def validate_run_config(config, positive_ints: tuple[str, ...]) -> None:
    """The checks every run config shares: ``positive_ints`` (``steps`` and ``downscale`` may be 0), learning
    rate and its schedule, samples per ray, then the field's and the priors' own ``validate``; InputError naming the first
    bad option."""
    for name in positive_ints:
        check_range(getattr(config, name), name, low=0 if name in ("steps", "downscale") else 1, integer=True)
    check_range(config.lr, "lr", low=0, low_open=True)
    if config.lr_schedule not in LR_SCHEDULES:
        raise InputError(f"must be one of {LR_SCHEDULES}, got {config.lr_schedule!r}", field="lr_schedule")
    check_range(config.lr_final_factor, "lr_final_factor", low=0, high=1, low_open=True)
    check_range(config.render.num_samples, "render.num_samples", low=1, integer=True)
    config.field.validate()
    config.priors.validate()


def run_config_to_dict(config) -> dict[str, Any]:
    """Plain JSON data (tuples become lists), as written to ``config.json``."""
    return config_to_dict(config)


def run_config_from_dict(cls, data: dict[str, Any]):
    """A run config of type ``cls`` from its JSON form; unknown keys are errors (InputError naming them)."""
    unknown = sorted(set(data) - {f.name for f in dataclasses.fields(cls)})
    if unknown:
        raise InputError(f"unknown option(s) {unknown} for {cls.__name__}", field=cls.__name__)
    return config_from_dict(cls, data)


def run_config_from_file(cls, path: Optional[Path]):
    """``cls``'s defaults updated by a (partial) JSON config file (nested sections field by field)."""
    return cls() if path is None else config_from_file(cls, path)


def _config_section(args: argparse.Namespace, key: str):
    """The ``key`` section of the ``--config`` file (None without one, or without the section). The file was
    read and checked when the config was built (e.g. ``run_config_from_file``)."""
    return json.loads(Path(args.config).read_text()).get(key) if args.config else None


def losses_given(args: argparse.Namespace) -> list[str]:
    """Names of the loss terms whose weights a command line sets: those ``--loss`` names and those the
    ``--config`` file lists under ``losses`` (a run's saved ``config.json`` lists them all, so training again
    from it keeps its weights)."""
    terms = _config_section(args, "losses")
    return [spec.partition("=")[0] for spec in args.loss] + [
        t["name"] for t in (terms if isinstance(terms, list) else []) if isinstance(t, dict) and "name" in t]


def field_options_given(args: argparse.Namespace) -> list[str]:
    """Names of the field options (the ``field`` section's, e.g. ``FieldConfig``'s) that a command line sets:
    ``--field.NAME`` options and the keys of the ``--config`` file's ``field`` section."""
    section = _config_section(args, "field")
    return [key.partition(".")[2] for key in vars(args) if key.startswith("field.")] + (
        list(section) if isinstance(section, dict) else [])


def apply_loss_weights(config, specs: list[str]):
    """``config`` with the ``NAME=WEIGHT`` loss weights set (a weight of 0 switches the term off; a name not
    in ``config.losses`` adds that term)."""
    terms = {t.name: t for t in config.losses}
    for spec in specs:
        name, _, weight = spec.partition("=")
        try:
            w = float(weight)
        except ValueError:
            raise InputError(f"must be NAME=WEIGHT, got {spec!r}", field="--loss") from None
        base = terms.get(name, LossTerm(name))
        terms[name] = dataclasses.replace(base, weight=w, enabled=w > 0)
    return dataclasses.replace(config, losses=tuple(terms.values()))


def view_list(text: Optional[str], name: str) -> Optional[list]:
    """'5,10,14' or 'r_20,r_40' -> a list of positions (int) or names (str); None stays None."""
    if text is None:
        return None
    items = [t.strip() for t in str(text).split(",") if t.strip()]
    if not items:
        raise InputError("is empty", field=name)
    return [int(t) if t.lstrip("-").isdigit() else t for t in items]


# ----------------------------------------------------------------------------------------------------
# Rays and schedule


def all_rays(views, scene) -> RayBatch:
    """Every pixel ray of ``views`` (view-major, row-major pixels) with the scene's near / far bounds."""
    origins, directions = [], []
    for cam in views.cameras:
        o, d = camera_rays(cam.intrinsics, cam.world_to_camera, views.height, views.width)
        origins.append(o)
        directions.append(d)
    n = len(views) * views.height * views.width
    depth = None if views.depth is None else torch.from_numpy(views.depth.reshape(-1).astype(np.float32))
    view = torch.arange(len(views)).repeat_interleave(views.height * views.width)
    pixel = torch.arange(views.height * views.width).repeat(len(views))
    return RayBatch(origins=torch.cat(origins), directions=torch.cat(directions),
                    near=torch.full((n,), float(scene.near)), far=torch.full((n,), float(scene.far)),
                    color=torch.from_numpy(views.images.reshape(-1, 3).astype(np.float32)), depth=depth, view=view,
                    pixel=pixel)


def rays_to(rays: RayBatch, device: torch.device) -> RayBatch:
    """The rays on ``device``."""
    return RayBatch(**{f.name: (None if getattr(rays, f.name) is None else getattr(rays, f.name).to(device))
                       for f in dataclasses.fields(RayBatch)})


def take_rays(rays: RayBatch, idx: torch.Tensor) -> RayBatch:
    """The rays at ``idx``."""
    return RayBatch(**{f.name: (None if getattr(rays, f.name) is None else getattr(rays, f.name)[idx])
                       for f in dataclasses.fields(RayBatch)})


def lr_factor(config) -> Callable[[int], float]:
    """Learning rate / peak at a step: linear warm-up, then the config's decay to ``lr_final_factor``."""
    warm, total, final = config.warmup_steps, max(config.steps, 1), config.lr_final_factor

    def factor(step: int) -> float:
        if step < warm:
            return (step + 1) / warm
        progress = min(1.0, (step - warm) / max(1, total - warm))
        if config.lr_schedule == "cosine":
            return final + (1.0 - final) * 0.5 * (1.0 + math.cos(math.pi * progress))
        if config.lr_schedule == "exponential":
            return final ** progress
        return 1.0
    return factor


def matching_views(views, config):
    """``views`` reduced to ``config.downscale`` (InputError when their own downscale does not divide it);
    unchanged for ``downscale`` 0 (auto)."""
    if views.downscale == config.downscale or config.downscale == 0:
        return views
    if config.downscale % views.downscale:
        raise InputError(f"views are at downscale {views.downscale}, which does not divide the config's "
                         f"{config.downscale}", field="downscale")
    return views.downscaled(config.downscale // views.downscale)


# ----------------------------------------------------------------------------------------------------
# Run directory


def open_run_dir(out: Path, config) -> Path:
    """Create the run directory, refuse one holding a run with another config (``steps`` may differ: a
    larger one extends the run; fields a config lists in ``RECORDS`` only record how it was made), write
    ``config.json``; returns the checkpoint path (which may not exist).
    Options added since a run was made count as their defaults. ``config`` is any run config with
    ``to_dict`` / ``from_dict`` (static or dynamic)."""
    out.mkdir(parents=True, exist_ok=True)
    config_file, ckpt_file = out / "config.json", out / "checkpoint.pt"
    wanted = config.to_dict()
    if config_file.is_file() and ckpt_file.is_file():
        saved = type(config).from_dict(json.loads(config_file.read_text())).to_dict()
        ignored = {"steps", *getattr(type(config), "RECORDS", ())}
        differ = sorted(k for k in set(saved) | set(wanted) if k not in ignored and saved.get(k) != wanted.get(k))
        if differ:
            raise InputError(f"holds a run with a different config ({', '.join(differ)} differ); use a new "
                             "directory", file=config_file)
    config_file.write_text(json.dumps(wanted, indent=2) + "\n")
    return ckpt_file


def restore_training_state(state: dict, optimizer, scheduler, generator: torch.Generator, config) -> int:
    """Load the optimiser, schedule (stretched to ``config.steps``) and sampling generator of a checkpoint;
    returns its step."""
    optimizer.load_state_dict(state["optimizer"])
    scheduler.load_state_dict(state["scheduler"])
    scheduler.lr_lambdas = [lr_factor(config)] * len(optimizer.param_groups)
    generator.set_state(state["generator"])
    return int(state["step"])


def open_log(out: Path, step: int):
    """``log.jsonl`` opened for appending, without the lines written after the checkpoint at ``step``."""
    log_file = out / "log.jsonl"
    if log_file.is_file():
        kept = [line for line in log_file.read_text().splitlines() if json.loads(line)["step"] <= step]
        log_file.write_text("".join(line + "\n" for line in kept))
    return log_file.open("a")


# ----------------------------------------------------------------------------------------------------
# Training


class FieldKind(Protocol):
    """What a static and a dynamic field do differently in :func:`train_run` (the rest is shared)."""

    def prepare(self, views, config) -> tuple[Any, Any, tuple[LossTerm, ...]]:
        """``(views, config, loss terms)`` validated, the views at the config's downscale, the config with what
        the views fix resolved (:func:`check_run` does the shared part)."""

    def new_model(self, views, config) -> torch.nn.Module:
        """A fresh model, seeded by ``config.seed``."""

    def model_from_state(self, state: dict, config) -> torch.nn.Module:
        """The model a checkpoint was made from (its scene, whatever the views would give)."""

    def ray_inputs(self, views, model) -> Optional[torch.Tensor]:
        """Per-ray inputs besides the rays (a dynamic field's ray times), or None."""

    def build_priors(self, views, config, model, cache_dir: Path):
        """The run's priors (or None); a ``torch.nn.Module`` is trained and checkpointed with the model."""

    def param_groups(self, model) -> list[dict]:
        """The model's Adam parameter groups (named)."""

    def render_step(self, priors, model, batch: RayBatch, inputs: Optional[torch.Tensor], step: int,
                    generator: torch.Generator) -> tuple[Any, dict]:
        """What a training step renders: the model's outputs for the batch (jittered samples; ``inputs`` are
        the batch's ray inputs) and what the priors (None: none) put into ``LossInputs.extras``."""

    def checkpoint_fields(self, model) -> dict:
        """What the checkpoint holds besides model, scene and background."""

    def log_fields(self, outputs) -> dict:
        """What a ``log.jsonl`` line holds besides the loss terms, learning rate and occupancy."""


def train_run(kind: FieldKind, views, config, out_dir: str | Path, progress: bool = True, *,
              extras_fn=None, device: str = "auto") -> Path:
    """Train the field ``kind`` builds on ``views`` and write the run into ``out_dir``; returns ``out_dir``.

    Args:
        kind: the static or dynamic specifics (:class:`FieldKind`).
        views: training views (validated by ``kind``; reduced to ``config.downscale`` if loaded at a finer one).
        config: the run's settings (``FieldTrainConfig`` or ``DynamicTrainConfig``).
        out_dir: the run directory (created; an existing run there with the same config is resumed).
        progress: show a tqdm bar.
        extras_fn: optional ``(model, batch, outputs, step) -> dict`` feeding ``LossInputs.extras`` beside
            what the enabled priors put there.
        device: ``cpu``, ``cuda`` or ``auto`` (:func:`resolve_device`). Model, priors' modules and every
            train ray live there; every random draw comes from one CPU generator seeded by ``config.seed`` and
            is moved there, so a device changes only float rounding, never what is drawn.

    Raises:
        InputError: bad views, config or device, or ``out_dir`` holding a run with a different config.
    """
    device = resolve_device(device)
    views, config, terms = kind.prepare(views, config)
    out = Path(out_dir)
    ckpt_file = open_run_dir(out, config)
    state = torch.load(ckpt_file, map_location="cpu", weights_only=True) if ckpt_file.is_file() else None
    model = kind.new_model(views, config) if state is None else kind.model_from_state(state, config)
    rays = rays_to(all_rays(views, model.scene), device)
    inputs = kind.ray_inputs(views, model)
    inputs = None if inputs is None else inputs.to(device)
    priors = kind.build_priors(views, config, model, out / "priors")
    trained_priors = priors if isinstance(priors, torch.nn.Module) else None
    model.to(device)
    if trained_priors is not None:
        trained_priors.to(device)
    params = kind.param_groups(model)
    if trained_priors is not None and any(True for _ in trained_priors.parameters()):
        params.append({"params": list(trained_priors.parameters()), "name": "priors"})
    optimizer = torch.optim.Adam(params, lr=config.lr, betas=(0.9, 0.99), eps=1e-15)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lr_factor(config))
    generator = torch.Generator().manual_seed(config.seed)
    step = 0
    elapsed_before = 0.0  # training wall time of earlier sessions of this run (resumed runs)
    if state is not None:
        elapsed_before = float(state.get("train_seconds", 0.0))
        model.load_state_dict(state["model"])
        if trained_priors is not None:
            trained_priors.load_state_dict(state["priors"])
        step = restore_training_state(state, optimizer, scheduler, generator, config)

    def save(at: int) -> None:
        tmp = ckpt_file.with_suffix(".pt.tmp")
        torch.save({"step": at, "train_seconds": elapsed_before + time.perf_counter() - start,
                    "model": model.state_dict(), "scene": model.scene.to_dict(),
                    "background": model.background.tolist(), **kind.checkpoint_fields(model),
                    "optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(),
                    "generator": generator.get_state(),
                    **({"priors": trained_priors.state_dict()} if trained_priors is not None else {})}, tmp)
        tmp.replace(ckpt_file)

    bar = None
    if progress and step < config.steps:
        bar = tqdm(total=config.steps, initial=step, desc=f"training {out.name}", unit="step")
    log = open_log(out, step)
    n_rays = rays.color.shape[0]
    occupied = 1.0
    start = time.perf_counter()
    model.train()
    if trained_priors is not None:
        trained_priors.train()
    try:
        while step < config.steps:
            # callbacks (schedules live here, not in forward)
            if step >= config.occupancy_warmup and (step - config.occupancy_warmup) % config.occupancy_every == 0:
                occupied = model.update_occupancy(generator)
                if trained_priors is not None:
                    trained_priors.update_occupancy(generator)
            idx = torch.randint(n_rays, (config.rays_per_batch,), generator=generator).to(device)
            batch = take_rays(rays, idx)
            outputs, extras = kind.render_step(priors, model, batch, None if inputs is None else inputs[idx], step,
                                               generator)
            if extras_fn is not None:
                extras.update(extras_fn(model, batch, outputs, step) or {})
            loss, values = assemble_loss(terms, model, batch, outputs, step, extras)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            scheduler.step()
            step += 1
            if step % config.log_every == 0 or step == config.steps:
                log.write(json.dumps({"step": step, "loss": float(loss.detach()), **values,
                                      "lr": optimizer.param_groups[0]["lr"], "occupied": occupied,
                                      **kind.log_fields(outputs),
                                      "seconds": round(elapsed_before + time.perf_counter() - start, 2)}) + "\n")
                log.flush()
            if bar is not None:
                bar.update(1)
                if step % 10 == 0:
                    bar.set_postfix(loss=f"{float(loss.detach()):.4f}", occ=f"{occupied:.2f}")
            if step % config.checkpoint_every == 0 and step < config.steps:
                save(step)
    finally:
        log.close()
        if bar is not None:
            bar.close()
    save(step)
    return out


def check_run(views, config, check_views: Callable, depth_known: bool):
    """Validate views and config, check the loss terms against them; ``(views at the config's downscale,
    config with downscale 0 (auto) resolved to the views', loss terms)``."""
    check_views(views)
    config.validate()
    terms = config.loss_terms()
    check_loss_terms(terms, depth_known)
    views = matching_views(views, config)
    if config.downscale == 0:
        config = dataclasses.replace(config, downscale=int(views.downscale))
    return views, config, terms


# ----------------------------------------------------------------------------------------------------
# Evaluation


def rank_correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman rank correlation of two equally long 1D arrays (ties share their mean rank); NaN below 2
    values or when either array is constant."""
    if a.size < 2:
        return float("nan")

    def ranks(x: np.ndarray) -> np.ndarray:
        _, inverse, counts = np.unique(x, return_inverse=True, return_counts=True)
        ends = np.cumsum(counts)
        return ((ends - (counts - 1) / 2.0) - 1.0)[inverse]

    ra, rb = ranks(a), ranks(b)
    ra, rb = ra - ra.mean(), rb - rb.mean()
    denom = math.sqrt(float((ra * ra).sum()) * float((rb * rb).sum()))
    return float((ra * rb).sum() / denom) if denom > 0 else float("nan")


def run_train_seconds(run_dir: str | Path) -> float:
    """Training wall time of a run (all sessions of a resumed run), from its last ``log.jsonl`` line."""
    log = Path(run_dir) / "log.jsonl"
    lines = log.read_text().splitlines() if log.is_file() else []
    return float(json.loads(lines[-1]).get("seconds", float("nan"))) if lines else float("nan")


def score_views(model, views, render_view: Callable[[int, Any], dict], *, with_flip: bool = True,
                return_images: bool = False, regions: Optional[dict[str, np.ndarray]] = None
                ) -> tuple[dict[str, Any], list[float], list[dict]]:
    """Render every view with ``render_view(i, camera)`` (``render_image``'s dict) in eval mode and score it.

    PSNR, SSIM (``engine.eval.metrics.psnr`` / ``ssim_map``, Gaussian window) and FLIP (``flip_map``, LDR, 67
    pixels per degree) are computed on display-encoded images (``engine.core.colorspace.display_encode``) over
    the whole frame (the NeRF protocol: no border crop) and averaged over views. ``depth_mae`` is the mean
    |rendered - true| planar depth over pixels where both are finite and ``depth_spearman`` the rank
    correlation of the two over those pixels, all views pooled (NaN when the views carry no depth);
    ``depth_valid_fraction`` is the share of pixels with a finite true depth where the field also rendered
    a surface. ``render_ms_per_frame`` is the median wall time of rendering one view. ``regions`` (name ->
    (N, H, W) bool masks) adds ``psnr_<name>``: the mean over views of the PSNR over the region's pixels (views
    where it is empty skipped; NaN when it is empty everywhere).

    Returns:
        (scores, the PSNR of each view, the rendered colour and depth of each view if ``return_images``).
    """
    was_training = model.training
    model.eval()
    psnrs, ssims, flips, times_ms, abs_errors, pairs, valid, known, images = [], [], [], [], [], [], 0, 0, []
    regions = regions or {}
    region_psnrs: dict[str, list[float]] = {name: [] for name in regions}
    try:
        for i, cam in enumerate(views.cameras):
            out = render_view(i, cam)
            truth, pred = display_encode(views.images[i]), display_encode(out["color"])
            psnrs.append(psnr(truth, pred))
            for name, masks in regions.items():
                if masks[i].any():
                    region_psnrs[name].append(psnr(truth, pred, masks[i]))
            ssims.append(float(np.mean(ssim_map(truth, pred))))
            if with_flip:
                flips.append(float(np.mean(flip_map(truth, pred))))
            times_ms.append(float(out["seconds"]) * 1000.0)
            if return_images:
                images.append({"color": out["color"], "depth": out["depth"]})
            if views.depth is not None:
                true_depth = views.depth[i]
                mask = np.isfinite(true_depth)
                both = mask & np.isfinite(out["depth"])
                known += int(mask.sum())
                valid += int(both.sum())
                abs_errors.append(np.abs(out["depth"][both] - true_depth[both]))
                pairs.append((out["depth"][both], true_depth[both]))
    finally:
        model.train(was_training)
    errors = np.concatenate(abs_errors) if abs_errors else np.zeros(0)
    spearman = (rank_correlation(np.concatenate([p[0] for p in pairs]), np.concatenate([p[1] for p in pairs]))
                if pairs else float("nan"))
    scores: dict[str, Any] = {
        "psnr": float(np.mean(psnrs)), "ssim": float(np.mean(ssims)),
        "flip": float(np.mean(flips)) if flips else float("nan"),
        "depth_mae": float(errors.mean()) if errors.size else float("nan"),
        "depth_spearman": spearman,
        "depth_valid_fraction": valid / known if known else float("nan"),
        "render_ms_per_frame": float(np.median(times_ms)), "num_views": len(views),
        **{f"psnr_{name}": float(np.mean(v)) if v else float("nan") for name, v in region_psnrs.items()},
    }
    return scores, psnrs, images


# ----------------------------------------------------------------------------------------------------
# Command-line helpers


def json_safe(value):
    """NaN / inf -> None, recursively (JSON has neither)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value


def write_renders(folder: Path, views, images: list[dict]) -> None:
    """Each render beside its truth (display-encoded PNG, named after the view) into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    for i, img in enumerate(images):
        pair = np.concatenate([display_encode(img["color"]), display_encode(views.images[i])], axis=1)
        stem = Path(views.names[i]).stem if views.names else f"view{i}"
        cv2.imwrite(str(folder / f"{stem}.png"), (np.clip(pair, 0, 1) * 255 + 0.5).astype(np.uint8)[..., ::-1])


def run_eval_command(argv: Optional[list[str]], prog: str, description: str, made_by: str,
                     load_views: Callable, evaluate: Callable, header: Callable,
                     splits: Optional[tuple[str, ...]] = None) -> int:
    """``interleave eval field|dynamic RUN_DIR [--json OUT.json]``: render a run's held-out views and score them.

    ``load_views(run) -> (train, test)``, or with ``splits`` (the command then takes ``--split``)
    ``load_views(run, split) -> (train, test)`` (``split`` None: the run's own);
    ``evaluate(run, test, train, with_flip, return_images, renderer) -> scores``;
    ``header(run, train, test) -> dict`` (the keys printed before the scores)."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    parser.add_argument("run", type=Path, help=f"run directory written by '{made_by}'")
    parser.add_argument("--json", type=Path, default=None, help="also write the scores to this JSON file")
    parser.add_argument("--no-flip", action="store_true", help="skip FLIP")
    parser.add_argument("--images", type=Path, default=None,
                        help="write each held-out render (PNG, display-encoded) beside its truth into this folder")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    add_renderer_option(parser)
    if splits:
        parser.add_argument("--split", choices=list(splits), default=None,
                            help="score this split's views instead of the run's held-out ones")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        train, test = load_views(args.run, args.split) if splits else load_views(args.run)
        scores = evaluate(args.run, test, train, not args.no_flip, args.images is not None, args.renderer)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    images = scores.pop("images", None)
    if images is not None:
        write_renders(args.images, test, images)
    scores = json_safe({**header(args.run, train, test), **scores})
    text = json.dumps(scores, indent=2)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text + "\n")
    print(text)
    return 0
