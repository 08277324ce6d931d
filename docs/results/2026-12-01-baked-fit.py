"""Baked static fields: the vertex values fitted by least squares (``models.fields.bake.fit_matrix``, the bake now)
against the field sampled at the vertices (the bake before), on every held-out view of a run, numpy renderers:
PSNR of each baked render against the exact render of the same field and against the held-out photo, and the
samples a pixel each evaluates (up to its early termination).

    PYTHONPATH=. python docs/results/2026-12-01-baked-fit.py RUN EXPORT OUT.json

RUN: a run of ``interleave train field --field.shading deferred`` (or ``--config configs/field-baked.json``);
EXPORT: its ``interleave export field`` folder (the exact assets, and the fitted bake at the export's resolution).
"""
import json
import sys
import time

import numpy as np
import torch

from engine.core.colorspace import display_encode
from engine.eval.metrics import psnr
from engine.fields.baked import BakedAssets, load_baked, render_baked
from engine.fields.render import load_field, render_field
from models.fields.bake import _occupied_bricks, bake_static, fit_bricks, fit_points
from models.fields.data.select import load_run_views
from models.fields.train_static import load_model

torch.set_num_threads(1)


def vertex_sampled(model, fitted: BakedAssets) -> tuple[BakedAssets, float]:
    """The bake before the fit (6c62d59's ``_bake_bricks``): the field's values at the vertices of the same bricks
    (:func:`fit_bricks` with the vertices alone as fit points: the identity)."""
    t0 = time.process_time()
    resolution, brick = fitted.grid["resolution"], fitted.grid["brick"]
    occupied, _, _ = _occupied_bricks(model, model.field, resolution, 1 << 16)
    cells = occupied.nonzero()
    raws, feats = [], []
    for raw, feat in fit_bricks(model.field, cells, brick, resolution, local=fit_points(brick)[:(brick + 1) ** 3]):
        raws.append(raw.numpy().astype(np.float16).astype(np.float32))
        feats.append(np.rint(feat.numpy() * 255.0).astype(np.uint8))
    index = np.full(fitted.brick_index.shape, -1, np.int32)
    index[tuple(cells.numpy().T)] = np.arange(cells.shape[0], dtype=np.int32)
    assert np.array_equal(index >= 0, fitted.brick_index >= 0)
    baked = BakedAssets(fitted.manifest, np.concatenate(raws), np.concatenate(feats), index, fitted.color_layers)
    return baked, time.process_time() - t0


def main(run, export, out):
    model = load_model(run)
    exact, fitted = load_field(export), load_baked(export)
    sampled, sample_seconds = vertex_sampled(model, fitted)
    t0 = time.process_time()
    bake_static(model, fitted.grid["resolution"])  # the fit, timed as the export runs it
    fit_seconds = time.process_time() - t0
    _, test = load_run_views(run)
    views = []
    for name, cam, photo in zip(test.names, test.cameras, test.images):
        k, w2c, h, w = cam.intrinsics, cam.world_to_camera, test.height, test.width
        truth = display_encode(photo)
        ref = render_field(exact, k, w2c, h, w)
        row = {"view": name, "exact_vs_photo": float(psnr(truth, display_encode(ref["color"])))}
        for label, baked in (("vertex_samples", sampled), ("fit", fitted)):
            img = render_baked(baked, k, w2c, h, w)
            row[f"{label}_vs_exact"] = float(psnr(display_encode(ref["color"]), display_encode(img["color"])))
            row[f"{label}_vs_photo"] = float(psnr(truth, display_encode(img["color"])))
            row[f"{label}_evaluations"] = float(img["evaluations"].mean())  # samples a pixel the GL renderer runs
        views.append(row)
        print(json.dumps(row), flush=True)
    keys = [k for k in views[0] if k != "view"]
    summary = {k: {"mean": float(np.mean([v[k] for v in views])), "min": float(np.min([v[k] for v in views]))}
               for k in keys}
    result = {"run": str(run), "export": str(export), "grid": fitted.grid, "check": fitted.manifest.get("check"),
              "bake_cpu_seconds": {"vertex_samples": sample_seconds, "fit": fit_seconds}, "views": views,
              "summary": summary}
    json.dump(result, open(out, "w"), indent=1)
    print(json.dumps(summary))


if __name__ == "__main__":
    main(*sys.argv[1:4])
