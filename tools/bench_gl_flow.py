"""The GL backend's optical flow (``engine.geometry.backends.gl.flow.GlOpticalFlow``) against OpenCV DIS medium,
on the inputs ``flow2d`` gives its flow, on held-out sequences.

``python -m tools.bench_gl_flow [--out out/bench_motion] [--size 640x360] [--frames 16] [--k 2]
[--sets gentle,fast] [--validation] [--config patch_size=8,patch_stride=4 ...] [--json FILE]``

For every pair (n-k, n) with at least 50 moving pixels, frame n-k is warped into frame n's view exactly as
``Flow2D._prepare`` does it (``engine.predict.base.warp_and_fill`` to frame n's ``Target``: camera motion
cancelled, holes filled), and u(n -> n-k) is estimated from frame n to the warped frame by DIS medium
(``dis_estimator("medium")`` + ``dis_calc`` on ``luma8``) and by the GL flow (from the linear colours; it
computes the same 8-bit luma on the GPU). Scored over the pixels whose true u(n -> n-k) (from the object
transforms, ``true_object_flow``) exceeds 0.5 px: the median end-point error of each pair against the truth
(GL, DIS, and zero motion for scale), the median EPE between the GL and DIS flows (moving pixels and whole
frame), each averaged over the set's pairs; and the median wall ms per estimate (GL: upload, passes and
readback; on Mesa llvmpipe this is CPU time, not a GPU's).

Sets: ``gentle`` seeds 1001, 1002 (the generator's defaults), ``fast`` seeds 7003, 7005, 7007 of the ``fast``
preset (the sequences of ``tools.bench_motion``'s fast set). ``--validation`` uses the validation sequences
instead (gentle 1005, 1006; fast 7204, 7205, under ``out/validation``), on which ``GlFlowConfig``'s defaults
were chosen; ``--config`` (repeatable) adds a GL row with those ``GlFlowConfig`` fields changed.
"""
from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from engine.geometry.backends.gl.flow import GlFlowConfig, GlOpticalFlow
from engine.io.rgbd import read_sequence
from engine.predict.base import Target, Timer, true_object_flow, warp_and_fill
from engine.predict.dis import dis_calc, dis_estimator, luma8
from tools.heldout import render_set, report_speed, write_json

#: set name -> (preset, seeds) of the benchmark and of the validation
SETS = {"gentle": ("gentle", (1001, 1002)), "fast": ("fast", (7003, 7005, 7007))}
VALIDATION = {"gentle": ("gentle", (1005, 1006)), "fast": ("fast", (7204, 7205))}


def set_sequences(out: Path, name: str, validation: bool, width: int, height: int, frames: int) -> list[Path]:
    """Folders of a set's sequences (rendered on first use; the names ``tools.bench_motion`` and
    ``tools.motion_ablation`` cache them under, so their renders are reused)."""
    preset, seeds = (VALIDATION if validation else SETS)[name]
    prefix = "seed" if preset == "gentle" else ("valfast" if validation else "fast")
    return [render_set(out, f"{prefix}{s}", {"seed": s}, width, height, frames, preset) for s in seeds]


def parse_config(text: str) -> GlFlowConfig:
    """``GlFlowConfig`` with the fields of ``"name=value,name=value"`` changed (each of its default's type, an int where
    the default is None)."""
    default, fields = GlFlowConfig(), {}
    for item in filter(None, text.split(",")):
        name, _, value = item.partition("=")
        name = name.strip()
        if not hasattr(default, name):
            raise SystemExit(f"GlFlowConfig has no field '{name}'")
        now = getattr(default, name)
        fields[name] = int(value) if now is None else type(now)(value)
    return replace(default, **fields)


def config_name(config: GlFlowConfig) -> str:
    changed = [f"{k}={v}" for k, v in asdict(config).items() if v != getattr(GlFlowConfig(), k)]
    return "gl" + (f" ({', '.join(changed)})" if changed else "")


def pairs(seq, k: int):
    """(frame n, warped frame n-k, true u(n -> n-k) (H, W, 2), moving mask) of a sequence's scored pairs."""
    objects = {o.id: o for o in seq.objects}
    for n in range(k, len(seq), k):
        older, newest = seq[n - k], seq[n]
        truth = true_object_flow(newest, objects, n - k)[..., :2]
        moving = np.linalg.norm(truth, axis=-1) > 0.5
        if moving.sum() < 50:
            continue
        warped, _ = warp_and_fill(older, Target(newest.camera, newest.time, newest.index), Timer())
        yield newest.color, warped, truth, moving


