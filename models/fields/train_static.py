"""Training and evaluation of static tri-plane fields from a few posed views, and a command line.

``train_field(views, config, out_dir)`` runs the shared training loop (``models/fields/trainer.py``: run
directory with ``config.json`` (the :class:`FieldTrainConfig`), ``checkpoint.pt`` and ``log.jsonl``; seeded
and resumable) with the static specifics, :data:`STATIC`.

Command line (the measurement in ``docs/fields.md``)::

    python -m models.fields.train_static --dataset nerf-synthetic --data /work/shared/data/nerf_synthetic_lego \\
        --views 8 --downscale 8 --steps 4000 --threads 1 --out runs/lego8
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Optional, Sequence

import torch

from engine.core.config import add_options, config_from_args
from engine.core.errors import InputError
from models.fields.components.render import render_image
from models.fields.data.select import DATASETS, detect_dataset, load_run_views, select_views
from models.fields.data.views import Views, check_views
from models.fields.losses import LossTerm, RayBatch, default_loss_terms
from models.fields.priors.config import (PRIOR_NAMES, PriorsConfig, auto_field_options, auto_loss_weights,
                                        auto_priors, build_priors, prior_loss_terms, with_priors)
from models.fields.static.field import FieldConfig
from models.fields.static.model import RenderConfig, SceneBox, StaticFieldModel
from models.fields.trainer import (RunConfig, add_renderer_option, apply_loss_weights, check_run,
                                   field_options_given, gl_view_renderer, json_safe, losses_given, rank_correlation,
                                   resolve_renderer, run_config_from_file, run_eval_command, run_train_seconds,
                                   score_views, train_run, validate_run_config, view_list)
from models.trainer_cli import DEVICES, resolve_device

__all__ = ["FieldTrainConfig", "STATIC", "train_field", "evaluate_field", "load_model", "build_model",
           "rank_correlation", "run_train_seconds", "load_run_views", "select_views", "detect_dataset",
           "config_from_file", "add_run_arguments", "add_config_options", "config_from_command_line",
           "views_from_args", "parse_run_command", "losses_given", "field_options_given", "choose_priors", "run_inputs",
           "main", "eval_main"]



@dataclass
class FieldTrainConfig(RunConfig):
    """Everything that defines a training run (saved as ``config.json`` beside its outputs): the shared
    :class:`~models.fields.trainer.RunConfig` options, then the static field's."""

    losses: tuple[LossTerm, ...] = field(default_factory=default_loss_terms, metadata={
        "help": "named loss terms with weights; see models/fields/losses.py"})
    occupancy_warmup: int = field(default=64, metadata={"help": "steps before the first occupancy-grid update"})
    occupancy_every: int = field(default=16, metadata={"help": "steps between occupancy-grid updates"})
    checkpoint_every: int = field(default=500, metadata={"help": "steps between checkpoints (and at the end)"})
    log_every: int = field(default=50, metadata={"help": "steps between log.jsonl lines"})
    priors: PriorsConfig = field(default_factory=PriorsConfig, metadata={
        "help": "sparse-input priors (sparse depth, Simple-RF, ViP); see models/fields/priors/config.py"})
    priors_choice: str = field(default="", metadata={
        "help": "why the enabled priors are on, as 'interleave train field' chose them ('auto: ...' from the "
                "number of train views, or 'explicit: ...'); a record, not an input"})
    render: RenderConfig = field(default_factory=RenderConfig, metadata={"help": "sampling and rendering"})
    # keep last: from here on the class body's name `field` is this attribute, not dataclasses.field
    field: FieldConfig = field(default_factory=FieldConfig, metadata={"help": "tri-plane field size"})

    #: Fields that record how the run was set up rather than define it (a resumed run may differ in them).
    RECORDS: ClassVar[tuple[str, ...]] = ("priors_choice",)

    def validate(self) -> "FieldTrainConfig":
        """Raise InputError naming the first bad option; returns self."""
        validate_run_config(self, ("steps", "rays_per_batch", "downscale", "occupancy_every", "checkpoint_every",
                                   "log_every"))
        return self

    def loss_terms(self) -> tuple[LossTerm, ...]:
        """``losses`` plus the terms of the enabled priors."""
        return tuple(self.losses) + prior_loss_terms(self.priors, self.steps)


