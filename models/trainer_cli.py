"""Command-line pieces every trainer shares: a ``--config FILE`` the options override, ``--resume``, ``--no-progress``,
``--device``'s values.

The options themselves are the training config's fields (``engine.core.config.add_options``: nested
configs as ``--model.name``); the config a run used is saved beside it as JSON and reads back with
``--config``.
"""
from __future__ import annotations

import argparse
from typing import Callable, Optional, Sequence

import torch

from engine.core import config as core_config
from engine.core.errors import InputError

__all__ = ["DEVICES", "resolve_device", "add_trainer_options", "trainer_config", "trainer_parser", "trainer_main"]


#: What ``--device`` takes: ``auto`` is ``cuda`` when torch sees a GPU, else ``cpu``.
DEVICES = ("auto", "cpu", "cuda")


def resolve_device(name: str) -> torch.device:
    """The torch device of a ``--device`` value (:data:`DEVICES`); InputError for ``cuda`` where torch sees
    no GPU (a CPU-only build, or no GPU visible) and for any other name."""
    if name not in DEVICES:
        raise InputError(f"must be one of {', '.join(DEVICES)}, got {name!r}", field="device")
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        build = "a CPU-only build" if torch.version.cuda is None else f"built for CUDA {torch.version.cuda}"
        raise InputError(f"cuda: torch {torch.__version__} ({build}) sees no GPU; use --device cpu or auto",
                         field="device")
    return torch.device(name)


def add_trainer_options(parser: argparse.ArgumentParser, cls: type) -> None:
    """``--config FILE``, one ``--option`` per field of the training config ``cls``, ``--resume``, ``--no-progress``."""
    parser.add_argument("--config", metavar="FILE", help=f"JSON {cls.__name__} as a run writes it; command-line "
                                                         "options override its values")
    core_config.add_options(parser, cls)
    parser.add_argument("--resume", action="store_true", help="continue from out_dir/checkpoint.pt")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def trainer_config(cls: type, args: argparse.Namespace):
    """The run's ``cls``: ``args.config``'s file (if any; else the defaults) with the options given on the
    command line set."""
    base = core_config.config_from_file(cls, args.config) if args.config else None
    return core_config.config_from_args(cls, args, base)


def trainer_parser(cls: type, prog: str, description: str) -> argparse.ArgumentParser:
    """The command line of a trainer whose run is configured by ``cls`` (see :func:`add_trainer_options`)."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    add_trainer_options(parser, cls)
    return parser


def trainer_main(argv: Optional[Sequence[str]], prog: str, description: str, cls: type, train: Callable) -> None:
    """Parse ``argv`` and run ``train(config, progress=..., resume=...)`` with the run's ``cls``."""
    args = trainer_parser(cls, prog, description).parse_args(None if argv is None else list(argv))
    train(trainer_config(cls, args), progress=not args.no_progress, resume=args.resume)
