"""Where a method's error lies: its squared error split by region, beside the others', on the evaluation's
frames. A diagnostic.

``python -m tools.error_regions SEQ_DIR... [--k 2] [--methods reproject,flow2d,oracle] [--near 20] [--json FILE]``

For every predicted frame of ``interleave eval``'s protocol (same pairs, same border crop, display-encoded
colour), the squared error summed over four disjoint regions of the target frame:

- ``moving``: the target's moving pixels (its ``moving`` channel);
- ``vacated``: frame n's moving pixels that no longer move at the target (where an object was: what it
  uncovered, or the object itself when it stayed);
- ``near``: the rest within ``--near`` px of either (disocclusions, and motion a flow spread around an object);
- ``far``: everything else: static surfaces away from any moving object, where object motion has no business.

Printed per method: the sums (means over frames, x 1e3 of the mean squared error per cropped pixel, so the
four add up to the frame's MSE x 1e3) and the difference to ``reproject``'s. A method whose extra error is
``far`` moves static surfaces; one whose gain is ``moving`` follows the objects.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from engine.core.colorspace import display_encode
from engine.eval.metrics import crop_slices
from engine.eval.protocol import evaluation_pairs, rendered_history
from engine.io.rgbd import read_sequence
from engine.predict import Target, make_predictor, split_methods
from tools.heldout import write_json

REGIONS = ("moving", "vacated", "near", "far")


def region_masks(moving_n: np.ndarray, moving_target: np.ndarray, near: int) -> dict[str, np.ndarray]:
    """The four disjoint regions (module docstring) of a target frame, (H, W) bool each."""
    vacated = moving_n & ~moving_target
    grown = cv2.dilate((moving_n | moving_target).astype(np.uint8), np.ones((2 * near + 1,) * 2, np.uint8)) > 0
    close = grown & ~moving_target & ~vacated
    return {"moving": moving_target, "vacated": vacated, "near": close, "far": ~(moving_target | vacated | close)}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sequences", nargs="+", type=Path)
    parser.add_argument("--k", type=int, default=2)
    parser.add_argument("--methods", default="reproject,flow2d,oracle")
    parser.add_argument("--near", type=int, default=20, help="px around moving pixels counted as 'near'")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    methods = split_methods(args.methods)
    if "reproject" not in methods:
        methods.insert(0, "reproject")
    sums = {m: {r: [] for r in REGIONS} for m in methods}
    for path in args.sequences:
        seq = read_sequence(path)
        predictors = {m: make_predictor(m, seq.objects, backend="cpu") for m in methods}
        wants_three = any(p.history_wanted >= 3 for p in predictors.values())
        for older, newest, targets in evaluation_pairs(len(seq), args.k):
            history = rendered_history(seq, older, newest, with_vectors=False, three=wants_three)
            states = {m: p.prepare(history) for m, p in predictors.items()}
            for t in targets:
                truth = seq[t]
                rows, cols = crop_slices(*truth.depth.shape)
                masks = {r: m[rows, cols] for r, m in region_masks(history[-1].moving, truth.moving,
                                                                     args.near).items()}
                reference = display_encode(truth.color)[rows, cols]
                for m, predictor in predictors.items():
                    out = predictor.render(states[m], Target(truth.camera, truth.time, truth.index))
                    error = ((display_encode(out.color)[rows, cols] - reference) ** 2).mean(axis=-1)
                    for r in REGIONS:
                        sums[m][r].append(1e3 * float(error[masks[r]].sum()) / error.size)
    rows_out = []
    base = {r: float(np.mean(sums["reproject"][r])) for r in REGIONS}
    print("| method | " + " | ".join(REGIONS) + " | total |\n|---|" + "---|" * (len(REGIONS) + 1))
    for m in methods:
        mean = {r: float(np.mean(sums[m][r])) for r in REGIONS}
        rows_out.append({"method": m, **mean})
        cells = [f"{mean[r]:.3f} ({mean[r] - base[r]:+.3f})" for r in REGIONS]
        total = sum(mean.values())
        print(f"| {m} | " + " | ".join(cells) + f" | {total:.3f} ({total - sum(base.values()):+.3f}) |")
    write_json(args.json, {"sequences": [p.name for p in args.sequences], "k": args.k, "near": args.near,
                           "rows": rows_out})


if __name__ == "__main__":
    main()
