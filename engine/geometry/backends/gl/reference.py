"""numpy oracles of the optical flow's GL passes (``flow.py``), imported by tests only (the warp, the hole fill,
the trust rules and the luma have theirs in ``engine.geometry`` and ``engine.predict.dis``).

Conventions: images (H, W) float32, flows (H, W, 2) float32 pixels (x right, y down), pixel centres at +0.5.
"""
from __future__ import annotations

import numpy as np

__all__ = ["downsample_reference", "upsample_flow_reference", "patch_origins", "densify_reference",
           "patch_search_reference", "refine_reference", "level_reference", "coarse_reference"]

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


def refine_reference(first: np.ndarray, second: np.ndarray, flow: np.ndarray, alpha: float, delta: float,
                     gamma: float, omega: float, iterations: int, sor_iterations: int) -> np.ndarray:
    """Passes ``flow_refine_*`` (DIS's variational refinement of a level's flow (H, W, 2), OpenCV's
    VariationalRefinement): the increment du minimising delta Psi(E_I) + gamma Psi(E_G) + alpha Psi(E_S),
    linearised at the second image warped by the flow (bilinear, clamped), derivatives I(x + 1) - I(x - 1)
    with replicated borders, robust weights lagged over ``iterations`` fixed-point iterations of
    ``sor_iterations`` red-black SOR sweeps (pixels with (x + y) even first); returns flow + du (a non-finite
    du is dropped). float64 inside."""
    h, w = first.shape
    zeta2, eps2 = 0.1 * 0.1, 0.001 * 0.001
    u = flow.astype(np.float64)
    ys, xs = np.mgrid[0:h, 0:w]
    warped = _bilinear_clamped(second.astype(np.float64), xs + u[..., 0], ys + u[..., 1])
    f1 = first.astype(np.float64)
    mean, iz = 0.5 * (f1 + warped), warped - f1

    def dx(a):
        p = np.pad(a, ((0, 0), (1, 1)), mode="edge")
        return p[:, 2:] - p[:, :-2]

    def dy(a):
        p = np.pad(a, ((1, 1), (0, 0)), mode="edge")
        return p[2:] - p[:-2]

    ix, iy = dx(mean), dy(mean)
    ixx, ixy, iyy, ixz, iyz = dx(ix), dy(ix), dy(iy), dx(iz), dy(iz)
    du = np.zeros((h, w, 2))
    right = lambda a: np.concatenate([a[:, 1:], a[:, -1:]], axis=1)  # noqa: E731  (replicated border)
    down = lambda a: np.concatenate([a[1:], a[-1:]], axis=0)  # noqa: E731
    for _ in range(iterations):
        norm = ix * ix + iy * iy + zeta2
        residual = iz + ix * du[..., 0] + iy * du[..., 1]
        wd = (0.5 * delta / np.sqrt(residual * residual / norm + eps2)) / norm
        a11, a12, a22 = wd * ix * ix + zeta2, wd * ix * iy, wd * iy * iy + zeta2
        b1, b2 = -wd * iz * ix, -wd * iz * iy
        nx, ny = ixx * ixx + ixy * ixy + zeta2, iyy * iyy + ixy * ixy + zeta2
        rx, ry = ixz + ixx * du[..., 0] + ixy * du[..., 1], iyz + ixy * du[..., 0] + iyy * du[..., 1]
        wg = 0.5 * gamma / np.sqrt(rx * rx / nx + ry * ry / ny + eps2)
        a11 = a11 + wg * (ixx * ixx / nx + ixy * ixy / ny)
        a12 = a12 + wg * (ixx * ixy / nx + ixy * iyy / ny)
        a22 = a22 + wg * (ixy * ixy / nx + iyy * iyy / ny)
        b1 = b1 - wg * (ixx * ixz / nx + ixy * iyz / ny)
        b2 = b2 - wg * (ixy * ixz / nx + iyy * iyz / ny)
        total = u + du
        gx, gy = right(total) - total, down(total) - total
        ws = 0.5 * alpha / np.sqrt((gx * gx).sum(-1) + (gy * gy).sum(-1) + eps2)
        for _ in range(sor_iterations):
            for parity in (0, 1):
                pull, weight = np.zeros((h, w, 2)), np.zeros((h, w))
                total = u + du
                # right, left, down, up neighbours inside the level; an edge's weight is its left / upper pixel's
                for sy, sx, edge in ((0, 1, ws), (0, -1, None), (1, 0, ws), (-1, 0, None)):
                    valid = np.zeros((h, w), bool)
                    valid[max(0, -sy):h - max(0, sy), max(0, -sx):w - max(0, sx)] = True
                    nb = np.roll(total, (-sy, -sx), axis=(0, 1))
                    wgt = edge if edge is not None else np.roll(ws, (-sy, -sx), axis=(0, 1))
                    wgt = np.where(valid, wgt, 0.0)
                    pull += wgt[..., None] * (nb - u) * valid[..., None]
                    weight += wgt
                mine = ((xs + ys) & 1) == parity
                new_x = (1 - omega) * du[..., 0] + omega * (b1 + pull[..., 0] - a12 * du[..., 1]) / (a11 + weight)
                new_y = (1 - omega) * du[..., 1] + omega * (b2 + pull[..., 1] - a12 * new_x) / (a22 + weight)
                du[..., 0] = np.where(mine, new_x, du[..., 0])
                du[..., 1] = np.where(mine, new_y, du[..., 1])
    finite = np.isfinite(du).all(axis=-1)
    return np.where(finite[..., None], u + du, u).astype(np.float32)


def level_reference(first: np.ndarray, second: np.ndarray, init: np.ndarray, patch: int, stride: int, iterations: int,
                    sweeps: int, refine: dict | None) -> np.ndarray:
    """One pyramid level (H, W) as the passes run it: ``sweeps`` inverse searches (``patch_search_reference``, the
    first from the dense initial flow ``init`` (H, W, 2), each later one propagating the previous), densified
    (``densify_reference``), then refined (``refine_reference`` with the keywords of ``refine``: alpha, delta,
    gamma, omega, iterations, sor_iterations; None or 0 iterations: none). Returns the level's dense flow."""
    flows = patch_search_reference(first, second, init, patch, stride, iterations, False)
    for _ in range(sweeps - 1):
        flows = patch_search_reference(first, second, flows, patch, stride, iterations, True)
    dense = densify_reference(first, second, flows, patch, stride)
    if refine and refine.get("iterations", 0):
        dense = refine_reference(first, second, dense, **refine)
    return dense


def coarse_reference(firsts: list, seconds: list, last: int, patch: int, stride: int, iterations: int, sweeps: int,
                     refine: dict | None) -> np.ndarray:
    """Pass ``flow_coarse``: levels ``len(firsts) - 1`` (the coarsest, from a zero flow) down to ``last`` of the
    two pyramids (``firsts[l]``, ``seconds[l]``: level l, (H_l, W_l) float32, level l + 1 ``downsample_reference``
    of level l), each from the coarser level's flow upsampled (``upsample_flow_reference``, scale 2) and run as
    ``level_reference``. Returns level ``last``'s dense flow (H_last, W_last, 2)."""
    dense = None
    for level in range(len(firsts) - 1, last - 1, -1):
        shape = firsts[level].shape
        init = np.zeros(shape + (2,), np.float32) if dense is None else upsample_flow_reference(dense, shape, 2.0)
        dense = level_reference(firsts[level], seconds[level], init, patch, stride, iterations, sweeps, refine)
    return dense
