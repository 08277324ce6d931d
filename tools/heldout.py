"""Held-out sequences of the benchmarks: rendered once from the scene generator (seeds no network trained on:
training uses 5000-5031), cached under an output folder, with their measured screen speed.

``speed_set`` builds a set by a rule stated in advance, not by scores: the first seeds of a preset whose
moving pixels move a median within a speed range (px per frame at the rendered size, scaled to 640 px
width), so a set is as fast as the content it stands for whatever each seed happens to draw.
"""
from __future__ import annotations

import argparse
import json
import shutil
import statistics
import time
from dataclasses import replace
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from engine.eval.protocol import evaluation_pairs, json_safe, rendered_history, score_cell, summarize
from engine.io.rgbd import read_sequence
from engine.geometry.encoding import encode8
from engine.predict import Target
from engine.scenegen import generate_sequence
from engine.scenegen.presets import preset_config

__all__ = ["render_set", "motion_speed", "gap", "speed_set", "report_speed", "set_rows", "table_lines", "median_times",
           "write_json", "bench_parser", "parse_common"]


def render_set(out: Path, name: str, overrides: dict, width: int, height: int, frames: int,
               preset: str = "gentle") -> Path:
    """The sequence folder ``out/<name>_<W>x<H>x<frames>``, rendered unless it is already there."""
    folder = Path(out) / f"{name}_{width}x{height}x{frames}"
    if not (folder / "sequence.json").exists():
        config = preset_config(preset, width=width, height=height, num_frames=frames, **overrides)
        generate_sequence(config, folder, progress=False)
    return folder


def motion_speed(sequence) -> tuple[float, float]:
    """(median, 90th percentile) of |true object flow| (px per frame) over the moving pixels of all frames."""
    speeds = []
    for frame in sequence:
        if frame.moving is not None and frame.object_flow is not None and frame.moving.any():
            speeds.append(np.linalg.norm(frame.object_flow[frame.moving], axis=-1))
    if not speeds:
        return 0.0, 0.0
    s = np.concatenate(speeds)
    return float(np.median(s)), float(np.percentile(s, 90))


def gap(value: float, base: float, bound: float) -> float:
    """Share of the base -> bound gap that ``value`` recovers (NaN when the gap is under 0.05 dB)."""
    return (value - base) / (bound - base) if abs(bound - base) >= 0.05 else float("nan")


def speed_set(out: Path, name: str, preset: str, first_seed: int, count: int, speed_range: tuple[float, float],
              width: int, height: int, frames: int, max_tries: int = 40) -> list[tuple[str, Path]]:
    """[(sequence name, folder)] of the first ``count`` seeds from ``first_seed`` on whose moving pixels move
    a median within ``speed_range`` px per frame (at 640 px width); seeds outside it are rendered once and
    remembered in ``out/<name>_<W>x<H>x<frames>_seeds.json`` with their speed, so the choice is reproducible
    and visible. Raises RuntimeError if ``max_tries`` seeds give fewer than ``count``."""
    record_path = Path(out) / f"{name}_{width}x{height}x{frames}_seeds.json"
    record = json.loads(record_path.read_text()) if record_path.exists() else {}
    chosen = []
    for seed in range(first_seed, first_seed + max_tries):
        seq_name = f"{name}{seed}"
        folder = Path(out) / f"{seq_name}_{width}x{height}x{frames}"
        if str(seed) not in record:
            folder = render_set(out, seq_name, dict(seed=seed), width, height, frames, preset)
            median, p90 = motion_speed(read_sequence(folder))
            record[str(seed)] = {"median": median * 640.0 / width, "p90": p90 * 640.0 / width}
            record_path.parent.mkdir(parents=True, exist_ok=True)
            record_path.write_text(json.dumps(record, indent=1))
        if speed_range[0] <= record[str(seed)]["median"] <= speed_range[1]:
            chosen.append((seq_name, render_set(out, seq_name, dict(seed=seed), width, height, frames, preset)))
        elif folder.exists():  # not in the set: its frames are not kept
            shutil.rmtree(folder)
        if len(chosen) == count:
            return chosen
    raise RuntimeError(f"only {len(chosen)} of {max_tries} seeds of preset '{preset}' move a median within "
                       f"{speed_range} px per frame")


def report_speed(set_name: str, seq_name: str, sequence, speeds: dict) -> None:
    """Measure a sequence's ``motion_speed`` into ``speeds[seq_name]`` and print it."""
    speeds[seq_name] = motion_speed(sequence)
    print(f"{set_name}/{seq_name}: moving pixels move a median {speeds[seq_name][0]:.1f} px/frame "
          f"(90th percentile {speeds[seq_name][1]:.1f})", flush=True)


