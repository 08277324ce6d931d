"""How well a dynamic field's motion vectors predict its own next frames: pixel by pixel, against its motion.

``python -m tools.field_vectors_check DEMO_DIR [--k 2] [--json FILE]`` reads what ``interleave demo --field RUN``
wrote into DEMO_DIR (the rendered path ``field/`` and the export named in ``results.json``) and, for every
evaluation pair (n-k, n, targets) of the demo, sets the object flow that ``mvec`` extrapolates from the field's
vectors n -> n-k (``scene_velocity`` with frame n-k's depth, then ``extrapolated_flow`` at constant velocity)
against the field's own motion from n to each target (``field_object_flow``, what ``oracle`` applies): the
end-point error in pixels over the pixels that the field's motion moves by more than 0.25 px ("moving"), the
other foreground pixels ("static") and all foreground pixels, for the vectors as they are and with
``coherence=COHERENCE``, beside zero motion (``reproject``) and the backward motion halved in 2D (no depth
read). It also gives the share of foreground pixels whose vectors carry object motion (vectors minus the
camera's own) above 1/32 px (what ``mvec`` counts as moving) and 0.25 px. Conventions: ``docs/motion-vectors.md``.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from engine.core.errors import InputError
from engine.eval.protocol import evaluation_pairs
from engine.fields.dynamic import COHERENCE, field_motion_vectors, field_object_flow, load_dynamic_field
from engine.geometry.motion import camera_motion_vectors, extrapolated_flow, scene_velocity
from engine.io.rgbd import read_sequence

__all__ = ["check", "main", "report", "MOVING_PX"]

#: pixels the field's motion moves by more than this to the target are "moving" (the demo's ``MOVING_PX``)
MOVING_PX = 0.25


def _length(a: np.ndarray) -> np.ndarray:
    return np.hypot(a[..., 0], a[..., 1])


def check(demo_dir: Path, k: int) -> dict:
    """The means over the demo's pairs (module doc) as a flat dict of named figures."""
    demo_dir = Path(demo_dir)
    results = demo_dir / "results.json"
    if not results.is_file() or not (demo_dir / "field").is_dir():
        raise InputError("holds no results.json and field/ of 'interleave demo --field'", file=demo_dir)
    export = json.loads(results.read_text()).get("field", {}).get("export")
    if export is None:
        raise InputError("names no field export (not a dynamic field demo)", file=results)
    assets = load_dynamic_field(export)
    seq = read_sequence(demo_dir / "field")
    n = len(seq)
    t0, t1 = assets.time_range
    times = t0 + (t1 - t0) * np.arange(n) / max(n - 1, 1)  # the demo's times (run_field_demo)
    sums: dict[str, list[float]] = {}

    def add(key: str, value) -> None:
        sums.setdefault(key, []).append(float(value))

    variants = {"as is": None, f"coherence {COHERENCE}": COHERENCE}
    for older, newest, targets in evaluation_pairs(n, k):
        fo, fn = seq[older], seq[newest]
        k_mat, pose = fn.camera.intrinsics, fn.camera.world_to_camera
        fg = np.isfinite(fn.depth)
        camera_only = camera_motion_vectors(fn.depth, fn.camera, fo.camera)
        vectors = {name: field_motion_vectors(assets, k_mat, pose, fn.depth, times[newest], fo.camera.world_to_camera,
                                              times[older], coherence=c) for name, c in variants.items()}
        back = field_object_flow(assets, k_mat, pose, fn.depth, times[newest], times[older])
        for name, v in vectors.items():
            obj = np.nan_to_num(_length(v - camera_only))
            add(f"{name}: foreground share with object vectors > 1/32 px", (obj[fg] > 1 / 32).mean())
            add(f"{name}: foreground share with object vectors > 0.25 px", (obj[fg] > MOVING_PX).mean())
        for t in targets:
            s = (t - newest) / (newest - older)
            truth = field_object_flow(assets, k_mat, pose, fn.depth, times[newest], times[t])
            moving = (_length(truth) > MOVING_PX) & fg
            add("moving share of the frame", moving.mean())
            flows = {"zero motion (reproject)": np.zeros_like(truth), "backward motion halved, 2D": -s * back}
            for name, v in vectors.items():
                velocity, where = scene_velocity(fn.depth, v, fo.depth, fn.camera, fo.camera)
                flows[f"mvec's flow from the vectors {name}"] = np.nan_to_num(
                    extrapolated_flow(fn.depth, velocity, k_mat, s, where))
            for name, flow in flows.items():
                err = _length(flow[..., :2] - truth[..., :2])
                for region, mask in (("moving", moving), ("static", fg & ~moving), ("foreground", fg)):
                    if mask.any():
                        add(f"EPE {region}: {name}", err[mask].mean())
    out = {key: round(float(np.mean(values)), 4) for key, values in sums.items()}
    out["pairs"] = len(evaluation_pairs(n, k))
    return out


def main(argv: Optional[list[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.field_vectors_check", description=__doc__.splitlines()[0])
    parser.add_argument("demo", type=Path, help="the output folder of 'interleave demo --field RUN'")
    parser.add_argument("--k", type=int, default=2, help="the demo's k")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = parser.parse_args(argv)
    return report(lambda: check(args.demo, args.k), args.json, "python -m tools.field_vectors_check", argv)


def report(figures: Callable[[], dict], json_path: Optional[Path], prog: str, argv: Optional[list[str]]) -> int:
    """A check's command line: its figures one a line (and, with ``json_path``, as JSON with the command), or its
    InputError as one line and exit 2."""
    try:
        out = figures()
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for key, value in out.items():
        print(f"{value:>9} {key}")
    if json_path is not None:
        command = " ".join([prog, *(argv if argv is not None else sys.argv[1:])])
        json_path.write_text(json.dumps({"command": command, **out}, indent=1) + "\n")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
