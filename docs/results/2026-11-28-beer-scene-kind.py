"""Beer with 3 training views: one run of the default static field for a scene kind, split and priors.

``python docs/results/2026-11-28-beer-scene-kind.py KIND TRAIN TEST OUT PRIORS`` (from the repository root):
KIND ``forward-facing`` or ``bounded-360`` (``load_llff``'s ``scene_type``), TRAIN / TEST positions among the
capture's 71 photos, PRIORS ``auto`` or a ``--priors`` list; downscale 2 (360x640), 2000 steps, one torch
thread; scored on the held-out views with the GL renderer; writes OUT.json.
"""
import sys, json, time
import torch; torch.set_num_threads(1)
from models.fields.data.views import load_llff
from models.fields.train_static import FieldTrainConfig, train_field, evaluate_field, choose_priors
kind, train_idx, test_idx, out, priors = sys.argv[1], [int(x) for x in sys.argv[2].split(",")], [int(x) for x in sys.argv[3].split(",")], sys.argv[4], sys.argv[5]
pool = load_llff("../shared/data/llff_beer", downscale=2, scene_type=kind)
train, test = pool.subset(train_idx), pool.subset(test_idx)
config = choose_priors(FieldTrainConfig(downscale=2), len(train), train.scene_type, None if priors == "auto" else priors)
t = time.perf_counter()
run = train_field(train, config, out, progress=False)
scores = evaluate_field(run, test, with_flip=False, renderer="gl")
res = {"kind": kind, "train": train_idx, "test": test_idx, "priors": config.priors_choice, "psnr": scores["psnr"], "ssim": scores["ssim"], "seconds": time.perf_counter() - t}
print(json.dumps(res)); open(out + ".json", "w").write(json.dumps(res))
