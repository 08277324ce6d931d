"""A/B timing of the field march's distance skipping (engine.fields.gl.empty_distance) against the march that
tests every sample (the distances clamped to 1: the same shader, no jumps), renders alternating on the demo
path's cameras, and the check that both give the same bits.

    PYTHONPATH=. python docs/results/2026-11-28-field-skip.py EXPORT OUT.json [--size 512x512] [--renders 12]
"""
from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from engine.fields import gl as glfield
from engine.fields.baked import load_baked
from engine.fields.camera_path import field_camera_path, scale_intrinsics
from engine.fields.glbaked import GlBakedRenderer
from engine.fields.render import load_field


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("export")
    ap.add_argument("out")
    ap.add_argument("--size", default="512x512")
    ap.add_argument("--renders", type=int, default=12)
    args = ap.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    field = load_field(args.export)
    cams, w0, h0 = field_camera_path(field, None, 8)
    exact = glfield.empty_distance
    clamped = lambda occ, cap=255: np.minimum(exact(occ, cap), 1).astype(np.uint8)  # noqa: E731
    makers = {"gl float": lambda: glfield.GlFieldRenderer(field, width, height)}
    if os.path.isfile(os.path.join(args.export, "baked.json")):
        baked = load_baked(args.export)
        makers["gl baked"] = lambda: GlBakedRenderer(baked, width, height)
    records = []
    for name, make in makers.items():
        renderers = {"skip": make()}
        glfield.empty_distance = clamped
        try:
            renderers["step"] = make()
        finally:
            glfield.empty_distance = exact
        times = {k: ([], []) for k in renderers}
        same = True
        for i in range(args.renders + 2):
            cam = cams[i % len(cams)]
            k = scale_intrinsics(cam.intrinsics, w0, h0, width, height)
            outs = {}
            for key, r in renderers.items():
                wall, cpu = time.perf_counter(), time.process_time()
                outs[key] = r.render(k, cam.world_to_camera)
                if i >= 2:
                    times[key][0].append(time.perf_counter() - wall)
                    times[key][1].append(time.process_time() - cpu)
            same &= all(np.array_equal(outs["skip"][c], outs["step"][c], equal_nan=True)
                        for c in ("color", "depth", "opacity"))
        for r in renderers.values():
            r.release()
        rec = {"renderer": name, "size": args.size, "identical": bool(same), "load": os.getloadavg()[0]}
        for key, (wall, cpu) in times.items():
            rec[f"{key}_wall_ms"] = 1e3 * float(np.median(wall))
            rec[f"{key}_cpu_ms"] = 1e3 * float(np.median(cpu))
        rec["cpu_ratio"] = rec["skip_cpu_ms"] / rec["step_cpu_ms"]
        print(json.dumps(rec), flush=True)
        records.append(rec)
    with open(args.out, "w") as f:
        json.dump({"export": args.export, "records": records}, f, indent=2)


if __name__ == "__main__":
    main()
