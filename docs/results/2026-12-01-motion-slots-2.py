"""Thread CPU ms of the motion field's forward + backward on N points with 24 distinct times (a training batch's
kind), one torch thread: the default's hex-planes + flow MLP, the slots mixed by hat weights (forced) and by time.

    PYTHONPATH=. python docs/results/2026-12-01-motion-slots-2.py OUT.json
"""
import json, statistics, sys, time
import torch
torch.set_num_threads(1)
import models.fields.dynamic.model as dm
from models.fields.dynamic.model import MotionField, MotionConfig
out = {}
for n in (20000, 60000):
    torch.manual_seed(0)
    c = torch.rand(n, 3) * 2 - 1
    t = (torch.randint(0, 24, (n,)) / 23.0) * 2 - 1
    fields = {"default": (MotionField(MotionConfig(), 12), 64),
              "slots, hat weights": (MotionField(MotionConfig(slots=8), 12), 0),
              "slots, by time": (MotionField(MotionConfig(slots=8), 12), 64)}
    for f, _ in fields.values():
        for p in f.parameters():
            p.data += 0.01 * torch.randn_like(p)
    times = {k: [] for k in fields}
    for _ in range(15):
        for k, (f, limit) in fields.items():
            dm.SLOT_SEGMENT_TIMES = limit
            t0 = time.thread_time()
            f(c, t).square().sum().backward()
            times[k].append(1e3 * (time.thread_time() - t0))
    out[n] = {k: statistics.median(v[3:]) for k, v in times.items()}
    print(n, {k: round(v, 1) for k, v in out[n].items()})
json.dump(out, open(sys.argv[1], "w"), indent=1)
