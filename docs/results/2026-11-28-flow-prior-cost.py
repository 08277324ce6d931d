"""The sparse flow prior's cost, stage by stage, with the numpy matcher against pycolmap's on the same pairs.

``python docs/results/2026-11-28-flow-prior-cost.py RIG_DIR OUT.json`` (from the repository root): loads the
rig's training views as ``interleave train dynamic`` does (its default downscale), takes the frame pairs of the
default prior, and times SIFT extraction (``sift_features``, no cache), the matching of every pair with
``match_descriptors`` and with ``pycolmap.FeatureMatcher`` (cross check, the same options as before), the
number of matches each finds and how many are common, and the verification of the numpy matches.
"""
import json
import sys
import time

import numpy as np
import pycolmap

from engine.core.colorspace import display_encode
from models.fields.data.select import select_dynamic_views
from models.fields.priors.depth import _extractor, match_descriptors, sift_features
from models.fields.priors.flow import SparseFlowPrior, flow_pairs, verify_matches
from models.fields.train_dynamic import DynamicTrainConfig


def main(rig: str, out: str) -> None:
    train, _, _ = select_dynamic_views("rig", rig, DynamicTrainConfig().downscale)
    prior = SparseFlowPrior(enabled=True)
    pairs = flow_pairs(train.times, prior)
    start = time.perf_counter()
    feats = sift_features(train.images, prior.max_features)
    features_s = time.perf_counter() - start
    start = time.perf_counter()
    ours = [match_descriptors(feats[a][1], feats[b][1], prior.ratio) for a, b in pairs]
    numpy_s = time.perf_counter() - start
    options = pycolmap.FeatureMatchingOptions()
    options.num_threads = 1
    options.sift.max_ratio, options.sift.cross_check = prior.ratio, True
    matcher = pycolmap.FeatureMatcher.create(options, pycolmap.Device.cpu)
    extractor = _extractor(prior.max_features)
    start = time.perf_counter()
    colmap = [extractor.extract_from_float32_array(np.ascontiguousarray(
        np.clip(display_encode(image).mean(-1), 0, 1).astype(np.float32))) for image in train.images]
    features_again_s = time.perf_counter() - start
    start = time.perf_counter()
    theirs = [np.asarray(matcher.match(colmap[a][0], colmap[a][1], colmap[b][0], colmap[b][1]),
                         np.int64).reshape(-1, 2) for a, b in pairs]
    pycolmap_s = time.perf_counter() - start
    common = sum(len(set(map(tuple, x.tolist())) & set(map(tuple, y.tolist()))) for x, y in zip(ours, theirs))
    start = time.perf_counter()
    kept = [int(verify_matches(train, a, b, feats[a][0][i[:, 0]].reshape(-1, 2), feats[b][0][i[:, 1]].reshape(-1, 2),
                               prior).sum()) for (a, b), i in zip(pairs, ours)]
    verify_s = time.perf_counter() - start
    result = {"command": " ".join(sys.argv), "views": len(train), "size": [train.width, train.height],
              "pairs": len(pairs), "features_s": features_s, "features_again_s": features_again_s,
              "match_numpy_s": numpy_s, "match_pycolmap_s": pycolmap_s, "matches_numpy": int(sum(map(len, ours))),
              "matches_pycolmap": int(sum(map(len, theirs))), "common": int(common), "verify_s": verify_s,
              "kept": int(sum(kept))}
    print(json.dumps(result, indent=1))
    with open(out, "w") as f:
        json.dump(result, f, indent=1)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