def set_rows(set_name: str, results: list, methods: list[str], ks: list[int], columns: tuple[str, ...]) -> list[dict]:
    """One row per (k, method) of a set's evaluation ``results``: ``columns`` of the summary (means over the
    set's sequences), the share of the reproject -> oracle gap recovered (whole frame, moving pixels; the
    bound is ``reproject`` where ``oracle`` did not run) and the per-sequence ``records``."""
    summary = summarize(results)
    rows = []
    for k in ks:
        base = summary[f"reproject/k={k}"]
        bound = summary.get(f"oracle/k={k}", base)
        for method in methods:
            row = summary.get(f"{method}/k={k}")
            if row is None:
                continue
            rows.append({"set": set_name, "k": k, "method": method, **{c: row.get(c) for c in columns},
                         "gap_whole": gap(row["psnr"], base["psnr"], bound["psnr"]),
                         "gap_moving": gap(row["psnr_moving"], base["psnr_moving"], bound["psnr_moving"]),
                         "records": [r.__dict__ for r in results if r.method == method and r.k == k]})
    return rows


def table_lines(rows: list[dict], columns: tuple[tuple[str, int], ...]) -> list[str]:
    """Markdown rows of ``set_rows``' rows: set, k, method, the (name, digits) ``columns`` and the two gaps."""
    lines = []
    for r in rows:
        values = [score_cell(r[name], digits) for name, digits in columns]
        lines.append(f"| {r['set']} | {r['k']} | {r['method']} | " + " | ".join(values)
                     + f" | {score_cell(100 * r['gap_whole'], 0)}% | {score_cell(100 * r['gap_moving'], 0)}% |")
    return lines


def median_times(rows: list[dict], methods: list[str]) -> str:
    """The line of each method's median ms per frame over all rows."""
    return "median ms per frame over all sets and k: " + ", ".join(
        f"{m} {statistics.median(r['ms_per_frame'] for r in rows if r['method'] == m):.1f}" for m in methods
        if any(r["method"] == m for r in rows))


def timing_cases(sequence, k: int) -> list[tuple[list, list]]:
    """``(history, targets)`` of every evaluation pair (n-k, n) of ``sequence`` at ``k``, held in memory: the
    rendered frames a predictor is given (three, with the motion vectors ``mvec`` reads) and the targets
    n+1 .. n+k-1 (``Target.index``: their frames in the sequence)."""
    cases = []
    for older, newest, targets in evaluation_pairs(len(sequence), k):
        history = rendered_history(sequence, older, newest, with_vectors=True, three=True)
        cases.append((history, [Target(sequence.cameras[t], float(sequence.times[t]), t) for t in targets]))
    return cases


def warm_runs(predictors: dict, cases: list, repeats: int, encoding: str = "linear",
              clock: Callable[[], float] = time.perf_counter) -> Iterator[tuple]:
    """Time ``predictors`` (key -> Predictor) on ``cases`` (``timing_cases``), warm: ``repeats`` passes, the
    predictors in rotating order per case so none always runs first. Yields ``(repeat, case, key, state,
    predictions, ms)`` per run: one prepare and the renders of the case's targets, ``ms`` the wall time per
    predicted frame. ``encoding="srgb8"`` asks each target for 8-bit codes, as a ``Session`` with
    ``color_out="srgb8"`` does: a prediction that comes back linear is encoded on the host inside the timing
    (``encoding.encode8``), so every prediction yielded holds codes. ``clock`` (seconds) is what ``ms`` measures:
    wall time, or e.g. ``time.process_time`` (CPU time of all the process's threads, steadier than wall time on a
    machine shared with other jobs)."""
    keys = list(predictors)
    for r in range(repeats):
        for c, (history, targets) in enumerate(cases):
            targets = [replace(target, encoding=encoding) for target in targets]
            shift = (r + c) % len(keys)
            for key in keys[shift:] + keys[:shift]:
                predictor = predictors[key]
                frames = history[-max(predictor.history_needed, predictor.history_wanted, 1):]
                start = clock()
                state = predictor.prepare(frames)
                predictions = [predictor.render(state, target) for target in targets]
                for p in predictions:
                    if p.encoding != encoding:
                        p.color = encode8(p.color)
                yield r, c, key, state, predictions, 1e3 * (clock() - start) / len(targets)


def write_json(path, doc: dict) -> None:
    """``doc`` as indented JSON at ``path`` (NaN as null; folders made), nothing when ``path`` is None."""
    if path is None:
        return
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(json_safe(doc), indent=1))


def bench_parser(doc: str, out: str, k: str, methods: str, sets: list[str]) -> argparse.ArgumentParser:
    """The options the held-out benchmarks share, with their defaults: --out, --size, --frames, --k,
    --methods, --sets, --max-groups, --json."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path(out))
    parser.add_argument("--size", default="640x360")
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--k", default=k)
    parser.add_argument("--methods", default=methods)
    parser.add_argument("--sets", default=",".join(sets))
    parser.add_argument("--max-groups", type=int, default=None)
    parser.add_argument("--json", type=Path, default=None)
    return parser


def parse_common(args) -> tuple[int, int, list[int], list[str]]:
    """(width, height, ks, methods with reproject and oracle) of ``bench_parser``'s options."""
    from engine.predict import split_methods

    width, height = (int(v) for v in args.size.lower().split("x"))
    methods = split_methods(args.methods)
    for needed in ("oracle", "reproject"):
        if needed not in methods:
            methods.insert(0, needed)
    return width, height, [int(v) for v in args.k.split(",")], methods
