"""Figures of 2026-11-29-dynamic-deferred.md measured on the suite's tiny fields (issue 44, item 1).

``PYTHONPATH=. python docs/results/2026-11-29-dynamic-deferred.py train``: the moving sphere of
tests/fields/test_dynamic_field.py, DeRF and K-Planes, per-sample and deferred, 40 and 120 steps, held-out PSNR.
``... bake RUN OUT.json``: a lego run trained with deferred shading and a canonical field of tri-planes, baked
(128 cells a side, 33^3 flow vertices a time key) and rendered by the numpy oracle against the exact render.
``... gl RUN OUT.json``: the same in the GL renderers, and their time at 512x512.
``... parity``: the deferred fixtures of tests/fields/test_dynrender.py rendered by torch, numpy, onnxruntime
and GL at two times; the largest colour differences and GL's PSNR against numpy.
"""
from __future__ import annotations

import dataclasses
import pathlib
import sys
import tempfile
import warnings

import numpy as np
import torch


def train() -> None:
    from models.fields.data.timed import split_by_camera
    from models.fields.train_dynamic import evaluate_dynamic, train_dynamic
    from tests.fields.test_dynamic_field import TIMES, TINY, sphere_video, tiny_config

    train_views, test = split_by_camera(sphere_video([0, 30, 15, 60], TIMES), ["cam0", "cam1", "cam3"], ["cam2"])
    for kind in ("derf", "kplanes"):
        for shading in ("per-sample", "deferred"):
            for steps in (40, 120):
                field = dataclasses.replace(TINY, kind=kind,
                                            canonical=dataclasses.replace(TINY.canonical, shading=shading))
                with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    run = train_dynamic(train_views, tiny_config(steps, field=field), tmp + "/run", progress=False)
                    psnr = evaluate_dynamic(run, test, with_flip=False)["psnr"]
                print(kind, shading, steps, round(psnr, 2), flush=True)


def parity() -> None:
    import tests.fields.test_dynrender as T
    from engine.fields.dynamic import load_dynamic_field, render_dynamic_field
    from engine.fields.gldynamic import GlDynamicRenderer

    class Factory:  # pytest's tmp_path_factory, enough for the fixtures
        def __init__(self, root: str) -> None:
            self.root = pathlib.Path(root)

        def mktemp(self, name: str) -> pathlib.Path:
            path = self.root / name
            path.mkdir()
            return path

    with tempfile.TemporaryDirectory() as tmp:
        for name in ("derf_deferred", "kplanes_deferred"):
            model, out, camera = getattr(T, name).__wrapped__(Factory(tmp))
            assets = load_dynamic_field(out)
            t0, t1 = assets.time_range
            for t in (t0 + 0.3 * (t1 - t0), t1):
                ref = T._torch(model, camera, t)
                for query in ("numpy", "onnx"):
                    got = render_dynamic_field(assets, *camera, T.H, T.W, t, query=query)
                    print(name, t, query, "colour", np.abs(got["color"] - ref["color"]).max())
                numpy_frame = render_dynamic_field(assets, *camera, T.H, T.W, t)
                with GlDynamicRenderer(assets, T.W, T.H, **T.EXACT) as renderer:
                    got = renderer.render(*camera, t)
                print(name, t, "gl", "colour", np.abs(got["color"] - numpy_frame["color"]).max(),
                      "psnr", T._psnr(numpy_frame, got))
            print(name, "parity", assets.manifest["parity"])


def bake(run: str, out_json: str) -> None:
    """A lego run trained with --field.canonical.shading deferred --no-field.canonical-time, baked
    (``bake_dynamic``) and rendered by the numpy oracle against the exact numpy render on every held-out view."""
    import json
    import time

    from engine.core.colorspace import display_encode
    from engine.eval.metrics import psnr
    from engine.fields.baked import load_baked_dynamic, render_baked_dynamic
    from engine.fields.dynamic import render_dynamic_field
    from models.fields.assets import dynamic_assets, load_assets
    from models.fields.bake import bake_dynamic
    from models.fields.data.select import load_dynamic_run_views
    from models.fields.train_dynamic import load_dynamic_model

    model = load_dynamic_model(run)
    exact = load_assets(*dynamic_assets(model), "dynamic")
    start = time.perf_counter()
    resolution, motion_resolution = 128, 33
    arrays, manifest = bake_dynamic(model, resolution, motion_resolution)
    seconds = time.perf_counter() - start
    with tempfile.TemporaryDirectory() as tmp:
        np.savez_compressed(pathlib.Path(tmp) / "baked_dynamic.npz", **arrays)
        (pathlib.Path(tmp) / "baked_dynamic.json").write_text(json.dumps(manifest))
        npz_bytes = (pathlib.Path(tmp) / "baked_dynamic.npz").stat().st_size
        baked = load_baked_dynamic(tmp)
    _, test = load_dynamic_run_views(run)
    views = []
    for i, cam in enumerate(test.cameras):
        t = float(test.times[i])
        a = render_dynamic_field(exact, cam.intrinsics, cam.world_to_camera, test.height, test.width, t)
        b = render_baked_dynamic(baked, cam.intrinsics, cam.world_to_camera, test.height, test.width, t)
        truth = display_encode(test.images[i])
        views.append({"time": t, "exact": float(psnr(display_encode(a["color"]), truth)),
                      "baked": float(psnr(display_encode(b["color"]), truth)),
                      "baked_vs_exact": float(psnr(display_encode(a["color"]), display_encode(b["color"]))),
                      "evaluations": [float(a["evaluations"].mean()), float(b["evaluations"].mean())]})
        print(views[-1], flush=True)
    result = {"run": run, "resolution": resolution, "motion_resolution": motion_resolution,
              "bake_seconds": seconds, "bricks": manifest["grid"]["count"],
              "occupied_fraction": manifest["grid"]["occupied_fraction"], "npz_bytes": npz_bytes,
              "motion_bytes": int(arrays["motion"].nbytes), "views": views,
              "mean": {k: float(np.mean([v[k] for v in views])) for k in ("exact", "baked", "baked_vs_exact")}}
    print(result["mean"], result["bricks"], npz_bytes, seconds)
    pathlib.Path(out_json).write_text(json.dumps(result, indent=1) + "\n")


