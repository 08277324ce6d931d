"""numpy oracles of GL passes that have no other CPU twin, imported by tests only (the warp, the hole fill,
the trust rules and the luma have theirs in ``engine.geometry`` and ``engine.predict.dis``).

Conventions: images (H, W) float32, flows (H, W, 2) float32 pixels (x right, y down), pixel centres at +0.5.
"""
from __future__ import annotations

import numpy as np

__all__ = ["downsample_reference", "upsample_flow_reference", "patch_origins", "densify_reference",
           "patch_search_reference"]

#: ``flow_patch``'s Tikhonov term of the Hessian (levels^2)
PATCH_EPS = 1e-2


def downsample_reference(image: np.ndarray) -> np.ndarray:
    """Pass ``flow_downsample``: (ceil(H / 2), ceil(W / 2)) means of 2 x 2 blocks, the last row / column
    repeated past an odd border, in float32 (the GPU may round the sum in another order)."""
    h, w = image.shape
    padded = np.pad(image.astype(np.float32), ((0, h % 2), (0, w % 2)), mode="edge")
    a, b = padded[0::2, 0::2], padded[0::2, 1::2]
    c, d = padded[1::2, 0::2], padded[1::2, 1::2]
    return np.float32(0.25) * (((a + b) + c) + d)


def upsample_flow_reference(flow: np.ndarray, size: tuple[int, int], scale: float) -> np.ndarray:
    """Pass ``flow_upsample``: a coarse flow (Hc, Wc, 2), ``scale`` times smaller per axis than ``size``
    (x_fine + 0.5 = scale (x_coarse + 0.5)), sampled bilinearly with clamped borders and times ``scale``;
    non-finite results become 0. float64 inside (the GPU's float32 differs by rounding)."""
    hc, wc = flow.shape[:2]
    h, w = size
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    px = np.clip((xs + 0.5) / scale - 0.5, 0, wc - 1)
    py = np.clip((ys + 0.5) / scale - 0.5, 0, hc - 1)
    x0, y0 = np.floor(px).astype(int), np.floor(py).astype(int)
    tx, ty = (px - x0)[..., None], (py - y0)[..., None]
    x1, y1 = np.minimum(x0 + 1, wc - 1), np.minimum(y0 + 1, hc - 1)
    f = flow.astype(np.float64)
    top = f[y0, x0] * (1 - tx) + f[y0, x1] * tx
    bottom = f[y1, x0] * (1 - tx) + f[y1, x1] * tx
    out = (top * (1 - ty) + bottom * ty) * scale
    out[~np.isfinite(out).all(axis=-1)] = 0.0
    return out.astype(np.float32)


def patch_origins(n: int, patch: int, stride: int) -> np.ndarray:
    """First pixels of the patches along an axis of ``n`` pixels (``flow_common.glsl``): ``j * stride``, the
    last moved back to end at the border; one patch at 0 when ``n`` <= ``patch``."""
    count = 1 if n <= patch else (n - patch + stride - 1) // stride + 1
    return np.maximum(0, np.minimum(np.arange(count) * stride, n - patch))


