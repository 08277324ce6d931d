"""fill_holes against fill_holes_reference at 1920x1080: 5 % random holes plus 40 empty rows at the top (a
pitch revealed them); median ms of 7 and whether the results are equal. Usage: python THIS.py"""
import time, numpy as np
from engine.geometry.holefill import fill_holes, fill_holes_reference
rng = np.random.default_rng(0)
h, w = 1080, 1920
color = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
depth = rng.uniform(1, 10, (h, w)).astype(np.float32)
holes = rng.uniform(size=(h, w)) < 0.05
holes[:40] = True  # a pitch revealed rows with no surface
fb = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
for name, fn in (("fill_holes", fill_holes), ("reference", fill_holes_reference)):
    fn(color, depth, holes, fb); ts = []
    for _ in range(7):
        t = time.perf_counter(); out = fn(color, depth, holes, fb); ts.append(1e3 * (time.perf_counter() - t))
    print(name, round(float(np.median(ts)), 1), "ms")
a, b = fill_holes(color, depth, holes, fb), fill_holes_reference(color, depth, holes, fb)
print("equal", all(np.array_equal(x, y) for x, y in zip(a, b)))
