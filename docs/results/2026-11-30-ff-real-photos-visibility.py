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
from engine.io.rgbd import read_sequence
from models.fields.data.select import load_run_views
from models.fields.train_static import load_model, evaluate_field

#: A training view sees a point when its own depth there is within this fraction of the point's depth.
DEPTH_TOLERANCE = 0.02


def seen_by(frame, train_frames) -> np.ndarray:
    """(H, W) int: how many of ``train_frames`` see each pixel's true surface point; -1 where there is none."""
    h, w = frame.depth.shape
    v, u = np.mgrid[0:h, 0:w]
    pixels = np.stack([u + 0.5, v + 0.5, np.ones((h, w))], -1).reshape(-1, 3)
    z = frame.depth.reshape(-1).astype(np.float64)
    finite = np.isfinite(z)
    c2w = frame.camera.camera_to_world
    points = (pixels @ np.linalg.inv(frame.camera.intrinsics).T) * np.where(finite, z, 1.0)[:, None]
    points = points @ c2w[:3, :3].T + c2w[:3, 3]
    count = np.zeros(h * w, int)
    for other in train_frames:
        w2c = other.camera.world_to_camera
        q = points @ w2c[:3, :3].T + w2c[:3, 3]
        uv = q @ other.camera.intrinsics.T
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = uv[:, 0] / q[:, 2], uv[:, 1] / q[:, 2]
        inside = finite & (q[:, 2] > 0) & (x >= 0) & (x < w) & (y >= 0) & (y < h)
        row = np.clip(np.nan_to_num(y), 0, h - 1).astype(int)
        column = np.clip(np.nan_to_num(x), 0, w - 1).astype(int)
        there = other.depth[row, column]
        count += inside & (np.abs(there - q[:, 2]) < DEPTH_TOLERANCE * q[:, 2])
    return np.where(finite, count, -1).reshape(h, w)


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