# ----------------------------------------------------------------------------------------------------
# Model and training


def build_model(views: Views, config: FieldTrainConfig) -> StaticFieldModel:
    """A fresh model for ``views`` (seeded by ``config.seed``): scene from the views, field from the config."""
    torch.manual_seed(config.seed)
    return StaticFieldModel(SceneBox.from_views(views), views.background, config.field, config.render)


class StaticKind:
    """The static field's part of the shared training loop (``models.fields.trainer.FieldKind``): tri-plane
    model, the sparse-input priors (trained and checkpointed with it), planes and MLPs as parameter groups."""

    def prepare(self, views: Views, config: FieldTrainConfig):
        return check_run(views, config, check_views, views.depth is not None)

    def new_model(self, views: Views, config: FieldTrainConfig) -> StaticFieldModel:
        return build_model(views, config)

    def model_from_state(self, state: dict, config: FieldTrainConfig) -> StaticFieldModel:
        return StaticFieldModel(SceneBox.from_dict(state["scene"]), state["background"], config.field, config.render)

    def ray_inputs(self, views: Views, model: StaticFieldModel) -> None:
        return None

    def build_priors(self, views: Views, config: FieldTrainConfig, model: StaticFieldModel, cache_dir: Path):
        return build_priors(views, config, model, cache_dir)

    def param_groups(self, model: StaticFieldModel) -> list[dict]:
        return [{"params": list(model.field.encoding.parameters()), "name": "planes"},
                {"params": [p for n, p in model.field.named_parameters() if not n.startswith("encoding.")],
                 "name": "mlps"}]

    def render_step(self, priors, model: StaticFieldModel, batch: RayBatch, inputs: None, step: int,
                    generator: torch.Generator):
        outputs = model.render_rays(batch.origins, batch.directions, batch.near, batch.far, jitter=True,
                                    generator=generator)
        return outputs, (priors.extras(model, batch, outputs, step, generator) if priors is not None else {})

    def checkpoint_fields(self, model: StaticFieldModel) -> dict:
        return {}

    def log_fields(self, outputs) -> dict:
        return {}


#: The static specifics of the training loop.
STATIC = StaticKind()


def train_field(views: Views, config: FieldTrainConfig, out_dir: str | Path, progress: bool = True, *,
                extras_fn=None, device: str = "auto") -> Path:
    """Train a static field on ``views`` and write the run into ``out_dir``; returns ``out_dir``.

    Args:
        views: training views (validated here; reduced to ``config.downscale`` if loaded at a finer one).
        config: the run's settings.
        out_dir: the run directory (created; an existing run there with the same config is resumed).
        progress: show a tqdm bar.
        extras_fn: optional ``(model, batch, outputs, step) -> dict`` feeding ``LossInputs.extras`` beside
            what the enabled priors of ``config.priors`` put there (``models/fields/priors/config.py``).
        device: ``cpu``, ``cuda`` or ``auto`` (``cuda`` when torch sees a GPU); the same seed draws the same
            rays and samples on either (``models.fields.trainer.train_run``).

    Raises:
        InputError: bad views, config or device, or ``out_dir`` holding a run with a different config.
    """
    return train_run(STATIC, views, config, out_dir, progress, extras_fn=extras_fn, device=device)


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


