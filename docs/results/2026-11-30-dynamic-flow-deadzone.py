"""Issue 45 (page 2026-11-30-dynamic-flow-deadzone.md): does a trained dynamic default lose its still background to
small, noisy flows? Evaluation only: the run's held-out views scored with its flow set to 0 wherever |flow|
(contracted units) is under each EPS (EPS 0: the run as trained).

    PYTHONPATH=. python docs/results/2026-11-30-dynamic-flow-deadzone.py RUN EPS[,EPS...] OUT.json
"""
import json
import sys

import torch

from models.fields.data.select import load_dynamic_run_views
from models.fields.train_dynamic import evaluate_dynamic, load_dynamic_model

torch.set_num_threads(1)
run = sys.argv[1]
model = load_dynamic_model(run)
_, test = load_dynamic_run_views(run)
mf = model.field.motion_field
orig = mf.forward
res = {}
for eps in [float(e) for e in sys.argv[2].split(",")]:
    def fwd(coords, times, _eps=eps):
        flow = orig(coords, times)
        if _eps > 0:
            keep = flow.norm(dim=-1, keepdim=True) >= _eps
            flow = flow * keep
        return flow
    mf.forward = fwd
    with torch.no_grad():
        s = evaluate_dynamic(model, test, with_flip=False)
    res[eps] = {k: s[k] for k in ("psnr", "psnr_objects", "psnr_background", "depth_mae", "flow_moving_fraction")}
    print(run, eps, json.dumps(res[eps]), flush=True)
json.dump(res, open(sys.argv[3], "w"), indent=1)
