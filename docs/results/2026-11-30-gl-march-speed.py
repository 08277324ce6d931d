"""The GL field renderers on llvmpipe, 512x512 (page 2026-11-30-gl-march-speed.md): each renderer renders its
frames in turn, rounds interleaved between renderers, median wall and process CPU ms a frame after one warm-up
round. Run it once per code tree to compare trees (``PYTHONPATH=TREE``), alternating trees between runs.

    PYTHONPATH=. python docs/results/2026-11-30-gl-march-speed.py OUT.json --static EXPORT \
        --dynamic RUN BAKE128 BAKE256 --rig RUN [--rounds 3]

EXPORT: a static field's export with a bake (``interleave export field``); RUN: a dynamic run (its exact assets
are built from the checkpoint); BAKE128 / BAKE256: folders with ``baked_dynamic.*`` of that run
(``models.fields.bake.bake_dynamic(model, 128 | 256, 33)``); --rig: a second dynamic run, forward-facing.
Cameras: the static export's demo path (8 views); a dynamic run's held-out views (at most 5, spread over time).
"""
from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from engine.fields.baked import load_baked, load_baked_dynamic
from engine.fields.camera_path import field_camera_path, scale_intrinsics
from engine.fields.gl import GlFieldRenderer
from engine.fields.glbaked import GlBakedDynamicRenderer, GlBakedRenderer
from engine.fields.gldynamic import GlDynamicRenderer
from engine.fields.render import load_field
from models.fields.assets import dynamic_assets, load_assets
from models.fields.data.select import load_dynamic_run_views
from models.fields.train_dynamic import load_dynamic_model

SIZE = 512


def dynamic_frames(run: str) -> list[tuple]:
    """(K, world_to_camera, time) of up to 5 held-out views of ``run`` spread over its views, at SIZE^2."""
    _, test = load_dynamic_run_views(run)
    picks = np.unique(np.linspace(0, len(test.cameras) - 1, 5).round().astype(int))
    return [(scale_intrinsics(test.cameras[i].intrinsics, test.width, test.height, SIZE, SIZE),
             test.cameras[i].world_to_camera, float(test.times[i])) for i in picks]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("--static", required=True)
    ap.add_argument("--dynamic", nargs=3, required=True, metavar=("RUN", "BAKE128", "BAKE256"))
    ap.add_argument("--rig", required=True)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    cams, w0, h0 = field_camera_path(load_field(args.static), None, 8)
    static = [(scale_intrinsics(c.intrinsics, w0, h0, SIZE, SIZE), c.world_to_camera) for c in cams]
    lego, rig = dynamic_frames(args.dynamic[0]), dynamic_frames(args.rig)
    exact = {run: load_assets(*dynamic_assets(load_dynamic_model(run)), "dynamic")
             for run in (args.dynamic[0], args.rig)}
    renderers = {
        "static baked": (GlBakedRenderer(load_baked(args.static), SIZE, SIZE), static),
        "static exact": (GlFieldRenderer(load_field(args.static), SIZE, SIZE), static),
        "dynamic baked, 128 cells": (GlBakedDynamicRenderer(load_baked_dynamic(args.dynamic[1]), SIZE, SIZE), lego),
        "dynamic baked, 256 cells": (GlBakedDynamicRenderer(load_baked_dynamic(args.dynamic[2]), SIZE, SIZE), lego),
        "dynamic exact": (GlDynamicRenderer(exact[args.dynamic[0]], SIZE, SIZE), lego),
        "dynamic exact, forward-facing rig": (GlDynamicRenderer(exact[args.rig], SIZE, SIZE), rig),
    }
    times = {name: ([], []) for name in renderers}
    load = [os.getloadavg()[0]]
    for round_ in range(args.rounds + 1):
        for name, (renderer, frames) in renderers.items():
            for frame in frames:
                wall, cpu = time.perf_counter(), time.process_time()
                renderer.render(*frame)
                if round_:
                    times[name][0].append(time.perf_counter() - wall)
                    times[name][1].append(time.process_time() - cpu)
    load.append(os.getloadavg()[0])
    rows = []
    for name, (renderer, frames) in renderers.items():
        wall_ms = 1e3 * float(np.median(times[name][0]))
        rows.append({"renderer": name, "frames": len(frames), "wall_ms": wall_ms, "fps": 1e3 / wall_ms,
                     "cpu_ms": 1e3 * float(np.median(times[name][1]))})
        renderer.release()
        print(json.dumps(rows[-1]), flush=True)
    with open(args.out, "w") as f:
        json.dump({"size": SIZE, "rounds": args.rounds, "load_1min": load, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