def gl(run: str, out_json: str) -> None:
    """The same run and bake (128 cells, 33^3 flow vertices) in the GL renderers: held-out PSNR of the exact
    (``GlDynamicRenderer``) and baked (``GlBakedDynamicRenderer``) renders at the views' size, and the time of a
    512x512 frame of the first held-out view (median of 5 after a warm-up; wall and process CPU time, llvmpipe's
    threads included)."""
    import json
    import time

    from engine.core.colorspace import display_encode
    from engine.eval.metrics import psnr
    from engine.fields.baked import load_baked_dynamic
    from engine.fields.camera_path import scale_intrinsics
    from engine.fields.gldynamic import GlDynamicRenderer
    from engine.fields.glbaked import GlBakedDynamicRenderer
    from models.fields.assets import dynamic_assets, load_assets
    from models.fields.bake import bake_dynamic
    from models.fields.data.select import load_dynamic_run_views
    from models.fields.train_dynamic import load_dynamic_model

    model = load_dynamic_model(run)
    exact = load_assets(*dynamic_assets(model), "dynamic")
    arrays, manifest = bake_dynamic(model, 128, 33)
    with tempfile.TemporaryDirectory() as tmp:
        np.savez(pathlib.Path(tmp) / "baked_dynamic.npz", **arrays)
        (pathlib.Path(tmp) / "baked_dynamic.json").write_text(json.dumps(manifest))
        baked = load_baked_dynamic(tmp)
    _, test = load_dynamic_run_views(run)
    result = {"run": run, "views": []}
    with GlDynamicRenderer(exact, test.width, test.height) as a, GlBakedDynamicRenderer(baked, test.width,
                                                                                       test.height) as b:
        for i, cam in enumerate(test.cameras):
            t, truth = float(test.times[i]), display_encode(test.images[i])
            fa, fb = (r.render(cam.intrinsics, cam.world_to_camera, t) for r in (a, b))
            result["views"].append({"time": t, "exact": float(psnr(display_encode(fa["color"]), truth)),
                                    "baked": float(psnr(display_encode(fb["color"]), truth)),
                                    "baked_vs_exact": float(psnr(display_encode(fa["color"]),
                                                                 display_encode(fb["color"])))})
    result["mean"] = {k: float(np.mean([v[k] for v in result["views"]])) for k in ("exact", "baked", "baked_vs_exact")}
    print(result["mean"], flush=True)
    cam, t = test.cameras[0], float(test.times[0])
    k = scale_intrinsics(cam.intrinsics, test.width, test.height, 512, 512)
    for name, make in (("gl exact", lambda: GlDynamicRenderer(exact, 512, 512)),
                       ("gl baked", lambda: GlBakedDynamicRenderer(baked, 512, 512))):
        with make() as renderer:
            renderer.render(k, cam.world_to_camera, t)
            walls, cpus = [], []
            for _ in range(5):
                w0, c0 = time.perf_counter(), time.process_time()
                renderer.render(k, cam.world_to_camera, t)
                walls.append(time.perf_counter() - w0)
                cpus.append(time.process_time() - c0)
        result[name] = {"wall_ms": 1e3 * float(np.median(walls)), "cpu_ms": 1e3 * float(np.median(cpus))}
        print(name, result[name], flush=True)
    pathlib.Path(out_json).write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    torch.set_num_threads(1)
    {"train": train, "parity": parity, "bake": bake, "gl": gl}[sys.argv[1]](*sys.argv[2:])
