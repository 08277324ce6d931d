"""Beer with 3 training views: one run of the default static field for a scene kind, split and priors.

``python docs/results/2026-11-28-beer-scene-kind.py KIND TRAIN TEST OUT PRIORS`` (from the repository root):
KIND ``forward-facing`` or ``bounded-360`` (``load_llff``'s ``scene_type``), TRAIN / TEST positions among the
capture's 71 photos, PRIORS ``auto`` or a ``--priors`` list; downscale 2 (360x640), 2000 steps, one torch
thread; scored on the held-out views with the GL renderer; writes OUT.json.
"""
import json
import sys
import time

import torch

from models.fields.data.views import load_llff
from models.fields.train_static import FieldTrainConfig, choose_priors, evaluate_field, train_field

torch.set_num_threads(1)
kind, out, priors = sys.argv[1], sys.argv[4], sys.argv[5]
train_idx, test_idx = ([int(x) for x in arg.split(",")] for arg in sys.argv[2:4])
pool = load_llff("../shared/data/llff_beer", downscale=2, scene_type=kind)
train, test = pool.subset(train_idx), pool.subset(test_idx)
config = choose_priors(FieldTrainConfig(downscale=2), len(train), train.scene_type,
                       None if priors == "auto" else priors)
start = time.perf_counter()
run = train_field(train, config, out, progress=False)
scores = evaluate_field(run, test, with_flip=False, renderer="gl")
result = {"kind": kind, "train": train_idx, "test": test_idx, "priors": config.priors_choice, "psnr": scores["psnr"],
          "ssim": scores["ssim"], "seconds": time.perf_counter() - start}
print(json.dumps(result))
with open(out + ".json", "w") as f:
    f.write(json.dumps(result))
