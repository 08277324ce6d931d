"""Early ray termination of the baked GL renderers (issue 44): milliseconds a 512x512 frame on every held-out view
of a run, at each stop threshold, with the PSNR of each frame against the one stopped at 1e-4 (the exact
renderers' threshold) and the samples evaluated per pixel.

    PYTHONPATH=. python docs/results/2026-11-30-baked-termination.py OUT.json static EXPORT RUN
    PYTHONPATH=. python docs/results/2026-11-30-baked-termination.py OUT.json dynamic EXPORT RUN

Rounds alternate the thresholds (llvmpipe's times drift by up to 10 % in a session); the median of every frame
timed (dispatch to finish, no readback) is reported.
"""
import json
import sys
from pathlib import Path

import numpy as np

from engine.fields.baked import load_baked, load_baked_dynamic
from engine.fields.camera_path import scale_intrinsics
from engine.fields.glbaked import GlBakedDynamicRenderer, GlBakedRenderer

SIZE, EPS, ROUNDS, FRAMES = 512, (1e-4, 1e-3, 1.0 / 255.0), 5, 4


def main() -> None:
    out_path, kind, export, run = sys.argv[1:5]
    if kind == "dynamic":
        from models.fields.data.select import load_dynamic_run_views
        _, test = load_dynamic_run_views(run)
        baked, cls = load_baked_dynamic(export), GlBakedDynamicRenderer
        times = [float(t) for t in test.times]
    else:
        from models.fields.data.select import load_run_views
        _, test = load_run_views(run)
        baked, cls = load_baked(export), GlBakedRenderer
        times = [None] * len(test.cameras)
    renderers = {e: cls(baked, SIZE, SIZE, transmittance_eps=e) for e in EPS}
    counters = {e: cls(baked, SIZE, SIZE, transmittance_eps=e, count_evaluations=True) for e in EPS}
    rows = []
    for view, (cam, tm) in enumerate(zip(test.cameras, times)):
        k = scale_intrinsics(cam.intrinsics, test.width, test.height, SIZE, SIZE)
        extra = () if tm is None else (tm,)
        ms = {e: [] for e in EPS}
        frames = {e: renderers[e].render(k, cam.world_to_camera, *extra)["color"] for e in EPS}
        for _ in range(ROUNDS):
            for e, r in renderers.items():
                r.render(k, cam.world_to_camera, *extra)  # sets the time uniforms of a dynamic field
                ms[e] += [1e3 * t for t in r.dispatch_seconds(k, cam.world_to_camera, FRAMES)]
        row = {"view": view, "time": tm}
        for e in EPS:
            mse = float(np.mean((frames[e] - frames[EPS[0]]) ** 2))
            evals = counters[e].render(k, cam.world_to_camera, *extra)["evaluations"]
            row[f"{e:.6g}"] = {"ms": float(np.median(ms[e])), "psnr_vs_1e-4": 10 * np.log10(1 / max(mse, 1e-20)),
                               "evaluations_per_pixel": float(evals.mean())}
        rows.append(row)
        print(json.dumps(row), flush=True)
    for r in list(renderers.values()) + list(counters.values()):
        r.release()
    Path(out_path).write_text(json.dumps({"kind": kind, "export": export, "run": run, "size": SIZE,
                                          "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
