"""Session wall time per call at 1920x1080, reproject on the cpu backend, for each colour encoding in and out:
median ms of submit and of predict over 6 frames (after 2 warm-ups). Usage: python session_bench.py OUT.json"""
import json, sys, time
import numpy as np
from engine.runtime.session import Session, SessionConfig

w, h = 1920, 1080
rng = np.random.default_rng(0)
depth = rng.uniform(2.0, 8.0, (h, w)).astype(np.float32)
linear = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
srgb = linear ** (1 / 2.2)
codes = (srgb * 255).astype(np.uint8)
fx = 1000.0
proj = np.array([[2 * fx / w, 0, 0, 0], [0, 2 * fx / h, 0, 0], [0, 0, -1.0002, -0.20002], [0, 0, -1, 0]])
out = {}
for space, color in (("linear", linear), ("srgb", srgb), ("srgb8", codes)):
    s = Session(SessionConfig(engine="opengl", width=w, height=h, color_in=space, color_out=space, method="reproject"),
                backend="cpu")
    sub, pred = [], []
    for i in range(8):
        view = np.eye(4); view[0, 3] = -0.01 * i
        t = time.perf_counter(); s.submit(color, depth, view, proj, i / 60.0); t1 = time.perf_counter()
        view2 = view.copy(); view2[0, 3] -= 0.005
        s.predict(view2, proj, (i + 0.5) / 60.0); t2 = time.perf_counter()
        if i >= 2:
            sub.append(1e3 * (t1 - t)); pred.append(1e3 * (t2 - t1))
    out[space] = {"submit_ms": float(np.median(sub)), "predict_ms": float(np.median(pred))}
    print(space, {k: round(v, 1) for k, v in out[space].items()}, flush=True)
json.dump(out, open(sys.argv[1], "w"), indent=1)
