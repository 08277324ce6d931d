"""Session submit ms at 1920x1080 with RGBA input (a game's backbuffer), cpu backend, reproject: median of 8."""
import sys, time, numpy as np
from engine.runtime.session import Session, SessionConfig
w, h = 1920, 1080
rng = np.random.default_rng(0)
depth = rng.uniform(2.0, 8.0, (h, w)).astype(np.float32)
inputs = {"srgb8": rng.integers(0, 256, (h, w, 4), dtype=np.uint8), "srgb": rng.uniform(0, 1, (h, w, 4)).astype(np.float32)}
fx = 1000.0
proj = np.array([[2 * fx / w, 0, 0, 0], [0, 2 * fx / h, 0, 0], [0, 0, -1.0002, -0.20002], [0, 0, -1, 0]])
out = []
for space, color in inputs.items():
    s = Session(SessionConfig(engine="opengl", width=w, height=h, color_in=space, method="reproject"), backend="cpu")
    ts = []
    for i in range(10):
        view = np.eye(4); view[0, 3] = -0.01 * i
        t = time.perf_counter(); s.submit(color, depth, view, proj, i / 60.0); ts.append(1e3 * (time.perf_counter() - t))
    out.append(f"{space} submit {np.median(ts[2:]):.1f}")
print(", ".join(out))