def _bilinear_clamped(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    h, w = image.shape
    x, y = np.clip(x, 0, w - 1), np.clip(y, 0, h - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    tx, ty = x - x0, y - y0
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    top = image[y0, x0] * (1 - tx) + image[y0, x1] * tx
    return (top * (1 - ty) + (image[y1, x0] * (1 - tx) + image[y1, x1] * tx) * ty)


def densify_reference(first: np.ndarray, second: np.ndarray, patch_flows: np.ndarray, patch: int,
                      stride: int) -> np.ndarray:
    """Pass ``flow_densify``: per pixel of a level (H, W), the average of the flows of the patches covering it
    (``patch_flows`` (rows, columns, 2), origins ``patch_origins``), each weighted by 1 / max(1, |second at
    the pixel moved by it (bilinear, clamped) - first at the pixel|) (8-bit levels); 0 where no patch covers
    it. float64 inside."""
    h, w = first.shape
    rows, cols = patch_origins(h, patch, stride), patch_origins(w, patch, stride)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    total, weight = np.zeros((h, w, 2)), np.zeros((h, w))
    f1, f2 = first.astype(np.float64), second.astype(np.float64)
    for i, oy in enumerate(rows):
        for j, ox in enumerate(cols):
            y0, y1, x0, x1 = oy, min(oy + patch, h), ox, min(ox + patch, w)
            u = patch_flows[i, j].astype(np.float64)
            sample = _bilinear_clamped(f2, xs[y0:y1, x0:x1] + u[0], ys[y0:y1, x0:x1] + u[1])
            wgt = 1.0 / np.maximum(1.0, np.abs(sample - f1[y0:y1, x0:x1]))
            total[y0:y1, x0:x1] += wgt[..., None] * u
            weight[y0:y1, x0:x1] += wgt
    out = np.zeros((h, w, 2))
    covered = weight > 0
    out[covered] = total[covered] / weight[covered][:, None]
    return out.astype(np.float32)


def patch_search_reference(first: np.ndarray, second: np.ndarray, start: np.ndarray, patch: int, stride: int,
                           iterations: int, propagate: bool) -> np.ndarray:
    """Pass ``flow_patch`` (one sweep of DIS's inverse search on a level (H, W)): per patch, inverse-
    compositional Lucas-Kanade with mean normalisation from a start flow, the result (rows, columns, 2).

    Without ``propagate`` ``start`` is the level's dense initial flow (H, W, 2), read bilinearly (clamped) at the
    patch centre; with it, the previous sweep's patch flows (rows, columns, 2), and a patch starts from the one
    of its own and its 4 neighbours' with the lowest mean-normalised SSD. The template gradients are central
    differences (borders clamped) centred on their means; the Hessian gets ``PATCH_EPS`` on its diagonal; each
    iteration steps u -= H^-1 sum(g e). A patch keeps the start where the last iterate has a higher SSD, is not
    finite or lies more than a patch away. float64 inside."""
    h, w = first.shape
    rows, cols = patch_origins(h, patch, stride), patch_origins(w, patch, stride)
    f1, f2 = first.astype(np.float64), second.astype(np.float64)
    clamp = lambda a, n: np.clip(a, 0, n - 1)  # noqa: E731
    out = np.zeros((rows.size, cols.size, 2))
    k = np.arange(patch * patch)
    for i, oy in enumerate(rows):
        for j, ox in enumerate(cols):
            ys, xs = oy + k // patch, ox + k % patch
            tmpl = f1[clamp(ys, h), clamp(xs, w)]
            gx = 0.5 * (f1[clamp(ys, h), clamp(xs + 1, w)] - f1[clamp(ys, h), clamp(xs - 1, w)])
            gy = 0.5 * (f1[clamp(ys + 1, h), clamp(xs, w)] - f1[clamp(ys - 1, h), clamp(xs, w)])
            gx, gy = gx - gx.mean(), gy - gy.mean()
            hxx, hxy, hyy = PATCH_EPS + (gx * gx).sum(), (gx * gy).sum(), PATCH_EPS + (gy * gy).sum()
            inverse = np.array([[hyy, -hxy], [-hxy, hxx]]) / (hxx * hyy - hxy * hxy)

            def cost(u):
                e = _bilinear_clamped(f2, xs + u[0], ys + u[1]) - tmpl
                d = e - e.mean()
                return (d * d).sum(), np.array([(gx * d).sum(), (gy * d).sum()])

            if not propagate:
                centre = 0.5 * (patch - 1)
                begin = np.array([_bilinear_clamped(start[..., c].astype(np.float64), np.array(ox + centre),
                                                    np.array(oy + centre)) for c in range(2)], dtype=np.float64)
                best, step = cost(begin)
            else:
                begin = start[i, j].astype(np.float64)
                best, step = cost(begin)
                for di, dj in ((0, -1), (0, 1), (-1, 0), (1, 0)):
                    if 0 <= i + di < rows.size and 0 <= j + dj < cols.size:
                        candidate = start[i + di, j + dj].astype(np.float64)
                        ssd, s = cost(candidate)
                        if ssd < best:
                            best, begin, step = ssd, candidate, s
            u, ssd = begin.copy(), best
            for _ in range(iterations):
                u = u - inverse @ step
                ssd, step = cost(u)
            keep = ssd <= best and np.isfinite(u).all() and np.hypot(*(u - begin)) <= patch
            out[i, j] = u if keep else begin
    return out.astype(np.float32)