def evaluate_field(run_or_model: str | Path | StaticFieldModel, views: Views, *, chunk: int = 8192,
                   with_flip: bool = True, return_images: bool = False, renderer: str = "torch") -> dict[str, Any]:
    """Render every view and score it against the truth: :func:`models.fields.trainer.score_views` (PSNR,
    SSIM, FLIP on display-encoded images over the whole frame, depth MAE and rank correlation, median render
    time per view) plus ``train_seconds``, the run's training wall time (NaN for a bare model), and
    ``renderer``. ``renderer`` (:func:`models.fields.trainer.resolve_renderer`): ``torch`` renders with the
    training code (the oracle), ``gl`` with the real-time GL renderer of the same field
    (:func:`models.fields.trainer.gl_view_renderer`), ``auto`` with gl where a GL context can be made.
    ``return_images`` adds ``images``: the rendered colour and depth per view.
    """
    check_views(views)
    kind = resolve_renderer(renderer)
    model = run_or_model if isinstance(run_or_model, StaticFieldModel) else load_model(run_or_model)
    gl = gl_view_renderer(model, views) if kind == "gl" else None

    def render_view(i: int, cam) -> dict:
        if gl is not None:
            return gl.render(cam.intrinsics, cam.world_to_camera)
        return render_image(model, cam.intrinsics, cam.world_to_camera, views.height, views.width,
                            model.scene.near, model.scene.far, chunk=chunk)

    try:
        scores, _, images = score_views(model, views, render_view, with_flip=with_flip, return_images=return_images)
    finally:
        if gl is not None:
            gl.release()
    scores["train_seconds"] = (run_train_seconds(run_or_model) if not isinstance(run_or_model, StaticFieldModel)
                               else float("nan"))
    scores["renderer"] = kind
    if return_images:
        scores["images"] = images
    return scores


# ----------------------------------------------------------------------------------------------------
# Command line


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
    parser.add_argument("--device", default="auto", metavar="|".join(DEVICES),
                        help="where to train: cpu, cuda, or auto (cuda when torch sees a GPU; default)")
    parser.add_argument("--config", type=Path, default=None, metavar="FILE",
                        help="JSON with any FieldTrainConfig fields (nested dicts for render/field/priors); "
                             "command-line options override it")


def add_config_options(parser: argparse.ArgumentParser) -> None:
    """One option per :class:`FieldTrainConfig` field (``engine.core.config``: ``--steps 400``,
    ``--field.resolutions 64,128``, ``--render.occupancy`` / ``--no-render.occupancy``)."""
    add_options(parser, FieldTrainConfig, skip=("priors_choice",))


def config_from_file(path: Optional[Path]) -> FieldTrainConfig:
    """Defaults updated by a (partial) JSON config file; nested sections merge field by field."""
    return run_config_from_file(FieldTrainConfig, path)


def config_from_command_line(args: argparse.Namespace) -> FieldTrainConfig:
    """The run config of a command line made with :func:`add_run_arguments` and :func:`add_config_options`:
    ``--config FILE``, then the config options given, then ``--loss NAME=WEIGHT`` (``--priors NAMES``: see
    :func:`choose_priors`)."""
    return apply_loss_weights(config_from_args(FieldTrainConfig, args, config_from_file(args.config)), args.loss)


def views_from_args(args: argparse.Namespace, downscale: int) -> tuple[Views, Views, dict[str, Any]]:
    """(train views, test views, data record) of a command line made with :func:`add_run_arguments`."""
    dataset = args.dataset or detect_dataset(args.data)
    return select_views(dataset, args.data, downscale, views=args.views,
                        train_views=view_list(getattr(args, "train_views", None), "train_views"),
                        test_views=view_list(getattr(args, "test_views", None), "test_views"),
                        max_test_views=args.max_test_views)


def parse_run_command(parser: argparse.ArgumentParser, argv: Optional[list[str]]) -> argparse.Namespace:
    """Add the :class:`FieldTrainConfig` options to a parser made with :func:`add_run_arguments`, parse
    ``argv`` and set the torch threads (``--threads``)."""
    add_config_options(parser)
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    return args


