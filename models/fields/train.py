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

    python -m models.fields.train --dataset nerf-synthetic --data /work/shared/data/nerf_synthetic_lego \\
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

from engine.colorspace import display_encode
from engine.errors import InputError
from engine.metrics import psnr, ssim_map
from models.fields.data import Views, check_views, load_llff, load_nerf_synthetic, load_rig, split_indices
from models.fields.field import FieldConfig
from models.fields.losses import LossTerm, RayBatch, assemble_loss, check_loss_terms, default_loss_terms
from models.fields.model import RenderConfig, SceneBox, StaticFieldModel
from models.fields.priors import PRIOR_NAMES, PriorsConfig, build_priors, prior_loss_terms, with_priors
from models.fields.render import render_image
from models.fields.sampling import camera_rays

__all__ = ["FieldTrainConfig", "train_field", "evaluate_field", "load_model", "build_model", "main"]

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
        "help": "sparse-input priors (sparse depth, Simple-RF, ViP); see models/fields/priors.py"})
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


def train_field(views: Views, config: FieldTrainConfig, out_dir: str | Path, progress: bool = True, *,
                extras_fn=None) -> Path:
    """Train a static field on ``views`` and write the run into ``out_dir``; returns ``out_dir``.

    Args:
        views: training views (validated here; reduced to ``config.downscale`` if loaded at a finer one).
        config: the run's settings.
        out_dir: the run directory (created; an existing run there with the same config is resumed).
        progress: show a tqdm bar.
        extras_fn: optional ``(model, batch, outputs, step) -> dict`` feeding ``LossInputs.extras`` beside
            what the enabled priors of ``config.priors`` put there (``models/fields/priors.py``).

    Raises:
        InputError: bad views or config, or ``out_dir`` holding a run with a different config.
    """
    check_views(views)
    config.validate()
    terms = config.loss_terms()
    check_loss_terms(terms, views.depth is not None)
    views = _matching_views(views, config)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    config_file, ckpt_file = out / "config.json", out / "checkpoint.pt"
    wanted = config.to_dict()
    if config_file.is_file() and ckpt_file.is_file():
        # options added since the run was made count as their defaults
        saved = FieldTrainConfig.from_dict(json.loads(config_file.read_text())).to_dict()
        differ = sorted(k for k in set(saved) | set(wanted) if k != "steps" and saved.get(k) != wanted.get(k))
        if differ:
            raise InputError(f"holds a run with a different config ({', '.join(differ)} differ); use a new "
                             "directory", file=config_file)
    config_file.write_text(json.dumps(wanted, indent=2) + "\n")

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
    if state is not None:
        model.load_state_dict(state["model"])
        if priors is not None:
            priors.load_state_dict(state["priors"])
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        scheduler.lr_lambdas = [_lr_factor(config)] * len(optimizer.param_groups)
        generator.set_state(state["generator"])
        step = int(state["step"])

    def save(at: int) -> None:
        tmp = ckpt_file.with_suffix(".pt.tmp")
        torch.save({"step": at, "model": model.state_dict(), "scene": model.scene.to_dict(),
                    "background": model.background.tolist(), "optimizer": optimizer.state_dict(),
                    "scheduler": scheduler.state_dict(), "generator": generator.get_state(),
                    **({"priors": priors.state_dict()} if priors is not None else {})}, tmp)
        tmp.replace(ckpt_file)

    bar = None
    if progress and step < config.steps:
        from tqdm import tqdm
        bar = tqdm(total=config.steps, initial=step, desc=f"training {out.name}", unit="step")
    log_file = out / "log.jsonl"
    if log_file.is_file():  # drop lines written after the checkpoint we resume from
        kept = [line for line in log_file.read_text().splitlines() if json.loads(line)["step"] <= step]
        log_file.write_text("".join(line + "\n" for line in kept))
    log = log_file.open("a")
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
                                      "seconds": round(time.perf_counter() - start, 2)}) + "\n")
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


