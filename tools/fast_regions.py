"""Where fast objects cost a warp: each method's squared error split by what the target shows there. A diagnostic.

``python -m tools.fast_regions SEQ_DIR... [--k 2,4] [--methods reproject,mvec,oracle] [--png-dir DIR] [--json FILE]``

For every predicted frame of ``interleave eval``'s protocol (same pairs, vectors and border crop as
``tools.bench_mvec``, display-encoded colour), the squared error summed over disjoint regions of the target:

- ``object``: the target's moving pixels (its ``moving`` channel): what a method must move there;
- ``revealed_seen``: background the target shows where frame n, seen from the target camera (a camera-only
  warp of its ``moving`` mask), had the object, and where frame n-k did not have it (frame n-k saw it);
- ``revealed_hidden``: the same, but frame n-k had the object there too (no rendered frame saw it);
- ``near``: the rest within ``--near`` px of the three;
- ``far``: everything else.

The sums are means over frames of 1e3 x the summed squared error / the cropped pixel count, so the regions add
up to the frame's MSE x 1e3. Also printed per method: the share of each region the warp left as holes. With
``--png-dir``, the first target of each sequence and k is written as one strip: truth | each method (sRGB).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from engine import geometry
from engine.core.colorspace import display_encode
from engine.eval.metrics import crop_slices
from engine.eval.protocol import evaluation_pairs, make_predictors, rendered_history
from engine.io.rgbd import read_sequence
from engine.predict import Mvec, Target, split_methods
from tools.heldout import write_json

REGIONS = ("object", "revealed_seen", "revealed_hidden", "near", "far")


def seen_from(frame, mask: np.ndarray, camera) -> np.ndarray:
    """``mask`` (H, W) bool of ``frame`` forward-warped camera-only to ``camera``: where the target camera sees
    the frame's masked surface (holes: False)."""
    values = np.repeat(mask.astype(np.float32)[..., None], 3, axis=-1)
    out, _, holes = geometry.forward_warp_frame(values, frame.depth, frame.camera.intrinsics,
                                                frame.camera.world_to_camera, camera.intrinsics,
                                                camera.world_to_camera)
    return (out[..., 0] > 0.5) & ~holes


def region_masks(older, newest, truth, near: int) -> dict[str, np.ndarray]:
    """The disjoint regions (module docstring) of ``truth``'s frame, (H, W) bool each."""
    obj = truth.moving
    was_n = seen_from(newest, newest.moving, truth.camera)
    was_older = seen_from(older, older.moving, truth.camera)
    revealed = was_n & ~obj
    seen, hidden = revealed & ~was_older, revealed & was_older
    grown = cv2.dilate((obj | revealed).astype(np.uint8), np.ones((2 * near + 1,) * 2, np.uint8)) > 0
    close = grown & ~obj & ~revealed
    return {"object": obj, "revealed_seen": seen, "revealed_hidden": hidden, "near": close,
            "far": ~(obj | revealed | close)}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sequences", nargs="+", type=Path)
    parser.add_argument("--k", default="2,4")
    parser.add_argument("--methods", default="reproject,mvec,oracle")
    parser.add_argument("--near", type=int, default=20, help="px around the object and revealed pixels: 'near'")
    parser.add_argument("--png-dir", type=Path, default=None)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    methods = split_methods(args.methods)
    if "reproject" not in methods:
        methods.insert(0, "reproject")
    rows = []
    for path in args.sequences:
        seq = read_sequence(path)
        name = path.name.split("_")[0]
        for k in (int(v) for v in args.k.split(",")):
            predictors = make_predictors(methods, seq.objects, has_vectors=seq.has_channel("motion_vectors"),
                                         backend="cpu", file=path)
            with_vectors = any(isinstance(p, Mvec) for p in predictors.values())
            three = any(p.history_wanted >= 3 for p in predictors.values())
            sums = {m: {r: [] for r in REGIONS} for m in methods}
            holes = {m: {r: [] for r in REGIONS} for m in methods}
            sizes = {r: [] for r in REGIONS}
            strip = None
            for older, newest, targets in evaluation_pairs(len(seq), k):
                history = rendered_history(seq, older, newest, with_vectors=with_vectors, three=three)
                states = {m: p.prepare(history) for m, p in predictors.items()}
                for t in targets:
                    truth = seq[t]
                    crop = crop_slices(*truth.depth.shape)
                    masks = {r: v[crop] for r, v in region_masks(history[-2], history[-1], truth, args.near).items()}
                    reference = display_encode(truth.color)[crop]
                    pictures = [reference]
                    for m, predictor in predictors.items():
                        out = predictor.render(states[m], Target(truth.camera, truth.time, truth.index))
                        shown = display_encode(out.color)[crop]
                        pictures.append(shown)
                        error = ((shown - reference) ** 2).mean(axis=-1)
                        for r in REGIONS:
                            sums[m][r].append(1e3 * float(error[masks[r]].sum()) / error.size)
                            holes[m][r].append(float(out.holes[crop][masks[r]].sum()))
                    for r in REGIONS:
                        sizes[r].append(float(masks[r].sum()))
                    if strip is None:
                        strip = np.concatenate(pictures, axis=1)
            if args.png_dir is not None and strip is not None:
                args.png_dir.mkdir(parents=True, exist_ok=True)
                image = (np.clip(strip, 0, 1) * 255 + 0.5).astype(np.uint8)[..., ::-1]
                cv2.imwrite(str(args.png_dir / f"{name}_k{k}.png"), image)
            share = {r: float(np.sum(sizes[r])) for r in REGIONS}
            print(f"\n{name} k={k}: region sizes (mean px) " + ", ".join(
                f"{r} {np.mean(sizes[r]):.0f}" for r in REGIONS))
            print("| method | " + " | ".join(REGIONS) + " | total |\n|---|" + "---|" * (len(REGIONS) + 1))
            base = {r: float(np.mean(sums["reproject"][r])) for r in REGIONS}
            for m in methods:
                mean = {r: float(np.mean(sums[m][r])) for r in REGIONS}
                hole_share = {r: float(np.sum(holes[m][r])) / share[r] if share[r] else 0.0 for r in REGIONS}
                rows.append({"sequence": name, "k": k, "method": m, "error": mean, "hole_share": hole_share,
                             "region_px": {r: float(np.mean(sizes[r])) for r in REGIONS}})
                cells = [f"{mean[r]:.2f} ({mean[r] - base[r]:+.2f}, holes {100 * hole_share[r]:.0f}%)"
                         for r in REGIONS]
                total = sum(mean.values())
                print(f"| {m} | " + " | ".join(cells) + f" | {total:.2f} ({total - sum(base.values()):+.2f}) |")
    write_json(args.json, {"sequences": [p.name for p in args.sequences], "near": args.near, "rows": rows})


if __name__ == "__main__":
    main()
