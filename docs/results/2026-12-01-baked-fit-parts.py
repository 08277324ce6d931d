"""Where a static bake's error against the exact render comes from (the first table of 2026-12-01-baked-fit.md):
on each held-out view, PSNR against the exact render of the same field (numpy renderers) of the baked march
reading the exact field, exact density with the vertex-sampled bake's features and the reverse, the vertex-sampled
bake with uint8 and float features, and the least-squares fit on the vertices and cell centres (the bake now) and
on the whole half-step lattice.

    PYTHONPATH=. python docs/results/2026-12-01-baked-fit-parts.py RUN EXPORT OUT.json

RUN / EXPORT as ``2026-12-01-baked-fit.py``.
"""
import json
import sys

import numpy as np
import torch

from engine.core.colorspace import display_encode
from engine.eval.metrics import psnr
from engine.fields.baked import BakedAssets, load_baked, lookup_bricks, render_baked
from engine.fields.render import load_field, march_field, pixel_shader, render_field
from models.fields.bake import _occupied_bricks, _raw_outputs, fit_bricks, fit_points
from models.fields.data.select import load_run_views
from models.fields.static.field import MAX_LOG_DENSITY
from models.fields.train_static import load_model

torch.set_num_threads(1)


def vertices(brick: int) -> torch.Tensor:
    return fit_points(brick)[:(brick + 1) ** 3]


def half_lattice(brick: int) -> torch.Tensor:
    h = torch.arange(2 * brick + 1, dtype=torch.float64) / 2.0
    return torch.stack(torch.meshgrid(h, h, h, indexing="ij"), dim=-1).reshape(-1, 3)


def rebake(model, like: BakedAssets, points, float_features: bool = False) -> BakedAssets:
    """``model``'s bake on ``like``'s grid, fitted at ``points(brick)`` (``vertices``: sampled)."""
    resolution, brick = like.grid["resolution"], like.grid["brick"]
    occupied, bricks, _ = _occupied_bricks(model, model.field, resolution, 1 << 16)
    cells = occupied.nonzero()
    raws, feats = [], []
    for raw, feat in fit_bricks(model.field, cells, brick, resolution, local=points(brick)):
        raws.append(raw.numpy().astype(np.float16).astype(np.float32))
        feats.append(feat.numpy() * 255.0 if float_features else np.rint(feat.numpy() * 255.0).astype(np.uint8))
    index = np.full((bricks,) * 3, -1, np.int32)
    index[tuple(cells.numpy().T)] = np.arange(cells.shape[0], dtype=np.int32)
    return BakedAssets(like.manifest, np.concatenate(raws), np.concatenate(feats), index, like.color_layers)


def main(run, export, out):
    model = load_model(run)
    exact_assets, like = load_field(export), load_baked(export)
    sampled = rebake(model, like, vertices)
    field = model.field

    @torch.no_grad()
    def exact(coords):
        raw, feat = _raw_outputs(field, torch.from_numpy(np.asarray(coords, np.float32)), 1 << 16)
        return np.exp(np.minimum(raw.numpy(), MAX_LOG_DENSITY)), feat.numpy()

    def hybrid(density_from, features_from):
        def query(points, coords, directions):
            sigma, feats, _ = lookup_bricks(sampled, coords)
            sigma_e, feats_e = exact(coords)
            return (sigma_e if density_from == "exact" else sigma), (feats_e if features_from == "exact" else feats)
        return lambda k, w2c, h, w: march_field(sampled, k, w2c, h, w, query, shade=pixel_shader(sampled),
                                                channels=sampled.feature_dim)

    def baked(assets):
        return lambda k, w2c, h, w: render_baked(assets, k, w2c, h, w)

    variants = {"the exact field (the bake's march, bricks and early termination)": hybrid("exact", "exact"),
                "exact density, baked features": hybrid("exact", "baked"),
                "baked density, exact features": hybrid("baked", "exact"),
                "the bake (vertex samples)": baked(sampled),
                "the bake with float features": baked(rebake(model, like, vertices, float_features=True)),
                "fitted at vertices and cell centres (the bake now)": baked(rebake(model, like, fit_points)),
                "fitted on the whole half-step lattice": baked(rebake(model, like, half_lattice))}
    _, test = load_run_views(run)
    rows = {}
    for name, cam in zip(test.names, test.cameras):
        k, w2c, h, w = cam.intrinsics, cam.world_to_camera, test.height, test.width
        ref = display_encode(render_field(exact_assets, k, w2c, h, w)["color"])
        rows[name] = {label: float(psnr(ref, display_encode(render(k, w2c, h, w)["color"])))
                      for label, render in variants.items()}
        print(name, json.dumps(rows[name]), flush=True)
    json.dump({"run": str(run), "export": str(export), "grid": like.grid, "psnr_vs_exact": rows},
              open(out, "w"), indent=1)


if __name__ == "__main__":
    main(*sys.argv[1:4])