def evaluate_field(run_or_model: str | Path | StaticFieldModel, views: Views, *, chunk: int = 8192
                   ) -> dict[str, float]:
    """Render every view and score it against the truth.

    PSNR and SSIM (``engine.metrics.psnr`` / ``ssim_map``, Gaussian window) are computed on display-encoded
    images (``engine.colorspace.display_encode``) over the whole frame (the NeRF protocol: no border crop)
    and averaged over views. ``depth_mae`` is the mean |rendered - true| planar depth over pixels where both
    are finite (NaN when the views carry no depth); ``depth_valid_fraction`` is the share of pixels with a
    finite true depth where the field also rendered a surface. ``render_ms_per_frame`` is the mean wall time
    of rendering one view (rays, sampling, field, compositing; the first view includes warm-up).
    """
    check_views(views)
    model = run_or_model if isinstance(run_or_model, StaticFieldModel) else load_model(run_or_model)
    was_training = model.training
    model.eval()
    psnrs, ssims, times, abs_errors, valid, known = [], [], [], [], 0, 0
    try:
        for i, cam in enumerate(views.cameras):
            out = render_image(model, cam.intrinsics, cam.world_to_camera, views.height, views.width,
                               model.scene.near, model.scene.far, chunk=chunk)
            truth = display_encode(views.images[i])
            pred = display_encode(out["color"])
            psnrs.append(psnr(truth, pred))
            ssims.append(float(np.mean(ssim_map(truth, pred))))
            times.append(float(out["seconds"]) * 1000.0)
            if views.depth is not None:
                true_depth = views.depth[i]
                mask = np.isfinite(true_depth)
                both = mask & np.isfinite(out["depth"])
                known += int(mask.sum())
                valid += int(both.sum())
                abs_errors.append(np.abs(out["depth"][both] - true_depth[both]))
    finally:
        model.train(was_training)
    errors = np.concatenate(abs_errors) if abs_errors else np.zeros(0)
    return {"psnr": float(np.mean(psnrs)), "ssim": float(np.mean(ssims)),
            "depth_mae": float(errors.mean()) if errors.size else float("nan"),
            "depth_valid_fraction": valid / known if known else float("nan"),
            "render_ms_per_frame": float(np.mean(times)), "num_views": len(views)}


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


def _load_views(args) -> tuple[Views, Views]:
    """(train views, test views) for the command line."""
    if args.dataset == "nerf-synthetic":
        pool = load_nerf_synthetic(args.data, "train", downscale=args.downscale)
        train_idx, _ = split_indices(len(pool), views=args.views, test_every=0)
        test = load_nerf_synthetic(args.data, "test", downscale=args.downscale)
        if args.max_test_views:
            test = test.subset(range(min(args.max_test_views, len(test))))
        return pool.subset(train_idx), test
    if args.dataset == "llff":
        pool = load_llff(args.data, factor=args.downscale)
    else:
        pool = load_rig(args.data).downscaled(args.downscale)
    if args.dataset == "rig" and pool.default_split is not None and args.views is None:
        train_idx, test_idx = pool.default_split
    else:
        train_idx, test_idx = split_indices(len(pool), views=args.views)
    return pool.subset(train_idx), pool.subset(test_idx)


def add_run_arguments(parser: argparse.ArgumentParser, out_help: str) -> None:
    """The dataset, split, loss-weight and thread options shared by the training and ablation commands."""
    parser.add_argument("--dataset", choices=["nerf-synthetic", "llff", "rig"], required=True)
    parser.add_argument("--data", required=True, help="dataset folder (scene)")
    parser.add_argument("--out", required=True, help=out_help)
    parser.add_argument("--views", type=int, default=None, help="number of train views (spread uniformly)")
    parser.add_argument("--max-test-views", type=int, default=0, help="evaluate at most this many test views")
    parser.add_argument("--loss", action="append", default=[], metavar="NAME=WEIGHT",
                        help="set a loss term's weight (0 switches it off); repeatable")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")


def main(argv: Optional[list[str]] = None) -> int:
    """``python -m models.fields.train``: train on a dataset, evaluate held-out views, print the scores."""
    parser = argparse.ArgumentParser(prog="python -m models.fields.train", description=__doc__.split("\n")[0])
    add_run_arguments(parser, "run directory")
    parser.add_argument("--priors", dest="prior_names", default=None, metavar="NAMES",
                        help=f"comma-separated priors to switch on, from {','.join(PRIOR_NAMES)} ('' for none)")
    _add_config_args(parser, FieldTrainConfig)
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        config = _apply_losses(_apply_args(FieldTrainConfig(), args), args.loss)
        if args.prior_names is not None:
            names = [n.strip() for n in args.prior_names.split(",") if n.strip()]
            config = dataclasses.replace(config, priors=with_priors(config.priors, names))
        if args.downscale is None:
            args.downscale = config.downscale
        train, test = _load_views(args)
        start = time.perf_counter()
        run = train_field(train, config, args.out)
        train_seconds = time.perf_counter() - start
        scores = evaluate_field(run, test)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    scores = {"train_views": len(train), "test_views": len(test), "image_size": [train.height, train.width],
              "steps": config.steps, "train_seconds": round(train_seconds, 1), **scores}
    scores = {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in scores.items()}  # strict JSON
    text = json.dumps(scores, indent=2)
    (Path(args.out) / "scores.json").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
