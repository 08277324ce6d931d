"""The figures of 2026-11-29-dynamic-cycles-rig.md beyond `train dynamic`'s own scores (run from the repository root
with the project's Python):

    python docs/results/2026-11-29-dynamic-cycles-rig.py motion RIG/cam2 ...
        the share of moving pixels and the objects' screen motion (px a frame: median, p95, max of |object_flow|
        over the moving pixels of every frame but the last)
    python docs/results/2026-11-29-dynamic-cycles-rig.py noise REFERENCE RIG
        PSNR (sRGB) of frame 0 of cam0, cam2, cam4 of RIG against the same frame of REFERENCE (a `rig` render
        of the same seed with more samples, `--frames 1`)
    python docs/results/2026-11-29-dynamic-cycles-rig.py split RIG IMAGES
        the held-out squared error of one run split into objects / changing background / still background;
        IMAGES is the folder of `interleave eval dynamic RUN --images IMAGES` (render left, truth right)

Each prints one JSON object. Colours are compared display-encoded (sRGB, clipped to [0, 1]), as `eval dynamic`
scores them. The changing background: pixels with object_id 0 whose truth differs from that pixel's temporal
median over the frames where it is background by more than CHANGE (mean over channels): moving shadows, light
bounced off the objects, the pixels at their edges; the still background is the rest.
"""
from __future__ import annotations

import json
import sys
import warnings
from pathlib import Path

import numpy as np
from PIL import Image

from engine.io.importers import frames_from_blender
from engine.io.rgbd import read_sequence

CHANGE = 0.05


def srgb(color: np.ndarray) -> np.ndarray:
    c = np.clip(color, 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)


def motion(camera: str) -> dict:
    seq = read_sequence(camera)
    speeds, shares = [], []
    for i in range(len(seq) - 1):
        frame = seq[i]
        shares.append(float(frame.moving.mean()))
        speeds.append(np.linalg.norm(frame.object_flow[frame.moving], axis=-1))
    a = np.concatenate(speeds)
    return {"moving_pixel_fraction": float(np.mean(shares)), "object_flow_px_median": float(np.median(a)),
            "object_flow_px_p95": float(np.percentile(a, 95)), "object_flow_px_max": float(a.max())}


def noise(reference: str, rig: str) -> dict:
    out = {}
    for cam in ("cam0", "cam2", "cam4"):
        ref = next(iter(frames_from_blender(Path(reference) / cam / "cameras.json").frames))
        noisy = read_sequence(Path(rig) / cam)[0]
        out[cam] = float(10 * np.log10(1 / np.mean((srgb(ref.color) - srgb(noisy.color)) ** 2)))
    return out


def split(rig: str, images: str, camera: str = "cam2") -> dict:
    seq = read_sequence(Path(rig) / camera)
    truth = np.stack([srgb(seq[i].color) for i in range(len(seq))])
    ids = np.stack([seq[i].object_id for i in range(len(seq))])
    background = ids == 0
    with warnings.catch_warnings(), np.errstate(invalid="ignore"):  # never background: NaN median, not "changing"
        warnings.simplefilter("ignore", RuntimeWarning)
        median = np.nanmedian(np.where(background[..., None], truth, np.nan), axis=0)
        changing = background & (np.abs(truth - median[None]).mean(-1) > CHANGE)
    masks = {"objects": ids > 0, "changing_background": changing, "still_background": background & ~changing}
    errors = {name: [] for name in masks}
    psnrs = []
    for path in sorted(Path(images).glob(f"{camera}@*.png"), key=lambda p: int(p.stem.split("@")[1])):
        i = int(path.stem.split("@")[1])
        render = np.asarray(Image.open(path), np.float64)[:, :truth.shape[2]] / 255.0
        error = ((render - truth[i]) ** 2).mean(-1)
        psnrs.append(10 * np.log10(1 / error.mean()))
        for name, mask in masks.items():
            errors[name].append(error[mask[i]])
    pooled = {name: np.concatenate(v) for name, v in errors.items()}
    pixels, total = sum(v.size for v in pooled.values()), sum(v.sum() for v in pooled.values())
    out = {"views": len(psnrs), "psnr_views_mean": float(np.mean(psnrs))}
    for name, v in pooled.items():
        out[name] = {"pixel_share": v.size / pixels, "error_share": float(v.sum() / total),
                     "psnr_pooled": float(10 * np.log10(1 / v.mean())), "sum_squared_error": float(v.sum())}
    return out


def main(argv: list[str]) -> int:
    command, args = argv[0], argv[1:]
    if command == "motion":
        result = {camera: motion(camera) for camera in args}
    elif command == "noise":
        result = noise(*args)
    else:
        result = split(*args)
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