def choose_priors(config: FieldTrainConfig, num_views: int, scene_type: str, explicit: Optional[str] = None,
                  given_losses: Sequence[str] = (), given_field: Sequence[str] = ()) -> FieldTrainConfig:
    """``config`` with the priors of a command line and ``priors_choice`` saying why.

    ``explicit`` (the ``--priors`` text, ``''`` for none) wins: exactly those priors. Otherwise
    :func:`~models.fields.priors.config.auto_priors` picks priors from the number of train views and the scene type
    and switches them on beside those the config (file or ``--priors.NAME.enabled``) already switches on (a recipe
    such as ``configs/field-baked.json`` adds its own); the loss weights of the same rule
    (:func:`~models.fields.priors.config.auto_loss_weights`) are set, except for the terms in ``given_losses``
    (those the command line sets: :func:`losses_given`), and so are its field options
    (:func:`~models.fields.priors.config.auto_field_options`), except for those in ``given_field``
    (:func:`field_options_given`).
    """
    if explicit is not None:
        names = [n.strip() for n in explicit.split(",") if n.strip()]
        priors = with_priors(config.priors, names)
        return dataclasses.replace(config, priors=priors, priors_choice=f"explicit: --priors '{','.join(names)}'")
    names, reason = auto_priors(num_views, scene_type)
    configured = config.priors.enabled()
    weights = [f"{name}={weight!r}" for name, weight in auto_loss_weights(num_views, scene_type)
               if name not in given_losses]
    options = {name: value for name, value in auto_field_options(num_views, scene_type) if name not in given_field}
    choice = f"auto: {reason}" + (f"; the config enables {','.join(configured)}" if configured else "")
    return dataclasses.replace(apply_loss_weights(config, weights),
                               priors=with_priors(config.priors, [*configured, *names]),
                               field=dataclasses.replace(config.field, **options).validate(), priors_choice=choice)


def run_inputs(args: argparse.Namespace) -> tuple[FieldTrainConfig, Views, Views, dict[str, Any]]:
    """(config, train views, test views, data record) of a command line parsed by :func:`parse_run_command`."""
    config = config_from_command_line(args)
    train, test, record = views_from_args(args, config.downscale)
    return dataclasses.replace(config, downscale=record["downscale"]), train, test, record


def main(argv: Optional[list[str]] = None, prog: str = "python -m models.fields.train_static") -> int:
    """``interleave train field``: train on a scene, evaluate the held-out views, print the scores."""
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n")[0])
    add_run_arguments(parser, "run directory (default: runs/field/<scene>-<N>v)", out_required=False)
    parser.add_argument("--priors", dest="prior_names", default=None, metavar="NAMES",
                        help=f"comma-separated priors to switch on, from {','.join(PRIOR_NAMES)} ('' for none; "
                             "default: the ones that paid in the ablation for this few train views and this kind of "
                             "scene, e.g. depth with <= 3 forward-facing views; printed and saved as priors_choice)")
    parser.add_argument("--no-flip", action="store_true", help="skip FLIP in the final evaluation")
    add_renderer_option(parser)
    args = parse_run_command(parser, argv)
    try:
        device = resolve_device(args.device)
        config, train, test, record = run_inputs(args)
        config = choose_priors(config, len(train), train.scene_type, args.prior_names, losses_given(args),
                               field_options_given(args))
        print(f"priors: {', '.join(config.priors.enabled()) or 'none'} ({config.priors_choice})", file=sys.stderr)
        out = Path(args.out) if args.out else Path("runs/field") / f"{Path(args.data).resolve().name}-{len(train)}v"
        run = train_field(train, config, out, device=str(device))
        (out / "data.json").write_text(json.dumps(record, indent=2) + "\n")
        scores = evaluate_field(run, test, with_flip=not args.no_flip, renderer=args.renderer)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    scores = json_safe({"run": str(out), "train_views": record["train_names"], "test_views": record["test_names"],
                        "image_size": [train.height, train.width], "steps": config.steps, "device": device.type,
                        **scores})
    text = json.dumps(scores, indent=2)
    (out / "scores.json").write_text(text + "\n")
    print(text)
    return 0


def eval_main(argv: Optional[list[str]] = None, prog: str = "interleave eval field") -> int:
    """``interleave eval field RUN_DIR [--json OUT.json]``: render the run's held-out views and score them."""
    return run_eval_command(
        argv, prog, "Render a trained field's held-out views and print PSNR, SSIM, FLIP, depth MAE, train and "
                    "render time.", "interleave train field", load_run_views,
        lambda run, test, train, with_flip, images, renderer: evaluate_field(
            run, test, with_flip=with_flip, return_images=images, renderer=renderer),
        lambda run, train, test: {"run": str(run), "train_views": list(train.names), "test_views": list(test.names),
                                  "image_size": [test.height, test.width]})


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
