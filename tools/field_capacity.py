"""Field size against quality: grow the tri-planes step by step and stop when capacity stops buying error.

``run_capacity_sweep`` trains the same run (seed, views, steps, priors) at each rung of a ladder of field
sizes, smallest first, scores each on the held-out views and stops climbing once ``patience`` rungs in a
row gain less than ``min_gain_db`` PSNR over the best so far (the rest of the ladder is not trained). It
returns every trained rung with its size (parameters, bytes of float32 and uint8 planes), PSNR / SSIM /
FLIP / depth MAE, training and render time, and the rung it picks: the smallest within ``min_gain_db`` of
the best. Because it selects on the held-out views it is a capacity study, not a protocol score::

    python -m tools.field_capacity --scene /work/shared/data/nerf_synthetic_lego --views 8 --downscale 8 \\
        --steps 2000 --threads 1 --out runs/capacity_lego8
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path
from typing import Optional, Sequence

from engine.core.errors import InputError
from models.fields.train_static import (FieldTrainConfig, add_run_arguments, evaluate_field, load_model,
                                        parse_run_command, run_inputs, train_field)
from tools.field_ablation import write_report

__all__ = ["DEFAULT_LADDER", "field_size", "run_capacity_sweep", "markdown_table", "main"]

#: (name, resolutions, feature_dim), smallest first.
DEFAULT_LADDER: tuple[tuple[str, tuple[int, ...], int], ...] = (
    ("r16-32_c4", (16, 32), 4),
    ("r32-64_c4", (32, 64), 4),
    ("r32-64-128_c8", (32, 64, 128), 8),
    ("r64-128-256_c8", (64, 128, 256), 8),
    ("r64-128-256_c16", (64, 128, 256), 16),
)


def field_size(model) -> dict[str, int]:
    """Parameter counts and bytes of the exported planes (float32 and uint8) and MLPs."""
    planes = sum(p.numel() for p in model.field.encoding.parameters())
    mlps = sum(p.numel() for n, p in model.field.named_parameters() if not n.startswith("encoding."))
    return {"plane_params": int(planes), "mlp_params": int(mlps), "float32_bytes": int(4 * (planes + mlps)),
            "uint8_plane_bytes": int(planes + 4 * mlps)}


def run_capacity_sweep(train, test, config: FieldTrainConfig, out_dir: str | Path,
                       ladder: Sequence[tuple[str, tuple[int, ...], int]] = DEFAULT_LADDER, *,
                       min_gain_db: float = 0.25, patience: int = 1, progress: bool = True,
                       data_record: Optional[dict] = None, with_flip: bool = True) -> dict:
    """Train up the ladder until capacity stops paying; returns ``{"rows": [...], "picked": name, ...}``."""
    if min_gain_db < 0 or patience < 1:
        raise InputError("min_gain_db must be >= 0 and patience >= 1", field="capacity")
    rows, best, stale = [], -math.inf, 0
    for name, resolutions, channels in ladder:
        run_config = dataclasses.replace(config, field=dataclasses.replace(
            config.field, resolutions=tuple(resolutions), feature_dim=int(channels)))
        run = train_field(train, run_config, Path(out_dir) / name, progress=progress)
        if data_record is not None:
            (run / "data.json").write_text(json.dumps(data_record, indent=2) + "\n")
        scores = evaluate_field(run, test, with_flip=with_flip)
        rows.append({"rung": name, "resolutions": list(resolutions), "feature_dim": int(channels),
                     **field_size(load_model(run)), **scores})
        if scores["psnr"] > best + min_gain_db:
            stale = 0
        else:
            stale += 1
        best = max(best, scores["psnr"])
        if stale >= patience:
            break
    top = max(r["psnr"] for r in rows)
    picked = next(r["rung"] for r in rows if r["psnr"] >= top - min_gain_db)
    skipped = [name for name, _, _ in ladder[len(rows):]]
    return {"rows": rows, "picked": picked, "not_trained": skipped, "min_gain_db": min_gain_db,
            "patience": patience}


def _cell(value, fmt: str) -> str:
    return "n/a" if value is None or (isinstance(value, float) and not math.isfinite(value)) else format(value, fmt)


def markdown_table(report: dict) -> str:
    lines = ["| rung | plane params | MB (fp32) | MB (uint8 planes) | PSNR | SSIM | FLIP | depth MAE | train s | "
             "render ms |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in report["rows"]:
        mark = " (picked)" if r["rung"] == report["picked"] else ""
        lines.append(f"| {r['rung']}{mark} | {r['plane_params']} | {r['float32_bytes'] / 1e6:.2f} | "
                     f"{r['uint8_plane_bytes'] / 1e6:.2f} | {_cell(r['psnr'], '.2f')} | {_cell(r['ssim'], '.3f')} | "
                     f"{_cell(r.get('flip'), '.3f')} | {_cell(r['depth_mae'], '.3f')} | "
                     f"{_cell(r['train_seconds'], '.1f')} | {_cell(r['render_ms_per_frame'], '.0f')} |")
    if report["not_trained"]:
        lines.append(f"\nNot trained (capacity stopped paying): {', '.join(report['not_trained'])}")
    return "\n".join(lines)


def main(argv: Optional[list[str]] = None) -> int:
    """``python -m tools.field_capacity``: the sweep, a markdown table and ``OUT/capacity.json``."""
    parser = argparse.ArgumentParser(prog="python -m tools.field_capacity", description=__doc__.split("\n")[0])
    add_run_arguments(parser, "folder of the rungs' run directories")
    parser.add_argument("--min-gain-db", type=float, default=0.25, help="smallest PSNR gain worth a bigger field")
    parser.add_argument("--patience", type=int, default=1, help="rungs without that gain before stopping")
    parser.add_argument("--no-flip", action="store_true", help="skip FLIP")
    args = parse_run_command(parser, argv)
    try:
        config, train, test, record = run_inputs(args)
        report = run_capacity_sweep(train, test, config, args.out, min_gain_db=args.min_gain_db,
                                    patience=args.patience, data_record=record, with_flip=not args.no_flip)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    report["rows"] = [{k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in r.items()}
                      for r in report["rows"]]
    report = write_report(args.out, "capacity.json", "tools.field_capacity", argv, record, train, config, report)
    print(markdown_table(report))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
