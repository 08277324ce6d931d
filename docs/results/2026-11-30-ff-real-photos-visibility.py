"""Where a forward-facing rig run's error lies (docs/results/2026-11-30-ff-real-photos.md).

    PYTHONPATH=. python docs/results/2026-11-30-ff-real-photos-visibility.py RUN RIG OUT.json

RUN is an ``interleave train field`` run on the generated rig RIG (``render-rig ... --static``). Every held-out
and training view is rendered by the GL renderer. Each pixel is put in a group by how many training views see
its true surface point: the point (the pixel centre unprojected at the rig's planar depth) projects inside the
training view, in front of it, and lands within 2 % of that view's own true depth there. Pixels with no surface
(infinite depth: sky) are a group of their own (-1). Per group: the share of pixels, the PSNR of the display-
encoded colour (as ``eval field`` scores), its share of the view's squared error, and the median relative depth
error of the render (finite depths only).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from engine.core.colorspace import display_encode
from engine.geometry.camera import reproject
from engine.io.rgbd import read_sequence
from models.fields.data.select import load_run_views
from models.fields.train_static import load_model, evaluate_field

#: A training view sees a point when its own depth there is within this fraction of the point's depth.
DEPTH_TOLERANCE = 0.02


def seen_by(frame, train_frames) -> np.ndarray:
    """(H, W) int: how many of ``train_frames`` see each pixel's true surface point; -1 where there is none."""
    h, w = frame.depth.shape
    finite = np.isfinite(frame.depth)
    count = np.zeros((h, w), int)
    for other in train_frames:
        uv, z, valid = reproject(frame.depth, frame.camera.intrinsics, frame.camera.world_to_camera,
                                 other.camera.intrinsics, other.camera.world_to_camera)
        x, y = uv[..., 0], uv[..., 1]
        inside = finite & valid & (x >= 0) & (x < w) & (y >= 0) & (y < h)
        there = other.depth[np.clip(y, 0, h - 1).astype(int), np.clip(x, 0, w - 1).astype(int)]
        count += inside & (np.abs(there - z) < DEPTH_TOLERANCE * z)
    return np.where(finite, count, -1)


def main(argv: list[str]) -> int:
    run, rig, out = Path(argv[0]), Path(argv[1]), Path(argv[2])
    train_views, test_views = load_run_views(run)
    frames = {name: read_sequence(rig / name)[0] for name in train_views.names + test_views.names}
    train_frames = [frames[name] for name in train_views.names]
    model = load_model(run)
    result = {"run": str(run), "rig": str(rig), "depth_tolerance": DEPTH_TOLERANCE, "views": {}}
    for split, views in (("held-out", test_views), ("training", train_views)):
        scores = evaluate_field(model, views, with_flip=False, return_images=True, renderer="gl")
        print(f"{split}: PSNR {scores['psnr']:.2f}")
        for name, image in zip(views.names, scores["images"]):
            frame = frames[name]
            groups = seen_by(frame, train_frames)
            error = ((display_encode(image["color"]) - display_encode(frame.color)) ** 2).mean(-1)
            rows = {}
            for k in range(-1, len(train_frames) + 1):
                mask = groups == k
                if not mask.any():
                    continue
                finite = mask & np.isfinite(frame.depth) & np.isfinite(image["depth"])
                rel = (float(np.median(np.abs(image["depth"][finite] - frame.depth[finite]) / frame.depth[finite]))
                       if finite.any() else None)
                rows[str(k)] = {"pixels": float(mask.mean()), "psnr": float(-10 * np.log10(error[mask].mean())),
                                "error_share": float(error[mask].sum() / error.sum()), "depth_rel_median": rel,
                                "rendered_depth_median": float(np.median(image["depth"][mask]))}
                row = rows[str(k)]
                print(f"  {name} seen by {k:2d}: {100 * mask.mean():5.1f} % of pixels, PSNR {row['psnr']:6.2f}, "
                      f"{100 * row['error_share']:5.1f} % of the error, "
                      f"depth off {rel if rel is None else round(rel, 3)}, "
                      f"rendered depth {row['rendered_depth_median']:.2f}")
            result["views"][name] = {"split": split, "psnr": float(-10 * np.log10(error.mean())), "groups": rows}
    out.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