def median_epe(flow: np.ndarray, reference: np.ndarray, mask=None) -> float:
    error = np.linalg.norm(flow - reference, axis=-1)
    return float(np.median(error if mask is None else error[mask]))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=None,
                        help="render cache (default out/bench_motion, with --validation out/validation)")
    parser.add_argument("--size", default="640x360")
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--k", type=int, default=2)
    parser.add_argument("--sets", default="gentle,fast")
    parser.add_argument("--validation", action="store_true", help="the validation sequences instead")
    parser.add_argument("--config", action="append", default=[], help="GlFlowConfig fields of an extra GL row")
    parser.add_argument("--no-default", action="store_true", help="no row for the default GlFlowConfig")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.lower().split("x"))
    out = args.out or Path("out/validation" if args.validation else "out/bench_motion")
    configs = ([] if args.no_default else [GlFlowConfig()]) + [parse_config(c) for c in args.config]
    estimators = {config_name(c): GlOpticalFlow(config=c) for c in configs}
    dis = dis_estimator("medium")
    rows, speeds, members = [], {}, {}
    for set_name in args.sets.split(","):
        if set_name not in SETS:
            parser.error(f"unknown set '{set_name}', expected some of {', '.join(SETS)}")
        scores = {name: {"epe": [], "epe_vs_dis": [], "epe_vs_dis_all": [], "ms": []} for name in estimators}
        scores.update({"dis medium": {"epe": [], "ms": []}, "zero motion": {"epe": []}})
        members[set_name] = []
        for folder in set_sequences(out, set_name, args.validation, width, height, args.frames):
            seq = read_sequence(folder)
            report_speed(set_name, folder.name, seq, speeds)
            members[set_name].append(folder.name)
            for color_n, warped, truth, moving in pairs(seq, args.k):
                start = time.perf_counter()
                reference = dis_calc(dis, luma8(color_n), luma8(warped))
                scores["dis medium"]["ms"].append(1e3 * (time.perf_counter() - start))
                scores["dis medium"]["epe"].append(median_epe(reference, truth, moving))
                scores["zero motion"]["epe"].append(median_epe(np.zeros_like(truth), truth, moving))
                for name, estimator in estimators.items():
                    estimator.estimate(color_n, warped)  # programs compiled, buffers grown: not timed
                    start = time.perf_counter()
                    flow = estimator.estimate(color_n, warped)
                    s = scores[name]
                    s["ms"].append(1e3 * (time.perf_counter() - start))
                    s["epe"].append(median_epe(flow, truth, moving))
                    s["epe_vs_dis"].append(median_epe(flow, reference, moving))
                    s["epe_vs_dis_all"].append(median_epe(flow, reference))
        for name, s in scores.items():
            row = {"set": set_name, "k": args.k, "estimate": name, "pairs": len(s["epe"]),
                   "median_epe": float(np.mean(s["epe"])), "median_epe_per_pair": s["epe"]}
            if "epe_vs_dis" in s:
                row["epe_vs_dis_moving"] = float(np.mean(s["epe_vs_dis"]))
                row["epe_vs_dis_all"] = float(np.mean(s["epe_vs_dis_all"]))
                row["config"] = asdict(configs[list(estimators).index(name)])
            if "ms" in s:
                row["ms"] = float(statistics.median(s["ms"]))
            rows.append(row)
    print("\n| set | k | estimate | pairs | median EPE vs truth (px) | EPE vs DIS, moving (px) | EPE vs DIS, all (px) "
          "| ms per estimate |\n|---|---|---|---|---|---|---|---|")
    for r in rows:
        cells = [f"{r[c]:.2f}" if c in r else "-" for c in ("median_epe", "epe_vs_dis_moving", "epe_vs_dis_all")]
        ms = f"{r['ms']:.1f}" if "ms" in r else "-"
        print(f"| {r['set']} | {r['k']} | {r['estimate']} | {r['pairs']} | " + " | ".join(cells) + f" | {ms} |")
    renderer = next(iter(estimators.values())).gl.renderer if estimators else None
    write_json(args.json, {"renderer": renderer, "size": [width, height], "frames": args.frames, "k": args.k,
                           "validation": args.validation, "sets": members, "speeds": speeds, "rows": rows})


if __name__ == "__main__":
    main()
