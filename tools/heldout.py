"""Held-out sequences of the benchmarks: rendered once from the scene generator (seeds no network trained on:
training uses 5000-5031), cached under an output folder, with their measured screen speed.

``speed_set`` builds a set by a rule stated in advance, not by scores: the first seeds of a preset whose
moving pixels move a median within a speed range (px per frame at the rendered size, scaled to 640 px
width), so a set is as fast as the content it stands for whatever each seed happens to draw.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from engine.io.rgbd import read_sequence
from engine.scenegen import generate_sequence
from engine.scenegen.presets import preset_config

__all__ = ["render_set", "motion_speed", "gap", "speed_set"]


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
