"""The distortion loss in the baking recipe (docs/results/2026-11-30-baked-distortion.md): for each trained static
run and its export, the baked GL renderer's milliseconds a frame on every held-out view (medians over alternating
rounds), the samples it evaluates per pixel, its PSNR against the exact GL render of the same field, and the
held-out PSNR of both renders against the photos (display-encoded).

    PYTHONPATH=. python docs/results/2026-11-30-baked-distortion.py OUT.json WIDTHxHEIGHT RUN[:EXPORT] ...

EXPORT defaults to RUN/export (``interleave export field RUN``). Frames are timed from dispatch to finish, without
readback, at WIDTHxHEIGHT; the held-out scores are at the run's own test size. Every run must hold the same
held-out views (the first run's are used).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from engine.core.colorspace import display_encode
from engine.eval.metrics import psnr
from engine.fields.baked import load_baked
from engine.fields.camera_path import scale_intrinsics
from engine.fields.gl import GlFieldRenderer
from engine.fields.glbaked import GlBakedRenderer
from engine.fields.render import load_field
from models.fields.data.select import load_run_views

ROUNDS, FRAMES = 5, 4


def _score(baked, exact, test, width: int, height: int) -> list[dict]:
    """Per held-out view: evaluations per pixel and PSNR against the exact render at ``width`` x ``height``; the
    held-out PSNR of the baked and the exact render at the test size."""
    renderers = [GlBakedRenderer(baked, width, height, count_evaluations=True), GlFieldRenderer(exact, width, height),
                 GlBakedRenderer(baked, test.width, test.height), GlFieldRenderer(exact, test.width, test.height)]
    count, exact_big, baked_test, exact_test = renderers
    rows = []
    for view, cam in enumerate(test.cameras):
        k = scale_intrinsics(cam.intrinsics, test.width, test.height, width, height)
        b, e = count.render(k, cam.world_to_camera), exact_big.render(k, cam.world_to_camera)
        truth = display_encode(test.images[view])
        rows.append({
            "view": view, "evaluations_per_pixel": float(b["evaluations"].mean()),
            "psnr_baked_vs_exact": float(psnr(display_encode(e["color"]), display_encode(b["color"]))),
            "heldout_psnr_baked": float(psnr(truth, display_encode(
                baked_test.render(cam.intrinsics, cam.world_to_camera)["color"]))),
            "heldout_psnr_exact": float(psnr(truth, display_encode(
                exact_test.render(cam.intrinsics, cam.world_to_camera)["color"]))),
            "ms": []})
    for r in renderers:
        r.release()
    return rows


def _time(renderers: dict, rows: dict, test, width: int, height: int) -> None:
    """Append each view's frame times to ``rows``; the runs alternate within every round and view."""
    for _ in range(ROUNDS):
        for view, cam in enumerate(test.cameras):
            k = scale_intrinsics(cam.intrinsics, test.width, test.height, width, height)
            for name, r in renderers.items():
                r.render(k, cam.world_to_camera)  # a full render first, as every round has
                rows[name][view]["ms"] += [1e3 * t for t in r.dispatch_seconds(k, cam.world_to_camera, FRAMES)]


def main(argv: list[str]) -> int:
    out_path, size, specs = Path(argv[0]), argv[1], argv[2:]
    width, height = (int(x) for x in size.split("x"))
    runs = {}
    for spec in specs:
        run, _, export = spec.partition(":")
        runs[Path(run).name] = (Path(run), Path(export) if export else Path(run) / "export")
    _, test = load_run_views(next(iter(runs.values()))[0])
    baked = {name: load_baked(export) for name, (_, export) in runs.items()}
    rows = {name: _score(baked[name], load_field(export), test, width, height) for name, (_, export) in runs.items()}
    renderers = {name: GlBakedRenderer(baked[name], width, height) for name in runs}
    _time(renderers, rows, test, width, height)
    for r in renderers.values():
        r.release()
    result = {"size": [width, height], "rounds": ROUNDS, "frames": FRAMES, "runs": {}}
    for name, (run, export) in runs.items():
        for row in rows[name]:
            row["ms"] = float(np.median(row.pop("ms")))
        scores = json.loads((run / "scores.json").read_text())
        summary = {
            "median_ms": float(np.median([r["ms"] for r in rows[name]])),
            "slowest_view_ms": max(r["ms"] for r in rows[name]),
            "evaluations_per_pixel": float(np.mean([r["evaluations_per_pixel"] for r in rows[name]])),
            "worst_psnr_baked_vs_exact": min(r["psnr_baked_vs_exact"] for r in rows[name]),
            "heldout_psnr_baked": float(np.mean([r["heldout_psnr_baked"] for r in rows[name]])),
            "heldout_psnr_exact": float(np.mean([r["heldout_psnr_exact"] for r in rows[name]])),
            "run_psnr": scores["psnr"], "run_ssim": scores["ssim"], "train_seconds": scores["train_seconds"]}
        result["runs"][name] = {"summary": summary, "views": rows[name]}
        print(name, json.dumps(summary), flush=True)
    out_path.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
