"""Which float32 formula cv2.remap (OpenCV 5, INTER_LINEAR, float32 maps, float32 image) computes: the share of
interior samples each candidate reproduces to the bit. A fused multiply-add fma(a, b, c) is emulated in float64
(the product of two float32 is exact there). Usage: python 2026-11-27-flow2d-prep-cost-remap.py"""
import cv2
import numpy as np

rng = np.random.default_rng(1)
h, w = 100, 120
img = rng.integers(0, 256, (h, w)).astype(np.float32)  # 8-bit levels, as the trust rules sample
gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
mx = gx + rng.uniform(1, 3, (h, w)).astype(np.float32)
my = gy + rng.uniform(1, 3, (h, w)).astype(np.float32)
ref = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=-1.0)
inside = (mx < w - 2) & (my < h - 2)
fx, fy = np.floor(mx), np.floor(my)
ax, ay = (mx - fx).astype(np.float32), (my - fy).astype(np.float32)
sx, sy = np.clip(fx.astype(int), 0, w - 2), np.clip(fy.astype(int), 0, h - 2)
t00, t01, t10, t11 = img[sy, sx], img[sy, sx + 1], img[sy + 1, sx], img[sy + 1, sx + 1]
one = np.float32(1)


def fma(a, b, c):
    return (a.astype(np.float64) * b.astype(np.float64) + c.astype(np.float64)).astype(np.float32)


candidates = {
    "weights (1-ay)(1-ax) ... products, summed": t00 * ((one - ay) * (one - ax)) + t01 * ((one - ay) * ax)
    + t10 * (ay * (one - ax)) + t11 * (ay * ax),
    "lerp along x then y, multiply-adds": (t00 * (one - ax) + t01 * ax) * (one - ay) + (t10 * (one - ax) + t11 * ax) * ay,
    "a + (b - a) t along x then y, separate rounding": (t00 + (t01 - t00) * ax)
    + ((t10 + (t11 - t10) * ax) - (t00 + (t01 - t00) * ax)) * ay,
    "a + (b - a) t along x then y, fused multiply-adds": (lambda top, bottom: fma(bottom - top, ay, top))(
        fma(t01 - t00, ax, t00), fma(t11 - t10, ax, t10)),
}
for name, value in candidates.items():
    print(f"{np.mean(value[inside] == ref[inside]):8.4f}  {name}")
