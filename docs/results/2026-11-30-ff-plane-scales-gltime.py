"""Exact GL field renderer (engine.fields.gl, default options): ms a frame of two exports, alternating rounds.

    PYTHONPATH=. python docs/results/2026-11-30-ff-plane-scales-gltime.py OUT.json EXPORT_A:RUN_A EXPORT_B:RUN_B

Each export is timed on its run's first held-out view at 504x378 and 1920x1080; the page's figures are in
2026-11-30-ff-plane-scales.json under "gl_ms".
"""
import json
import sys
import time

import numpy as np
from engine.fields.render import load_field
from engine.fields.gl import GlFieldRenderer
from engine.fields.camera_path import scale_intrinsics
from models.fields.data.select import load_run_views

out = {}
pairs = [a.split(":") for a in sys.argv[2:]]
for size in ((504, 378), (1920, 1080)):
    rs = {}
    for ex, run in pairs:
        _, test = load_run_views(run)
        cam = test.cameras[0]
        k = scale_intrinsics(cam.intrinsics, test.width, test.height, *size)
        rs[ex] = (GlFieldRenderer(load_field(ex), *size), k, cam.world_to_camera)
    ms = {ex: [] for ex in rs}
    for _ in range(3):
        for ex, (r, k, pose) in rs.items():
            r.render(k, pose)
            t = time.perf_counter(); r.render(k, pose); ms[ex].append(1e3 * (time.perf_counter() - t))
    for ex in rs:
        out[f"{ex} {size[0]}x{size[1]}"] = float(np.median(ms[ex]))
        print(ex, size, round(float(np.median(ms[ex])), 1), flush=True)
json.dump(out, open(sys.argv[1], "w"), indent=1)
