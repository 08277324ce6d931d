"""Training and evaluation of static tri-plane fields from a few posed views, and a command line.

``train_field(views, config, out_dir)`` writes into the run directory ``out_dir``:

- ``config.json``: the :class:`FieldTrainConfig` that produced the run (nested configs included);
- ``checkpoint.pt``: model, scene, optimiser, schedule, the sampling generator's state and the step;
- ``log.jsonl``: one line per ``log_every`` steps (loss terms, learning rate, occupied fraction).

Runs are seeded (parameter initialisation and every random choice come from ``config.seed``) and resumable:
calling ``train_field`` again on the same directory continues from the last checkpoint; a different config
is refused, except for ``steps``. An interrupted run resumed with the same config ends bit-identical to an
uninterrupted one (CPU). A larger ``steps`` extends a finished run, with the learning-rate schedule
stretched to the new length from the current step on (so not identical to a run planned that long).

Command line (the measurement in ``docs/fields.md``)::

    python -m models.fields.train_static --dataset nerf-synthetic --data /work/shared/data/nerf_synthetic_lego \\
        --views 8 --downscale 8 --steps 4000 --threads 1 --out runs/lego8
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Union

import numpy as np
import torch

from engine.core.colorspace import display_encode
from engine.core.errors import InputError
from engine.eval.metrics import psnr, ssim_map
from models.fields.data.views import Views, check_views, load_llff, load_nerf_synthetic, load_rig, split_indices
from models.fields.static.field import FieldConfig
from models.fields.losses import LossTerm, RayBatch, assemble_loss, check_loss_terms, default_loss_terms
from models.fields.static.model import RenderConfig, SceneBox, StaticFieldModel
from models.fields.priors.config import PRIOR_NAMES, PriorsConfig, build_priors, prior_loss_terms, with_priors
from models.fields.components.render import render_image
from models.fields.components.sampling import camera_rays

__all__ = ["FieldTrainConfig", "train_field", "evaluate_field", "load_model", "build_model", "rank_correlation",
           "run_train_seconds", "load_run_views", "select_views", "detect_dataset", "config_from_file", "main",
           "eval_main"]

LR_SCHEDULES = ("cosine", "exponential", "constant")


@dataclass
class FieldTrainConfig:
    """Everything that defines a training run (saved as ``config.json`` beside its outputs)."""

    seed: int = field(default=0, metadata={"help": "seed of parameter initialisation and ray/sample choice"})
    steps: int = field(default=2000, metadata={"help": "optimisation steps"})
    rays_per_batch: int = field(default=1024, metadata={"help": "rays per step, drawn uniformly from all train pixels"})
    lr: float = field(default=0.02, metadata={"help": "peak Adam learning rate (planes and MLPs)"})
    lr_schedule: str = field(default="cosine", metadata={
        "help": "decay after warm-up: cosine, exponential or constant"})
    lr_final_factor: float = field(default=0.05, metadata={"help": "learning rate at the last step / peak"})
    warmup_steps: int = field(default=50, metadata={"help": "linear learning-rate warm-up steps"})
    downscale: int = field(default=1, metadata={
        "help": "image resolution factor relative to the dataset's images (views are reduced to it if needed)"})
    losses: tuple[LossTerm, ...] = field(default_factory=default_loss_terms, metadata={
        "help": "named loss terms with weights; see models/fields/losses.py"})
    occupancy_warmup: int = field(default=64, metadata={"help": "steps before the first occupancy-grid update"})
    occupancy_every: int = field(default=16, metadata={"help": "steps between occupancy-grid updates"})
    checkpoint_every: int = field(default=500, metadata={"help": "steps between checkpoints (and at the end)"})
    log_every: int = field(default=50, metadata={"help": "steps between log.jsonl lines"})
    priors: PriorsConfig = field(default_factory=PriorsConfig, metadata={
        "help": "sparse-input priors (sparse depth, Simple-RF, ViP); see models/fields/priors/config.py"})
    render: RenderConfig = field(default_factory=RenderConfig, metadata={"help": "sampling and rendering"})
    # keep last: from here on the class body's name `field` is this attribute, not dataclasses.field
    field: FieldConfig = field(default_factory=FieldConfig, metadata={"help": "tri-plane field size"})

    def validate(self) -> "FieldTrainConfig":
        """Raise InputError naming the first bad option; returns self."""
        for name in ("steps", "rays_per_batch", "downscale", "occupancy_every", "checkpoint_every", "log_every"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < (0 if name == "steps" else 1):
                raise InputError(f"must be a positive integer, got {value!r}", field=name)
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise InputError(f"must be a positive number, got {self.lr!r}", field="lr")
        if self.lr_schedule not in LR_SCHEDULES:
            raise InputError(f"must be one of {LR_SCHEDULES}, got {self.lr_schedule!r}", field="lr_schedule")
        if not 0 < self.lr_final_factor <= 1:
            raise InputError(f"must be in (0, 1], got {self.lr_final_factor}", field="lr_final_factor")
        if self.render.num_samples < 1:
            raise InputError(f"must be >= 1, got {self.render.num_samples}", field="render.num_samples")
        self.field.validate()
        self.priors.validate()
        return self

    def loss_terms(self) -> tuple[LossTerm, ...]:
        """``losses`` plus the terms of the enabled priors."""
        return tuple(self.losses) + prior_loss_terms(self.priors, self.steps)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON data (tuples become lists), as written to ``config.json``."""
        return json.loads(json.dumps(dataclasses.asdict(self)))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "FieldTrainConfig":
        return _from_dict(cls, data)


