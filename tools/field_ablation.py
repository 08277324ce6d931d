"""Ablation of the sparse-input priors: the same run with {plain, +depth, +simple, +vip, all}.

Each variant trains in ``OUT/<variant>`` (resumable, as any run) with the same seed, views and settings, is
scored on the held-out views with :func:`~models.fields.train_static.evaluate_field`, and the command prints a
markdown table and writes ``OUT/ablation.json``::

    python -m tools.field_ablation --dataset nerf-synthetic --data /work/shared/data/nerf_synthetic_lego \\
        --views 4 --downscale 8 --steps 300 --threads 1 --out runs/ablation
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path
from typing import Optional

from engine.core.errors import InputError
from models.fields.priors.config import PRIOR_NAMES, with_priors
from models.fields.train_static import (FieldTrainConfig, add_run_arguments, evaluate_field, parse_run_command,
                                        run_inputs, train_field)

__all__ = ["VARIANTS", "run_ablation", "markdown_table", "main"]

#: variant name -> priors switched on.
VARIANTS: dict[str, tuple[str, ...]] = {"plain": (), "+depth": ("depth",), "+simple": ("simple",),
                                        "+vip": ("vip",), "all": PRIOR_NAMES}


def run_ablation(train, test, config: FieldTrainConfig, out_dir: str | Path, variants=tuple(VARIANTS),
                 progress: bool = True, data_record: Optional[dict] = None, with_flip: bool = True) -> list[dict]:
    """Train and score every variant; returns one row per variant (scores, train seconds, priors).

    ``train_seconds`` is the run's training wall time from its log (so a finished run that is only
    re-evaluated keeps the time it took to train); ``data_record`` (from ``select_views``) is written as each
    run's ``data.json`` so ``interleave eval field`` and ``export field`` work on the variants."""
    rows = []
    for name in variants:
        run_config = dataclasses.replace(config, priors=with_priors(config.priors, VARIANTS[name]))
        run = train_field(train, run_config, Path(out_dir) / name.lstrip("+"), progress=progress)
        if data_record is not None:
            (run / "data.json").write_text(json.dumps(data_record, indent=2) + "\n")
        scores = evaluate_field(run, test, with_flip=with_flip)
        scores["train_seconds"] = round(scores["train_seconds"], 1)
        rows.append({"variant": name, "priors": list(VARIANTS[name]), **scores})
    return rows


def _cell(value, fmt: str) -> str:
    return "n/a" if value is None or (isinstance(value, float) and math.isnan(value)) else format(value, fmt)


def markdown_table(rows: list[dict]) -> str:
    """The rows as a markdown table: PSNR, SSIM, FLIP, depth MAE and rank correlation, train seconds, render
    ms per frame."""
    lines = ["| variant | PSNR (dB) | SSIM | FLIP | depth MAE | depth rank corr. | train s | render ms/frame |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        lines.append(f"| {r['variant']} | {_cell(r['psnr'], '.2f')} | {_cell(r['ssim'], '.3f')} | "
                     f"{_cell(r.get('flip'), '.3f')} | {_cell(r['depth_mae'], '.3f')} | "
                     f"{_cell(r.get('depth_spearman'), '.3f')} | {_cell(r['train_seconds'], '.1f')} | "
                     f"{_cell(r['render_ms_per_frame'], '.0f')} |")
    return "\n".join(lines)


def write_report(out_dir: str | Path, file_name: str, prog: str, argv: Optional[list[str]], record: dict, train,
                 config: FieldTrainConfig, body: dict) -> dict:
    """Write ``out_dir/file_name``: the command, the train / test views, image size and steps, then ``body``;
    returns it. Shared by the ablation and capacity commands."""
    report = {"command": f"python -m {prog} " + " ".join(argv if argv is not None else sys.argv[1:]),
              "train_views": record["train_names"], "test_views": record["test_names"],
              "image_size": [train.height, train.width], "steps": config.steps, **body}
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    (Path(out_dir) / file_name).write_text(json.dumps(report, indent=2) + "\n")
    return report


def main(argv: Optional[list[str]] = None) -> int:
    """``python -m tools.field_ablation``: train every variant, print the table, write ``ablation.json``."""
    parser = argparse.ArgumentParser(prog="python -m tools.field_ablation", description=__doc__.split("\n")[0])
    add_run_arguments(parser, "folder of the variants' run directories")
    parser.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated, from {','.join(VARIANTS)}")
    parser.add_argument("--no-flip", action="store_true", help="skip FLIP in the evaluation")
    args = parse_run_command(parser, argv)
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    try:
        unknown = sorted(set(variants) - set(VARIANTS))
        if unknown:
            raise InputError(f"unknown variant(s) {unknown}; choose from {list(VARIANTS)}", field="--variants")
        config, train, test, record = run_inputs(args)
        rows = run_ablation(train, test, config, args.out, variants, data_record=record, with_flip=not args.no_flip)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    rows = [{k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in r.items()} for r in rows]
    write_report(args.out, "ablation.json", "tools.field_ablation", argv, record, train, config, {"rows": rows})
    print(markdown_table(rows))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
