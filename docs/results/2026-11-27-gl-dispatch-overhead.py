"""The Python side of a GL dispatch, and the dispatches of GlOpticalFlow.estimate per frame size (2026-11-27).

Usage: python docs/results/2026-11-27-gl-dispatch-overhead.py
1. Counts GlContext.dispatch_groups calls and wall ms of one estimate at 16x16, 64x64 and 1920x1080.
2. Profiles 50 estimates at 16x16 on the GL thread (cProfile): time inside moderngl's Program.run (the driver;
   llvmpipe executes the pass there) against the Python of dispatch_groups around it.
"""
import cProfile
import pstats
import time

import numpy as np

from engine.geometry.backends.gl.context import GlContext, shared_context
from engine.geometry.backends.gl.flow import GlOpticalFlow

count = [0]
original = GlContext.dispatch_groups


def counting(self, *args, **kwargs):
    count[0] += 1
    return original(self, *args, **kwargs)


rng = np.random.default_rng(0)
GlContext.dispatch_groups = counting
for h, w in ((16, 16), (64, 64), (1080, 1920)):
    a = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    b = np.roll(a, 2, axis=1)
    estimator = GlOpticalFlow()
    for _ in range(3):
        count[0] = 0
        start = time.perf_counter()
        estimator.estimate(a, b)
        wall = 1e3 * (time.perf_counter() - start)
    print(f"{w}x{h}: {count[0]} dispatches, {wall:.1f} ms wall")
GlContext.dispatch_groups = original

a = rng.uniform(0, 1, (16, 16, 3)).astype(np.float32)
b = np.roll(a, 2, axis=1)
estimator = GlOpticalFlow()
for _ in range(5):
    estimator.estimate(a, b)


def profiled():
    profile = cProfile.Profile()
    profile.enable()
    for _ in range(50):
        estimator.estimate(a, b)
    profile.disable()
    return profile


pstats.Stats(shared_context().call(profiled)).sort_stats("tottime").print_stats(6)
