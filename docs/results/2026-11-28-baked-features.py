"""Baked renderers of several exports timed side by side (issue 44, item 1; page 2026-11-28-baked-features.md):
one GlBakedRenderer per export, renders alternating between them on the demo path's 8 cameras, median wall and
process CPU time per frame after 2 warm-up rounds.

    PYTHONPATH=. python docs/results/2026-11-28-baked-features.py OUT.json EXPORT [EXPORT ...] [--size 512] [--renders 12]
"""
from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from engine.fields.baked import load_baked
from engine.fields.camera_path import field_camera_path, scale_intrinsics
from engine.fields.glbaked import GlBakedRenderer, channel_groups
from engine.fields.render import load_field


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("exports", nargs="+")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--renders", type=int, default=12)
    args = ap.parse_args()
    cams, w0, h0 = field_camera_path(load_field(args.exports[0]), None, 8)
    renderers = {}
    for export in args.exports:
        baked = load_baked(export)
        renderers[export] = (GlBakedRenderer(baked, args.size, args.size), baked)
    times = {e: ([], []) for e in renderers}
    load = [os.getloadavg()[0]]
    for i in range(args.renders + 2):
        cam = cams[i % len(cams)]
        k = scale_intrinsics(cam.intrinsics, w0, h0, args.size, args.size)
        for export, (renderer, _) in renderers.items():
            wall, cpu = time.perf_counter(), time.process_time()
            renderer.render(k, cam.world_to_camera)
            if i >= 2:
                times[export][0].append(time.perf_counter() - wall)
                times[export][1].append(time.process_time() - cpu)
    load.append(os.getloadavg()[0])
    rows = []
    for export, (renderer, baked) in renderers.items():
        wall_ms = 1e3 * float(np.median(times[export][0]))
        rows.append({"export": export, "feature_dim": int(baked.feature_dim),
                     "groups": channel_groups(int(baked.feature_dim)), "bricks": int(baked.density.shape[0]),
                     "wall_ms": wall_ms, "fps": 1e3 / wall_ms, "cpu_ms": 1e3 * float(np.median(times[export][1]))})
        renderer.release()
        print(json.dumps(rows[-1]), flush=True)
    with open(args.out, "w") as f:
        json.dump({"size": args.size, "renders": args.renders, "load_1min": load, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