# ----------------------------------------------------------------------------------------------------
# Config (de)serialisation


def _from_dict(cls, data: dict[str, Any]):
    """Rebuild a (nested) config dataclass from ``dataclasses.asdict`` output; unknown keys are errors."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise InputError(f"unknown option(s) {unknown} for {cls.__name__}", field=cls.__name__)
    return cls(**{k: _convert(hints[k], v) for k, v in data.items()})


def _convert(hint, value):
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if dataclasses.is_dataclass(hint) and isinstance(value, dict):
        return _from_dict(hint, value)
    if origin is Union:
        if value is None:
            return None
        return _convert(next(a for a in args if a is not type(None)), value)
    if origin is tuple and isinstance(value, (list, tuple)):
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v) for v in value)
        return tuple(_convert(a, v) for a, v in zip(args, value))
    return value


# ----------------------------------------------------------------------------------------------------
# Model and rays


def build_model(views: Views, config: FieldTrainConfig) -> StaticFieldModel:
    """A fresh model for ``views`` (seeded by ``config.seed``): scene from the views, field from the config."""
    torch.manual_seed(config.seed)
    return StaticFieldModel(SceneBox.from_views(views), views.background, config.field, config.render)


def _all_rays(views: Views, scene: SceneBox) -> RayBatch:
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


def _take(rays: RayBatch, idx: torch.Tensor) -> RayBatch:
    return RayBatch(**{f.name: (None if getattr(rays, f.name) is None else getattr(rays, f.name)[idx])
                       for f in dataclasses.fields(RayBatch)})


def _lr_factor(config: FieldTrainConfig):
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


def _matching_views(views: Views, config: FieldTrainConfig) -> Views:
    if views.downscale == config.downscale:
        return views
    if config.downscale % views.downscale:
        raise InputError(f"views are at downscale {views.downscale}, which does not divide the config's "
                         f"{config.downscale}", field="downscale")
    return views.downscaled(config.downscale // views.downscale)


# ----------------------------------------------------------------------------------------------------
# Training


def open_run_dir(out: Path, config) -> Path:
    """Create the run directory, refuse one holding a run with another config (``steps`` may differ: a
    larger one extends the run), write ``config.json``; returns the checkpoint path (which may not exist).
    Options added since a run was made count as their defaults. ``config`` is any run config with
    ``to_dict`` / ``from_dict`` (static or dynamic)."""
    out.mkdir(parents=True, exist_ok=True)
    config_file, ckpt_file = out / "config.json", out / "checkpoint.pt"
    wanted = config.to_dict()
    if config_file.is_file() and ckpt_file.is_file():
        saved = type(config).from_dict(json.loads(config_file.read_text())).to_dict()
        differ = sorted(k for k in set(saved) | set(wanted) if k != "steps" and saved.get(k) != wanted.get(k))
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
    scheduler.lr_lambdas = [_lr_factor(config)] * len(optimizer.param_groups)
    generator.set_state(state["generator"])
    return int(state["step"])


def open_log(out: Path, step: int):
    """``log.jsonl`` opened for appending, without the lines written after the checkpoint at ``step``."""
    log_file = out / "log.jsonl"
    if log_file.is_file():
        kept = [line for line in log_file.read_text().splitlines() if json.loads(line)["step"] <= step]
        log_file.write_text("".join(line + "\n" for line in kept))
    return log_file.open("a")


def train_field(views: Views, config: FieldTrainConfig, out_dir: str | Path, progress: bool = True, *,
                extras_fn=None) -> Path:
    """Train a static field on ``views`` and write the run into ``out_dir``; returns ``out_dir``.

    Args:
        views: training views (validated here; reduced to ``config.downscale`` if loaded at a finer one).
        config: the run's settings.
        out_dir: the run directory (created; an existing run there with the same config is resumed).
        progress: show a tqdm bar.
        extras_fn: optional ``(model, batch, outputs, step) -> dict`` feeding ``LossInputs.extras`` beside
            what the enabled priors of ``config.priors`` put there (``models/fields/priors/config.py``).

    Raises:
        InputError: bad views or config, or ``out_dir`` holding a run with a different config.
    """
    check_views(views)
    config.validate()
    terms = config.loss_terms()
    check_loss_terms(terms, views.depth is not None)
    views = _matching_views(views, config)
    out = Path(out_dir)
    ckpt_file = open_run_dir(out, config)
    state = torch.load(ckpt_file, map_location="cpu", weights_only=True) if ckpt_file.is_file() else None
    if state is None:
        model = build_model(views, config)
    else:  # the scene the run started with, whatever these views would give
        model = StaticFieldModel(SceneBox.from_dict(state["scene"]), state["background"], config.field, config.render)
    rays = _all_rays(views, model.scene)
    priors = build_priors(views, config, model, out / "priors")
    params = [{"params": list(model.field.encoding.parameters()), "name": "planes"},
              {"params": [p for n, p in model.field.named_parameters() if not n.startswith("encoding.")],
               "name": "mlps"}]
    if priors is not None and any(True for _ in priors.parameters()):
        params.append({"params": list(priors.parameters()), "name": "priors"})
    optimizer = torch.optim.Adam(params, lr=config.lr, betas=(0.9, 0.99), eps=1e-15)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, _lr_factor(config))
    generator = torch.Generator().manual_seed(config.seed)
    step = 0
    elapsed_before = 0.0  # training wall time of earlier sessions of this run (resumed runs)
    if state is not None:
        elapsed_before = float(state.get("train_seconds", 0.0))
        model.load_state_dict(state["model"])
        if priors is not None:
            priors.load_state_dict(state["priors"])
        step = restore_training_state(state, optimizer, scheduler, generator, config)

    def save(at: int) -> None:
        tmp = ckpt_file.with_suffix(".pt.tmp")
        torch.save({"step": at, "train_seconds": elapsed_before + time.perf_counter() - start,
                    "model": model.state_dict(), "scene": model.scene.to_dict(),
                    "background": model.background.tolist(), "optimizer": optimizer.state_dict(),
                    "scheduler": scheduler.state_dict(), "generator": generator.get_state(),
                    **({"priors": priors.state_dict()} if priors is not None else {})}, tmp)
        tmp.replace(ckpt_file)

    bar = None
    if progress and step < config.steps:
        from tqdm import tqdm
        bar = tqdm(total=config.steps, initial=step, desc=f"training {out.name}", unit="step")
    log = open_log(out, step)
    n_rays = rays.color.shape[0]
    occupied = 1.0
    start = time.perf_counter()
    model.train()
    if priors is not None:
        priors.train()
    try:
        while step < config.steps:
            # callbacks (schedules live here, not in forward)
            if step >= config.occupancy_warmup and (step - config.occupancy_warmup) % config.occupancy_every == 0:
                occupied = model.update_occupancy(generator)
                if priors is not None:
                    priors.update_occupancy(generator)
            idx = torch.randint(n_rays, (config.rays_per_batch,), generator=generator)
            batch = _take(rays, idx)
            outputs = model.render_rays(batch.origins, batch.directions, batch.near, batch.far, jitter=True,
                                        generator=generator)
            extras = priors.extras(model, batch, outputs, step, generator) if priors is not None else {}
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


def load_model(run_dir: str | Path) -> StaticFieldModel:
    """The trained model of a run directory (``config.json`` + ``checkpoint.pt``), in eval mode."""
    run = Path(run_dir)
    for name in ("config.json", "checkpoint.pt"):
        if not (run / name).is_file():
            raise InputError("file does not exist (not a run directory?)", file=run / name)
    config = FieldTrainConfig.from_dict(json.loads((run / "config.json").read_text()))
    state = torch.load(run / "checkpoint.pt", map_location="cpu", weights_only=True)
    model = StaticFieldModel(SceneBox.from_dict(state["scene"]), state["background"], config.field, config.render)
    model.load_state_dict(state["model"])
    return model.eval()


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


def evaluate_field(run_or_model: str | Path | StaticFieldModel, views: Views, *, chunk: int = 8192,
                   with_flip: bool = True, return_images: bool = False) -> dict[str, Any]:
    """Render every view and score it against the truth.

    PSNR, SSIM (``engine.eval.metrics.psnr`` / ``ssim_map``, Gaussian window) and FLIP (``flip_map``, LDR, 67
    pixels per degree) are computed on display-encoded images (``engine.core.colorspace.display_encode``) over
    the whole frame (the NeRF protocol: no border crop) and averaged over views. ``depth_mae`` is the mean
    |rendered - true| planar depth over pixels where both are finite and ``depth_spearman`` the rank
    correlation of the two over those pixels, all views pooled (NaN when the views carry no depth);
    ``depth_valid_fraction`` is the share of pixels with a finite true depth where the field also rendered
    a surface. ``render_ms_per_frame`` is the median wall time of rendering one view (rays, sampling,
    field, compositing). ``train_seconds`` is the run's training wall time (NaN for a bare model).
    ``return_images`` adds ``images``: the rendered colour and depth per view.
    """
    from engine.eval.metrics import flip_map

    check_views(views)
    model = run_or_model if isinstance(run_or_model, StaticFieldModel) else load_model(run_or_model)
    was_training = model.training
    model.eval()
    psnrs, ssims, flips, times, abs_errors, pairs, valid, known, images = [], [], [], [], [], [], 0, 0, []
    try:
        for i, cam in enumerate(views.cameras):
            out = render_image(model, cam.intrinsics, cam.world_to_camera, views.height, views.width,
                               model.scene.near, model.scene.far, chunk=chunk)
            truth = display_encode(views.images[i])
            pred = display_encode(out["color"])
            psnrs.append(psnr(truth, pred))
            ssims.append(float(np.mean(ssim_map(truth, pred))))
            if with_flip:
                flips.append(float(np.mean(flip_map(truth, pred))))
            times.append(float(out["seconds"]) * 1000.0)
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
        "render_ms_per_frame": float(np.median(times)), "num_views": len(views),
        "train_seconds": (run_train_seconds(run_or_model) if not isinstance(run_or_model, StaticFieldModel)
                          else float("nan")),
    }
    if return_images:
        scores["images"] = images
    return scores


# ----------------------------------------------------------------------------------------------------
# Command line


def _add_config_args(parser: argparse.ArgumentParser, cls, prefix: str = "") -> None:
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        hint, name = hints[f.name], prefix + f.name
        help_text = f.metadata.get("help", "")
        if dataclasses.is_dataclass(hint):
            _add_config_args(parser, hint, prefix=f"{name}.")
            continue
        if f.name == "losses":
            continue
        flag = "--" + name.replace("_", "-")
        origin, args = typing.get_origin(hint), typing.get_args(hint)
        if origin is tuple:
            parser.add_argument(flag, dest=name, nargs="+", type=args[0], default=None, help=help_text)
        elif hint is bool or (origin is Union and bool in args):
            parser.add_argument(flag, dest=name, choices=["true", "false"], default=None, help=help_text)
        else:
            parser.add_argument(flag, dest=name, type=hint, default=None, help=help_text)


def _apply_args(config, args: argparse.Namespace, prefix: str = ""):
    hints = typing.get_type_hints(type(config))
    changes = {}
    for f in dataclasses.fields(config):
        name = prefix + f.name
        if dataclasses.is_dataclass(hints[f.name]):
            changes[f.name] = _apply_args(getattr(config, f.name), args, prefix=f"{name}.")
            continue
        value = getattr(args, name, None)
        if value is None:
            continue
        if isinstance(value, str) and value in ("true", "false"):
            value = value == "true"
        elif isinstance(value, list):
            value = tuple(value)
        changes[f.name] = value
    return dataclasses.replace(config, **changes)


def _apply_losses(config: FieldTrainConfig, specs: list[str]) -> FieldTrainConfig:
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


DATASETS = ("nerf-synthetic", "llff", "rig")


def detect_dataset(path: str | Path) -> str:
    """The layout of a scene folder: ``nerf-synthetic`` (transforms_train.json), ``llff``
    (poses_bounds.npy) or ``rig`` (rig.json)."""
    root = Path(path)
    for marker, kind in (("transforms_train.json", "nerf-synthetic"), ("poses_bounds.npy", "llff"),
                         ("rig.json", "rig")):
        if (root / marker).is_file():
            return kind
    if not root.exists():
        raise InputError("folder does not exist", file=root)
    raise InputError("is not a scene folder: expected transforms_train.json (NeRF-synthetic), poses_bounds.npy "
                     "(LLFF) or rig.json (rgbd-rig)", file=root)


def _view_list(text: Optional[str], name: str) -> Optional[list]:
    """'5,10,14' or 'r_20,r_40' -> a list of positions (int) or view names (str); None stays None."""
    if text is None:
        return None
    items = [t.strip() for t in str(text).split(",") if t.strip()]
    if not items:
        raise InputError("is empty", field=name)
    return [int(t) if t.lstrip("-").isdigit() else t for t in items]


def _positions(pool: Views, spec: list, name: str) -> list[int]:
    """View positions in ``pool`` for a list of positions and/or names (a name matches a view's name or
    its file stem)."""
    stems = [Path(n).stem if n else "" for n in pool.names]
    out = []
    for item in spec:
        if isinstance(item, int):
            if not 0 <= item < len(pool):
                raise InputError(f"position {item} out of range: {len(pool)} views were loaded", field=name)
            out.append(item)
        elif item in pool.names or item in stems:
            out.append(pool.names.index(item) if item in pool.names else stems.index(item))
        else:
            raise InputError(f"no view named {item!r} (views: {', '.join(stems[:8])}{'...' if len(stems) > 8 else ''})",
                             field=name)
    if len(set(out)) != len(out):
        raise InputError(f"names a view twice: {spec}", field=name)
    return out


def select_views(dataset: str, scene: str | Path, downscale: int, *, views: Optional[int] = None,
                 train_views: Optional[list] = None, test_views: Optional[list] = None,
                 max_test_views: int = 0) -> tuple[Views, Views, dict[str, Any]]:
    """Load a scene and split it into (train, test) views; the third item records the choice (``data.json``).

    NeRF-synthetic: train views come from the train split, test views from the test split (all present
    frames unless ``test_views``). LLFF and rigs: one pool; the default split is ``split_indices`` (every
    8th frame held out, train views spread over the rest), or the rig's own train/test cameras when
    ``views`` is not given. ``train_views`` / ``test_views`` are positions among the *loaded* frames
    (listed frames whose files are missing are skipped) or view names (``r_20``, ``cam3``).
    """
    if dataset not in DATASETS:
        raise InputError(f"must be one of {DATASETS}, got {dataset!r}", field="dataset")
    if dataset == "nerf-synthetic":
        pool = load_nerf_synthetic(scene, "train", downscale=downscale)
        test_pool = load_nerf_synthetic(scene, "test", downscale=downscale)
        train_idx = (_positions(pool, train_views, "train_views") if train_views is not None
                     else split_indices(len(pool), views=views, test_every=0)[0])
        test_idx = (_positions(test_pool, test_views, "test_views") if test_views is not None
                    else list(range(len(test_pool))))
    else:
        pool = load_llff(scene, factor=downscale) if dataset == "llff" else load_rig(scene).downscaled(downscale)
        test_pool = pool
        tr = _positions(pool, train_views, "train_views") if train_views is not None else None
        te = _positions(pool, test_views, "test_views") if test_views is not None else None
        if dataset == "rig" and pool.default_split is not None and views is None and tr is None and te is None:
            train_idx, test_idx = (list(x) for x in pool.default_split)
        else:
            if tr is not None and te is None:
                te = split_indices(len(pool))[1]
                te = [i for i in te if i not in tr]
            train_idx, test_idx = split_indices(len(pool), views=None if tr is not None else views,
                                                train_views=tr, test_views=te)
    if max_test_views:
        test_idx = test_idx[:max_test_views]
    if not train_idx:
        raise InputError("no train views selected", field="train_views")
    if not test_idx:
        raise InputError("no test views selected", field="test_views")
    train, test = pool.subset(train_idx), test_pool.subset(test_idx)
    record = {"dataset": dataset, "scene": str(Path(scene).resolve()), "downscale": int(downscale),
              "train_views": [int(i) for i in train_idx], "test_views": [int(i) for i in test_idx],
              "train_names": list(train.names), "test_names": list(test.names)}
    return train, test, record


def load_run_views(run_dir: str | Path) -> tuple[Views, Views]:
    """The (train, test) views a run was trained and is evaluated on, from its ``data.json``."""
    file = Path(run_dir) / "data.json"
    if not file.is_file():
        raise InputError("file does not exist: the run was not made by 'interleave train field' (or the "
                         "folder is not a run directory)", file=file)
    rec = json.loads(file.read_text())
    train, test, _ = select_views(rec["dataset"], rec["scene"], rec["downscale"], train_views=rec["train_views"],
                                  test_views=rec["test_views"])
    return train, test


def _load_views(args) -> tuple[Views, Views, dict[str, Any]]:
    """(train views, test views, data record) for the command line."""
    dataset = args.dataset or detect_dataset(args.data)
    return select_views(dataset, args.data, args.downscale, views=args.views,
                        train_views=_view_list(getattr(args, "train_views", None), "train_views"),
                        test_views=_view_list(getattr(args, "test_views", None), "test_views"),
                        max_test_views=args.max_test_views)


def add_run_arguments(parser: argparse.ArgumentParser, out_help: str, *, out_required: bool = True) -> None:
    """The dataset, split, loss-weight and thread options shared by the training and ablation commands."""
    parser.add_argument("--scene", "--data", dest="data", required=True,
                        help="scene folder: NeRF-synthetic, LLFF or rgbd-rig (its layout is detected)")
    parser.add_argument("--dataset", choices=list(DATASETS), default=None,
                        help="the scene folder's layout (default: detected from its files)")
    parser.add_argument("--out", required=out_required, default=None, help=out_help)
    parser.add_argument("--views", type=int, default=None, help="number of train views (spread uniformly)")
    parser.add_argument("--train-views", default=None, metavar="LIST",
                        help="explicit train views: comma-separated positions among the loaded frames or names "
                             "(e.g. 5,10,14 or r_20,r_40)")
    parser.add_argument("--test-views", default=None, metavar="LIST", help="explicit test views, as --train-views")
    parser.add_argument("--max-test-views", type=int, default=0, help="evaluate at most this many test views")
    parser.add_argument("--loss", action="append", default=[], metavar="NAME=WEIGHT",
                        help="set a loss term's weight (0 switches it off); repeatable")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    parser.add_argument("--config", type=Path, default=None, metavar="FILE",
                        help="JSON with any FieldTrainConfig fields (nested dicts for render/field/priors); "
                             "command-line options override it")


def config_from_file(path: Optional[Path]) -> FieldTrainConfig:
    """Defaults updated by a (partial) JSON config file; nested sections merge field by field."""
    if path is None:
        return FieldTrainConfig()
    if not Path(path).is_file():
        raise InputError("config file does not exist", file=path)
    try:
        data = json.loads(Path(path).read_text())
    except json.JSONDecodeError as exc:
        raise InputError(f"is not valid JSON: {exc}", file=path) from None

    def merge(base: dict, over: dict) -> dict:
        out = dict(base)
        for k, v in over.items():
            out[k] = merge(base[k], v) if isinstance(v, dict) and isinstance(base.get(k), dict) else v
        return out

    return FieldTrainConfig.from_dict(merge(FieldTrainConfig().to_dict(), data))


def _json_ready(scores: dict) -> dict:
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in scores.items()}


def main(argv: Optional[list[str]] = None, prog: str = "python -m models.fields.train_static") -> int:
    """``interleave train field``: train on a scene, evaluate the held-out views, print the scores."""
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n")[0])
    add_run_arguments(parser, "run directory (default: runs/field/<scene>-<N>v)", out_required=False)
    parser.add_argument("--priors", dest="prior_names", default=None, metavar="NAMES",
                        help=f"comma-separated priors to switch on, from {','.join(PRIOR_NAMES)} ('' for none)")
    parser.add_argument("--no-flip", action="store_true", help="skip FLIP in the final evaluation")
    _add_config_args(parser, FieldTrainConfig)
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        config = _apply_losses(_apply_args(config_from_file(args.config), args), args.loss)
        if args.prior_names is not None:
            names = [n.strip() for n in args.prior_names.split(",") if n.strip()]
            config = dataclasses.replace(config, priors=with_priors(config.priors, names))
        if args.downscale is None:
            args.downscale = config.downscale
        train, test, record = _load_views(args)
        out = Path(args.out) if args.out else Path("runs/field") / f"{Path(args.data).resolve().name}-{len(train)}v"
        run = train_field(train, config, out)
        (out / "data.json").write_text(json.dumps(record, indent=2) + "\n")
        scores = evaluate_field(run, test, with_flip=not args.no_flip)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    scores = _json_ready({"run": str(out), "train_views": record["train_names"], "test_views": record["test_names"],
                          "image_size": [train.height, train.width], "steps": config.steps, **scores})
    text = json.dumps(scores, indent=2)
    (out / "scores.json").write_text(text + "\n")
    print(text)
    return 0


def eval_main(argv: Optional[list[str]] = None, prog: str = "interleave eval field") -> int:
    """``interleave eval field RUN_DIR [--json OUT.json]``: render the run's held-out views and score them."""
    parser = argparse.ArgumentParser(prog=prog, description="Render a trained field's held-out views and print "
                                                            "PSNR, SSIM, FLIP, depth MAE, train and render time.")
    parser.add_argument("run", type=Path, help="run directory written by 'interleave train field'")
    parser.add_argument("--json", type=Path, default=None, help="also write the scores to this JSON file")
    parser.add_argument("--no-flip", action="store_true", help="skip FLIP")
    parser.add_argument("--images", type=Path, default=None,
                        help="write each held-out render (PNG, display-encoded) and its truth into this folder")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        train, test = load_run_views(args.run)
        scores = evaluate_field(args.run, test, with_flip=not args.no_flip, return_images=args.images is not None)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    images = scores.pop("images", None)
    if images is not None:
        _write_renders(args.images, test, images)
    scores = _json_ready({"run": str(args.run), "train_views": list(train.names), "test_views": list(test.names),
                          "image_size": [test.height, test.width], **scores})
    text = json.dumps(scores, indent=2)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text + "\n")
    print(text)
    return 0


def _write_renders(folder: Path, views: Views, images: list[dict]) -> None:
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    for i, img in enumerate(images):
        pair = np.concatenate([display_encode(img["color"]), display_encode(views.images[i])], axis=1)
        stem = Path(views.names[i]).stem if views.names else f"view{i}"
        cv2.imwrite(str(folder / f"{stem}.png"), (np.clip(pair, 0, 1) * 255 + 0.5).astype(np.uint8)[..., ::-1])


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
