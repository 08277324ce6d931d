"""forward_warp_frame median ms (25 calls, the last 20) at 960x540 (frames 4 and 6 of SEQUENCE) and the same frames
doubled to 1920x1080. Usage: python docs/results/2026-11-27-frame-warp-in-place-warp.py SEQUENCE_DIR"""
import sys, time, numpy as np
from engine import geometry
from engine.io.rgbd import read_sequence
seq = read_sequence(sys.argv[1])
f0, f1 = seq[4], seq[6]
K = f0.camera.intrinsics
for size in (1, 2):
    c, d = f0.color, f0.depth
    if size == 2:
        c = np.repeat(np.repeat(c, 2, 0), 2, 1); d = np.repeat(np.repeat(d, 2, 0), 2, 1)
        KK = K.copy(); KK[:2] *= 2
    else:
        KK = K
    ts = []
    for _ in range(25):
        t = time.perf_counter(); geometry.forward_warp_frame(c, d, KK, f0.camera.world_to_camera, KK, f1.camera.world_to_camera); ts.append(1e3 * (time.perf_counter() - t))
    print(f"{d.shape}: {np.median(ts[5:]):.2f}", end="  ")
print()
