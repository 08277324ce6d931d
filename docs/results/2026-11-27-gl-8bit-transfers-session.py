"""Session predict at 1920x1080 on a backend, reproject, linear vs srgb8 out: median ms over 6 frames."""
import json, sys, time
import numpy as np
from engine.runtime.session import Session, SessionConfig
backend = sys.argv[2] if len(sys.argv) > 2 else "gl"
w, h = 1920, 1080
rng = np.random.default_rng(0)
depth = rng.uniform(2.0, 8.0, (h, w)).astype(np.float32)
linear = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
codes = ((linear ** (1 / 2.2)) * 255).astype(np.uint8)
fx = 1000.0
proj = np.array([[2 * fx / w, 0, 0, 0], [0, 2 * fx / h, 0, 0], [0, 0, -1.0002, -0.20002], [0, 0, -1, 0]])
out = {}
for space, color in (("linear", linear), ("srgb8", codes)):
    s = Session(SessionConfig(engine="opengl", width=w, height=h, color_in=space, color_out=space, method="reproject"),
                backend=backend)
    pred, warp = [], []
    for i in range(8):
        view = np.eye(4); view[0, 3] = -0.01 * i
        s.submit(color, depth, view, proj, i / 60.0); t1 = time.perf_counter()
        view2 = view.copy(); view2[0, 3] -= 0.005
        p = s.predict(view2, proj, (i + 0.5) / 60.0); t2 = time.perf_counter()
        if i >= 2:
            pred.append(1e3 * (t2 - t1)); warp.append(p.stages_ms.get("warp", float("nan")))
    out[space] = {"predict_ms": float(np.median(pred)), "warp_stage_ms": float(np.median(warp)), "dtype": str(p.color.dtype)}
    print(space, out[space], flush=True)
json.dump(out, open(sys.argv[1], "w"), indent=1)
