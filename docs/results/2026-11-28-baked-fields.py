"""Held-out scores of a deferred field's exact and baked renders (issue 44, item 1; results page
2026-11-28-baked-fields.md). For each RUN (trained with --field.shading deferred, exported with
`interleave export field RUN`): every held-out view rendered by the exact GL renderer and by the baked GL
renderer (both filtering="exact", the numpy references' arithmetic), PSNR of each against the photo and of
the baked render against the exact one, display-encoded as `interleave eval field` scores.

    PYTHONPATH=. python docs/results/2026-11-28-baked-fields.py OUT.json RUN [RUN ...]
    PYTHONPATH=. python docs/results/2026-11-28-baked-fields.py --background RUN [RUN ...]

``--background``: the torch render's squared error (linear RGB) on the photos' white background pixels and on
the rest, and the mean opacity on the background, over every 5th held-out view (where a field's fog shows).
"""
import json
import sys
from pathlib import Path

import numpy as np

from engine.core.colorspace import display_encode
from engine.eval.metrics import psnr
from engine.fields.baked import load_baked
from engine.fields.gl import GlFieldRenderer
from engine.fields.glbaked import GlBakedRenderer
from engine.fields.render import load_field
from models.fields.data.select import load_run_views


def scores(run: Path) -> dict:
    export = run / "export"
    _, test = load_run_views(run)
    exact_assets, baked = load_field(export), load_baked(export)
    exact_p, baked_p, between = [], [], []
    with GlFieldRenderer(exact_assets, test.width, test.height, filtering="exact") as ge, \
            GlBakedRenderer(baked, test.width, test.height, filtering="exact") as gb:
        for cam, image in zip(test.cameras, test.images):
            e = display_encode(ge.render(cam.intrinsics, cam.world_to_camera)["color"])
            b = display_encode(gb.render(cam.intrinsics, cam.world_to_camera)["color"])
            truth = display_encode(image)
            exact_p.append(psnr(truth, e))
            baked_p.append(psnr(truth, b))
            between.append(psnr(e, b))
    manifest = json.loads((export / "baked.json").read_text())
    return {"run": str(run), "views": len(exact_p), "size": [test.height, test.width],
            "psnr_exact": float(np.mean(exact_p)), "psnr_baked": float(np.mean(baked_p)),
            "psnr_baked_vs_exact_mean": float(np.mean(between)), "psnr_baked_vs_exact_min": float(np.min(between)),
            "grid": manifest["grid"], "baked_npz_bytes": (export / "baked.npz").stat().st_size,
            "field_npz_bytes": (export / "field.npz").stat().st_size}


def background(run: str) -> dict:
    import torch

    from models.fields.components.render import render_image
    from models.fields.train_static import load_model

    torch.set_num_threads(1)
    model = load_model(run)
    _, test = load_run_views(run)
    bg_err, fg_err, opacity = [], [], []
    for i in range(0, len(test.cameras), 5):
        cam, truth = test.cameras[i], test.images[i]
        out = render_image(model, cam.intrinsics, cam.world_to_camera, test.height, test.width, model.scene.near,
                           model.scene.far)
        white = (truth > 0.99).all(-1)
        err = ((out["color"] - truth) ** 2).mean(-1)
        bg_err.append(err[white].mean())
        fg_err.append(err[~white].mean())
        opacity.append(out["opacity"][white].mean())
    return {"run": run, "background_mse": float(np.mean(bg_err)), "object_mse": float(np.mean(fg_err)),
            "background_opacity": float(np.mean(opacity))}


if __name__ == "__main__":
    if sys.argv[1] == "--background":
        print(json.dumps([background(r) for r in sys.argv[2:]], indent=2))
        sys.exit(0)
    out = [scores(Path(r)) for r in sys.argv[2:]]
    Path(sys.argv[1]).write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out, indent=2))
