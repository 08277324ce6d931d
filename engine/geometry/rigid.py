"""Rigid parts of the moving scene from motion vectors and depth, their screw extrapolation on SE(3), and the
check that a motion model explained the last interval (``mvec[extrapolation=rigid]``, ``mvec[fallback=true]``).

Conventions: points are in frame n's camera axes (OpenCV: x right, y down, z forward; scene units), pixel
centres at +0.5. The "interval" is frame n-k -> n; a transform ``T = (R, t)`` of an interval maps a point's
position at n-k to its position at n (``P = R Q + t``); ``s`` counts intervals after frame n. Moving pixels are
given by their flat indices (``moving``, increasing) and per-moving-pixel arrays are (M, ...) in that order.

- ``motion_components``: the moving pixels in 4-connected groups whose neighbours lie at a similar depth
  and move alike (their velocities differ by at most what a turn of ``max_angle`` gives at their distance):
  candidate rigid parts, one group per object or less, never across a depth edge.
- ``rigid_parts``: per group, a robust rigid fit (RANSAC over 3-point Kabsch fits, then least squares on the
  inliers), repeated on what is left (a group holding two objects gives two parts); pixels in no part keep
  their own straight-line motion. ``find_parts`` runs the rounds of all groups in one compiled call (a
  ``PartTable``); ``rigid_parts_reference`` is its oracle.
- ``part_motion``, ``screw_affine``, ``spin_affine``: a part's path, the screw
  ``exp(s xi + s (s + 1) / 2 (xi - xi_prev)) P`` (constant angular and linear velocity on SE(3), with the
  change of twist of the interval before where the three frames agree) or a spin about the part's centre
  while the centre moves on (whichever continued the interval before better), written as the per-point
  parabola ``P + s V + s (s + 1) / 2 A`` that the warp passes already evaluate (``path_affine``: V and A
  affine in P): exact at s = 0, 1/4 and 3/4 (the predicted frames of interleaving lie between 0 and 1),
  within a small fraction of the turn in between (``tests/predict/test_mvec_rigid.py``). ``part_paths`` gives
  every part's path in one compiled call (a ``PartPaths``; ``part_paths_reference``, with ``part_motion``, is
  its oracle); ``apply_parts`` (compiled) gives every pixel of a group that a part's transform explains that
  part's path.
- ``previous_positions``: each moving pixel's position at frame n-2k, from frame n-k's velocity where frame
  n-k showed the point; ``hindcast_keeps``: per region, whether the motion the earlier interval predicted
  for the last one moved the points closer to where frame n shows them than no object motion would.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
from numba import njit

from engine.core.checks import checked_array, checked_matrix
from engine.core.errors import InputError
from engine.geometry import kernels
from engine.geometry.regions import region_keeps

__all__ = ["MAX_TURN", "HYPOTHESES", "ROUNDS", "RigidPart", "transform_points", "rotation_exp", "rotation_log",
           "se3_exp", "se3_log",
           "fit_rigid", "fit_groups", "group_inliers", "motion_components", "motion_components_reference",
           "moving_points", "moving_points_reference", "robust_rigid", "robust_rigid_reference",
           "rigid_parts", "rigid_parts_reference", "PartTable", "find_parts", "PartPaths", "part_paths",
           "part_paths_reference", "path_affine", "screw_affine", "spin_affine", "screw_coefficients", "part_motion",
           "apply_parts", "apply_parts_reference", "kept_part_motion", "kept_part_motion_reference",
           "refined_before", "refined_before_reference", "previous_positions",
           "previous_positions_reference",
           "hindcast_keeps", "hindcast_errors", "hindcast_errors_reference", "rigid_explains_better", "project_points"]

#: a sample of at most this many points scores the RANSAC hypotheses of a group
SCORE_SAMPLE = 256
#: RANSAC's hypotheses per fit and its least-squares refits of the best one's inliers (``robust_rigid``)
HYPOTHESES, ROUNDS = 32, 2
#: radians: the largest turn per interval taken as a rigid part's motion (faster turns alias: a turn of
#: 200 degrees looks like one of -160) and allowed between neighbours of one group (``motion_components``)
MAX_TURN = 1.2


@dataclass(frozen=True)
class RigidPart:
    """A rigid part: ``members`` indices into the moving pixels, ``rotation`` (3, 3) and ``translation`` (3,)
    of its interval transform (position at n-k -> position at n, frame n's camera axes), ``group`` the
    ``motion_components`` group it was found in."""

    members: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    group: int = 0


def _hat(w: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def rotation_exp(w: np.ndarray) -> np.ndarray:
    """The rotation (3, 3) of the rotation vector ``w`` (axis times angle, radians; Rodrigues)."""
    w = np.asarray(w, np.float64)
    theta = float(np.linalg.norm(w))
    k = _hat(w)
    if theta < 1e-12:
        return np.eye(3) + k
    return np.eye(3) + math.sin(theta) / theta * k + (1.0 - math.cos(theta)) / theta ** 2 * (k @ k)


def rotation_log(rotation: np.ndarray) -> np.ndarray:
    """The rotation vector (3,) of a rotation matrix (angle in [0, pi])."""
    r = np.asarray(rotation, np.float64)
    cos = min(1.0, max(-1.0, (float(np.trace(r)) - 1.0) / 2.0))
    theta = math.acos(cos)
    vee = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    if theta < 1e-6:
        return 0.5 * vee
    if math.pi - theta > 1e-4:
        return theta / (2.0 * math.sin(theta)) * vee
    # near a half turn: the axis is the eigenvector of R + I's largest column, the sign from vee
    sym = 0.5 * (r + np.eye(3))
    axis = sym[:, int(np.argmax(np.diag(sym)))]
    axis = axis / np.linalg.norm(axis)
    if axis @ vee < 0:
        axis = -axis
    return theta * axis


def _left_jacobian(w: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(w))
    k = _hat(w)
    if theta < 1e-6:
        return np.eye(3) + 0.5 * k + (k @ k) / 6.0
    return (np.eye(3) + (1.0 - math.cos(theta)) / theta ** 2 * k
            + (theta - math.sin(theta)) / theta ** 3 * (k @ k))


def se3_log(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """The twist (6,) = (rotation vector, rho) of the rigid transform (R, t): ``exp`` of it is (R, t)."""
    w = rotation_log(rotation)
    return np.concatenate([w, np.linalg.solve(_left_jacobian(w), np.asarray(translation, np.float64))])


def se3_exp(twist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rigid transform (R (3, 3), t (3,)) of a twist (6,) (``se3_log``'s inverse): a screw motion."""
    w, rho = np.asarray(twist[:3], np.float64), np.asarray(twist[3:], np.float64)
    return rotation_exp(w), _left_jacobian(w) @ rho


def transform_points(points: np.ndarray, matrix: np.ndarray, offset=0.0) -> np.ndarray:
    """``points @ matrix.T + offset`` for points (N, 3) and a 3x3 ``matrix``, by columns: a BLAS product of
    that shape is slow and, on a busy machine, starts threads that wait on each other."""
    p = np.asarray(points, np.float64)
    m = np.asarray(matrix, np.float64)
    return p[:, 0:1] * m[:, 0] + p[:, 1:2] * m[:, 1] + p[:, 2:3] * m[:, 2] + offset


def fit_rigid(src: np.ndarray, dst: np.ndarray,
              weights: Optional[np.ndarray] = None) -> tuple[np.ndarray, np.ndarray]:
    """The least-squares rigid transform ``dst ~ R src + t`` (Kabsch, optional per-point ``weights``),
    (R (3, 3), t (3,)) in float64; ``src``, ``dst`` (N, 3), N >= 3."""
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, np.float64)
    total = w.sum()
    cs, cd = (w @ src) / total, (w @ dst) / total
    u, _, vt = np.linalg.svd(np.einsum("ni,nj->ij", (src - cs) * w[:, None], dst - cd))
    d = 1.0 if np.linalg.det(vt.T @ u.T) >= 0 else -1.0
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cd - r @ cs


@njit(cache=True, nogil=True)
def _horn_rotation(cov, out, a, v):  # pragma: no cover - compiled
    """The rotation (into ``out`` (3, 3)) that best turns centred points a onto b given their cross-covariance
    ``cov`` = sum a b^T (Horn 1987: the unit quaternion of the largest eigenvalue of a symmetric 4x4, here by
    cyclic Jacobi sweeps): ``fit_rigid``'s rotation, without its 3x3 SVD. ``a``, ``v``: (4, 4) scratch."""
    sxx, sxy, sxz = cov[0, 0], cov[0, 1], cov[0, 2]
    syx, syy, syz = cov[1, 0], cov[1, 1], cov[1, 2]
    szx, szy, szz = cov[2, 0], cov[2, 1], cov[2, 2]
    a[0, 0], a[0, 1], a[0, 2], a[0, 3] = sxx + syy + szz, syz - szy, szx - sxz, sxy - syx
    a[1, 1], a[1, 2], a[1, 3] = sxx - syy - szz, sxy + syx, szx + sxz
    a[2, 2], a[2, 3] = -sxx + syy - szz, syz + szy
    a[3, 3] = -sxx - syy + szz
    for i in range(4):
        for j in range(i):
            a[i, j] = a[j, i]
        for j in range(4):
            v[i, j] = 1.0 if i == j else 0.0
    size = 0.0
    for i in range(4):
        for j in range(4):
            size += a[i, j] * a[i, j]
    for _ in range(50):
        off = 0.0
        for i in range(4):
            for j in range(i + 1, 4):
                off += a[i, j] * a[i, j]
        if off <= 1e-32 * size:
            break
        for p in range(3):
            for q in range(p + 1, 4):
                if a[p, q] == 0.0:
                    continue
                theta = (a[q, q] - a[p, p]) / (2.0 * a[p, q])
                t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    t = -t
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for k in range(4):
                    akp, akq = a[k, p], a[k, q]
                    a[k, p], a[k, q] = c * akp - s * akq, s * akp + c * akq
                for k in range(4):
                    apk, aqk = a[p, k], a[q, k]
                    a[p, k], a[q, k] = c * apk - s * aqk, s * apk + c * aqk
                for k in range(4):
                    vkp, vkq = v[k, p], v[k, q]
                    v[k, p], v[k, q] = c * vkp - s * vkq, s * vkp + c * vkq
    top = 0
    for i in range(1, 4):
        if a[i, i] > a[top, top]:
            top = i
    w, x, y, z = v[0, top], v[1, top], v[2, top], v[3, top]
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / norm, x / norm, y / norm, z / norm
    out[0, 0], out[0, 1], out[0, 2] = w * w + x * x - y * y - z * z, 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)
    out[1, 0], out[1, 1], out[1, 2] = 2.0 * (x * y + w * z), w * w - x * x + y * y - z * z, 2.0 * (y * z - w * x)
    out[2, 0], out[2, 1], out[2, 2] = 2.0 * (x * z - w * y), 2.0 * (y * z + w * x), w * w - x * x - y * y + z * z


@njit(cache=True, nogil=True)
def _fit_sets(src, dst, rotation, translation):  # pragma: no cover - compiled
    """``_fit_many`` compiled: per set h the centred cross-covariance, Horn's rotation and the translation."""
    cov = np.empty((3, 3))
    cs = np.empty(3)
    cd = np.empty(3)
    sym = np.empty((4, 4))
    vecs = np.empty((4, 4))
    for h in range(src.shape[0]):
        n = src.shape[1]
        cs[:] = 0.0
        cd[:] = 0.0
        for i in range(n):
            for c in range(3):
                cs[c] += src[h, i, c]
                cd[c] += dst[h, i, c]
        for c in range(3):
            cs[c] /= n
            cd[c] /= n
        cov[:, :] = 0.0
        for i in range(n):
            for a in range(3):
                for b in range(3):
                    cov[a, b] += (src[h, i, a] - cs[a]) * (dst[h, i, b] - cd[b])
        _horn_rotation(cov, rotation[h], sym, vecs)
        for c in range(3):
            translation[h, c] = cd[c] - (rotation[h, c, 0] * cs[0] + rotation[h, c, 1] * cs[1]
                                         + rotation[h, c, 2] * cs[2])


def _fit_many(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``fit_rigid`` of many small point sets at once: ``src``, ``dst`` (H, n, 3) -> R (H, 3, 3), t (H, 3)."""
    rotation, translation = np.empty((len(src), 3, 3)), np.empty((len(src), 3))
    _fit_sets(np.ascontiguousarray(src, np.float64), np.ascontiguousarray(dst, np.float64), rotation, translation)
    return rotation, translation


@njit(cache=True, nogil=True)
def _find(parent, a):  # pragma: no cover - compiled
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


@njit(cache=True, nogil=True)
def _join(parent, i, j):  # pragma: no cover - compiled
    """Union of the sets of i and j, the smaller root the root of both."""
    a = _find(parent, i)
    b = _find(parent, j)
    if a < b:
        parent[b] = a
    elif b < a:
        parent[a] = b


@njit(cache=True, nogil=True)
def _number_roots(parent, labels):  # pragma: no cover - compiled
    """Each element's set numbered 0.. in the order of the sets' smallest members; returns the count."""
    count = 0
    for i in range(parent.size):  # roots are the smallest member: a root comes before its members
        a = _find(parent, i)
        if a == i:
            labels[i] = count
            count += 1
        else:
            labels[i] = labels[a]
    return count


@njit(cache=True, nogil=True)
def _link(points, velocity, i, j, band):  # pragma: no cover - compiled
    """Whether points i and j lie within the depth ratio ``band``, and their squared distance and squared
    difference of velocity (``motion_components``)."""
    zi = points[i, 2]
    zj = points[j, 2]
    dp = 0.0
    dv = 0.0
    if zi > band * zj or zj > band * zi:
        return False, dp, dv
    for c in range(3):
        dp += (points[i, c] - points[j, c]) ** 2
        dv += (velocity[i, c] - velocity[j, c]) ** 2
    return True, dp, dv


@njit(cache=True, nogil=True)
def _union_indexed(index, points, velocity, band, slope, relative, labels):  # pragma: no cover - compiled
    """Union-find over the 4-neighbour links of the moving pixels, found through a full-frame ``index``
    (``motion_components_reference``); ``labels`` (M,) receives a component number 0.. per moving pixel;
    returns the count."""
    h, w = index.shape
    m = points.shape[0]
    parent = np.arange(m)
    for y in range(h):
        for x in range(w):
            i = index[y, x]
            if i < 0:
                continue
            for step in range(2):
                yy = y + step
                xx = x + 1 - step
                if yy >= h or xx >= w:
                    continue
                j = index[yy, xx]
                if j < 0:
                    continue
                near, dp, dv = _link(points, velocity, i, j, band)
                if not near:
                    continue
                vi = 0.0
                vj = 0.0
                for c in range(3):
                    vi += velocity[i, c] ** 2
                    vj += velocity[j, c] ** 2
                if math.sqrt(dv) > slope * math.sqrt(dp) + relative * 0.5 * (math.sqrt(vi) + math.sqrt(vj)):
                    continue
                _join(parent, i, j)
    return _number_roots(parent, labels)




@njit(cache=True, nogil=True)
def _speeds(velocity, lo, hi, speed):  # pragma: no cover - compiled
    for i in range(lo, hi):
        speed[i] = math.sqrt(velocity[i, 0] ** 2 + velocity[i, 1] ** 2 + velocity[i, 2] ** 2)


@njit(cache=True, nogil=True)
def _union_links(moving, width, points, velocity, speed, band, slope, relative, parent, lo, hi, stop,
                 below_only):  # pragma: no cover - compiled
    """``motion_components``' union-find over the links of the moving pixels i in [lo, hi) to their right
    neighbour (unless ``below_only``) and the one below, where that neighbour's index j < ``stop``: the right
    neighbour of moving pixel i is i + 1 where that is the next pixel of its row, the one below is found by a
    pointer that only moves forward (``moving`` increases), so no full-frame index is needed; a link is
    accepted without square roots where its velocities differ by less than the bound's square allows
    (``|a| <= sqrt(a^2 + b^2) <= |a| + |b|``). Unions within [lo, ``stop``) only touch ``parent`` there."""
    below = lo
    slope2 = slope * slope
    for i in range(lo, hi):
        p = moving[i]
        for step in range(1 if below_only else 0, 2):
            if step == 0:
                if i + 1 >= stop or moving[i + 1] != p + 1 or (p + 1) % width == 0:
                    continue
                j = i + 1
            else:
                while below < stop and moving[below] < p + width:
                    below += 1
                if below >= stop or moving[below] != p + width:
                    continue
                j = below
            near, dp, dv = _link(points, velocity, i, j, band)
            if not near:
                continue
            allowed = relative * 0.5 * (speed[i] + speed[j])
            if dv > slope2 * dp + allowed * allowed and math.sqrt(dv) > slope * math.sqrt(dp) + allowed:
                continue
            _join(parent, i, j)


def _row_cuts(moving: np.ndarray, width: int) -> list[tuple[int, int]]:
    """``kernels.split_points`` of the moving pixels, each cut moved back to the first pixel of its row: the
    ranges ``motion_components`` links on separate threads (no right link crosses a cut)."""
    ranges = kernels.split_points(moving.size)
    cuts = [0] + [int(np.searchsorted(moving, (moving[a] // width) * width)) for a, _ in ranges[1:]] + [moving.size]
    return list(zip(cuts[:-1], cuts[1:]))


def motion_components(shape: tuple[int, int], moving: np.ndarray, points: np.ndarray, velocity: np.ndarray, *,
                      depth_band: float = 1.1, max_angle: float = MAX_TURN,
                      relative: float = 0.05) -> tuple[np.ndarray, int]:
    """The moving pixels in groups that may move as one rigid body: (labels (M,) int64, count).

    Two 4-neighbours join when their depths differ by at most the ratio ``depth_band`` and their velocities
    (scene units per interval) by at most ``2 sin(max_angle / 2)`` times their distance (what a rigid turn of
    up to ``max_angle`` radians per interval gives) plus ``relative`` times their mean speed. Groups are the
    connected components of these links, numbered in the order of their first pixel (row-major).
    ``points``, ``velocity`` (M, 3) belong to the pixels ``moving`` (flat indices into ``shape``).
    """
    h, w = shape
    moving = np.asarray(moving, np.int64)
    sizes = {"M": moving.size}
    points = checked_array(points, "points", ("M", 3), sizes, np.float64)
    velocity = checked_array(velocity, "velocity", ("M", 3), sizes, np.float64)
    points, velocity = np.ascontiguousarray(points), np.ascontiguousarray(velocity)
    m = moving.size
    parent, speed, labels = np.arange(m), np.empty(m), np.empty(m, np.int64)
    args = (float(depth_band), 2.0 * math.sin(0.5 * max_angle), float(relative), parent)
    # each range of rows on its own thread (its unions stay inside it), then the links across the cuts: the same
    # sets as one pass, and each set is numbered by its smallest member whatever the order of the unions
    def link(a: int, b: int) -> None:  # a range's links read the speeds of its own pixels only
        _speeds(velocity, a, b, speed)
        _union_links(moving, w, points, velocity, speed, *args, a, b, b, False)

    ranges = _row_cuts(moving, w)
    kernels.run_ranges(link, ranges)
    for cut in (a for a, _ in ranges[1:]):
        row = int(np.searchsorted(moving, (moving[cut] // w - 1) * w)) if cut < m else cut
        _union_links(moving, w, points, velocity, speed, *args, row, cut, m, True)
    return labels, int(_number_roots(parent, labels))


def motion_components_reference(shape: tuple[int, int], moving: np.ndarray, points: np.ndarray,
                                velocity: np.ndarray, *, depth_band: float = 1.1, max_angle: float = MAX_TURN,
                                relative: float = 0.05) -> tuple[np.ndarray, int]:
    """``motion_components`` through a full-frame index of the moving pixels, each link's bound with its
    square roots (the test oracle)."""
    h, w = shape
    moving = np.asarray(moving, np.int64)
    index = np.full(h * w, -1, np.int64)
    index[moving] = np.arange(moving.size)
    labels = np.empty(moving.size, np.int64)
    count = _union_indexed(index.reshape(h, w), np.ascontiguousarray(points, np.float64),
                           np.ascontiguousarray(velocity, np.float64), float(depth_band),
                           2.0 * math.sin(0.5 * max_angle), float(relative), labels)
    return labels, int(count)


def project_points(points: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """Pixel positions (N, 2) of camera-axes points (N, 3) (pixel centres at +0.5, as ``K`` maps them);
    NaN for points on or behind the camera plane."""
    k = np.asarray(intrinsics, np.float64)
    z = np.asarray(points[:, 2], np.float64)
    ok = z > 1e-9
    zs = np.where(ok, z, 1.0)
    x = k[0, 0] * points[:, 0] / zs + k[0, 1] * points[:, 1] / zs + k[0, 2]
    y = k[1, 1] * points[:, 1] / zs + k[1, 2]
    out = np.stack([x, y], axis=-1)
    out[~ok] = np.nan
    return out


def _refit_guess(src, dst, scale, guess, threshold):
    """``robust_rigid``'s guess, refitted on its inliers (compiled: ``group_inliers`` and ``fit_groups`` of one
    group) where it explains half the points or more: (R, t, inliers), else None."""
    if guess is None:
        return None
    n = len(src)
    src, dst = np.ascontiguousarray(src, np.float64), np.ascontiguousarray(dst, np.float64)
    scale, one = np.ascontiguousarray(scale, np.float64), np.zeros(n, np.int64)
    inliers = group_inliers(src, dst, scale, one, np.asarray(guess[0], np.float64)[None],
                            np.asarray(guess[1], np.float64)[None], threshold)
    if inliers.sum() < max(3, n // 2):
        return None
    rotation, translation = fit_groups(src, dst, np.where(inliers, 0, -1), 1)
    inliers = group_inliers(src, dst, scale, one, rotation, translation, threshold)
    return rotation[0], translation[0], inliers


def robust_rigid(src: np.ndarray, dst: np.ndarray, scale: np.ndarray, key: tuple = (0,), *,
                 threshold: float = 1.0, hypotheses: int = HYPOTHESES, rounds: int = ROUNDS,
                 guess: Optional[tuple[np.ndarray, np.ndarray]] = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A rigid transform ``dst ~ R src + t`` robust to outliers: (R, t, inlier mask (N,)).

    RANSAC: ``hypotheses`` Kabsch fits of 3 random points each, scored on a sample of at most
    ``SCORE_SAMPLE`` points by their inliers (residual ``|R src + t - dst|`` times ``scale``, i.e. in pixels
    for ``scale = f / z``, at most ``threshold``); the best one's inliers among all points are then refitted by
    least squares ``rounds`` times. The random draws are a hash of ``key`` (a tuple of ints: ``draws``). A
    ``guess`` (R, t) that already explains half the points is refitted instead, without sampling (a part's
    transform of the interval before, under steady motion)."""
    n = len(src)
    guessed = _refit_guess(src, dst, scale, guess, threshold)
    if guessed is not None:
        return guessed
    src, dst = np.ascontiguousarray(src, np.float64), np.ascontiguousarray(dst, np.float64)
    scale, one = np.ascontiguousarray(scale, np.float64), np.zeros(n, np.int64)
    sample, picks = draws(_key_base(key), n, hypotheses)
    r, t = _fit_many(src[picks], dst[picks])
    best = np.zeros(1, np.int64)  # compiled scores: those of ``robust_rigid_reference``, without its (H, n, 3) arrays
    _best_hypotheses(src, dst, scale, sample.astype(np.int64), np.array([0, sample.size], np.int64), r, t, hypotheses,
                     float(threshold), best)
    rotation, translation = r[best[0]], t[best[0]]
    inliers = group_inliers(src, dst, scale, one, rotation[None], translation[None], threshold)
    for _ in range(rounds):
        if inliers.sum() < 3:
            break
        rotation, translation = fit_rigid(src[inliers], dst[inliers])
        inliers = group_inliers(src, dst, scale, one, rotation[None], translation[None], threshold)
    return rotation, translation, inliers


def robust_rigid_reference(src: np.ndarray, dst: np.ndarray, scale: np.ndarray, key: tuple = (0,), *,
                           threshold: float = 1.0, hypotheses: int = HYPOTHESES, rounds: int = ROUNDS,
                           guess: Optional[tuple[np.ndarray, np.ndarray]] = None
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``robust_rigid`` in numpy: the hypotheses scored by ``einsum``, the inliers by ``transform_points`` (the
    test oracle; that docstring states it)."""
    n = len(src)
    guessed = _refit_guess(src, dst, scale, guess, threshold)
    if guessed is not None:
        return guessed
    sample, picks = draws(_key_base(key), n, hypotheses)
    r, t = _fit_many(src[picks], dst[picks])
    moved = np.einsum("hij,nj->hni", r, src[sample]) + t[:, None, :]
    score = (np.linalg.norm(moved - dst[sample], axis=-1) * scale[sample] <= threshold).sum(axis=1)
    best = int(np.argmax(score))
    rotation, translation = r[best], t[best]
    inliers = np.linalg.norm(transform_points(src, rotation, translation) - dst, axis=-1) * scale <= threshold
    for _ in range(rounds):
        if inliers.sum() < 3:
            break
        rotation, translation = fit_rigid(src[inliers], dst[inliers])
        inliers = np.linalg.norm(transform_points(src, rotation, translation) - dst, axis=-1) * scale <= threshold
    return rotation, translation, inliers


_MASK = (1 << 64) - 1
_GOLDEN = 0x9E3779B97F4A7C15


def _mix(z):
    """splitmix64's finaliser of uint64 values (numpy arrays wrap modulo 2^64)."""
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def _key_base(key: tuple) -> int:
    """One 64-bit number from a tuple of ints (each folded in by splitmix64's steps)."""
    base = 0
    for part in key:
        z = (base ^ (int(part) & _MASK)) + _GOLDEN & _MASK
        z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9 & _MASK
        z = (z ^ (z >> 27)) * 0x94D049BB133111EB & _MASK
        base = z ^ (z >> 31)
    return base


def _uniform(bases: np.ndarray, counters: np.ndarray) -> np.ndarray:
    """Uniform numbers in [0, 1) (len(bases), len(counters)): a hash of each base (uint64) and counter."""
    z = _mix(bases[:, None] + counters[None, :].astype(np.uint64) * np.uint64(_GOLDEN))
    return (z >> np.uint64(11)).astype(np.float64) * 2.0 ** -53


def draws(base: int, n: int, hypotheses: int) -> tuple[np.ndarray, np.ndarray]:
    """RANSAC's draws for ``n`` points from the hash ``base``: (the points that score, at most ``SCORE_SAMPLE``
    of them (all when n is at most that), the picks (hypotheses, 3) of each hypothesis's 3 points).
    Counter-based, so that ``rigid_parts`` draws for all groups at once what one group draws alone."""
    bases = np.array([base], np.uint64)
    picks = np.minimum((_uniform(bases, np.arange(3 * hypotheses)) * n).astype(np.int64), n - 1)
    if n <= SCORE_SAMPLE:
        return np.arange(n), picks.reshape(hypotheses, 3)
    keys = _uniform(bases, 3 * hypotheses + np.arange(n))[0]
    return np.sort(np.argsort(keys, kind="stable")[:SCORE_SAMPLE]), picks.reshape(hypotheses, 3)


@njit(cache=True, nogil=True)
def _best_hypotheses(src, dst, scale, samples, offsets, rotation, translation, hypotheses, threshold,
                     best):  # pragma: no cover - compiled
    """Per group f: the first of its ``hypotheses`` transforms (rows f * hypotheses ..) with the most inliers
    among its points ``samples[offsets[f]:offsets[f + 1]]`` (``robust_rigid``'s score). A hypothesis's count
    stops once the points left could not lift it above the best one's (it could not win: the same choice)."""
    for f in range(offsets.size - 1):
        top = -1
        for h in range(hypotheses):
            j = f * hypotheses + h
            count = 0
            for s in range(offsets[f], offsets[f + 1]):
                if count + offsets[f + 1] - s <= top:  # even if every point left were an inlier: not more than top
                    break
                i = samples[s]
                r2 = 0.0
                for c in range(3):
                    d = (rotation[j, c, 0] * src[i, 0] + rotation[j, c, 1] * src[i, 1] + rotation[j, c, 2] * src[i, 2]
                         + translation[j, c] - dst[i, c])
                    r2 += d * d
                if math.sqrt(r2) * scale[i] <= threshold:
                    count += 1
            if count > top:
                top = count
                best[f] = h


_GOLDEN_U64 = np.uint64(_GOLDEN)
_MIX_A = np.uint64(0xBF58476D1CE4E5B9)
_MIX_B = np.uint64(0x94D049BB133111EB)


@njit(cache=True, nogil=True)
def _mix_one(z):  # pragma: no cover - compiled
    """``_mix`` of one uint64."""
    z = (z ^ (z >> np.uint64(30))) * _MIX_A
    z = (z ^ (z >> np.uint64(27))) * _MIX_B
    return z ^ (z >> np.uint64(31))


@njit(cache=True, nogil=True)
def _fold(base, part):  # pragma: no cover - compiled
    """One step of ``_key_base``: the int ``part`` folded into ``base`` (uint64)."""
    return _mix_one((base ^ np.uint64(part)) + _GOLDEN_U64)


@njit(cache=True, nogil=True)
def _uniform_one(base, counter):  # pragma: no cover - compiled
    """``_uniform`` of one base and counter."""
    return np.float64(_mix_one(base + np.uint64(counter) * _GOLDEN_U64) >> np.uint64(11)) * 2.0 ** -53


@njit(cache=True, nogil=True)
def _member_inliers(src, dst, scale, members, rotation, translation, threshold, out):  # pragma: no cover
    """``group_inliers`` of the points ``members`` under one transform, into ``out[k]`` for ``members[k]``;
    returns their count."""
    count = 0
    for k in range(members.size):
        i = members[k]
        r2 = 0.0
        for c in range(3):
            d = src[i, 0] * rotation[c, 0] + src[i, 1] * rotation[c, 1] + src[i, 2] * rotation[c, 2]
            d = d + translation[c] - dst[i, c]
            r2 += d * d
        out[k] = math.sqrt(r2) * scale[i] <= threshold
        count += out[k]
    return count


@njit(cache=True, nogil=True)
def _finish_fit(sums, cov, rotation, translation, a, v):  # pragma: no cover - compiled
    """``fit_groups``' last steps for one group of moments ``sums`` (7,) and ``cov`` (3, 3): Horn's rotation (the
    identity under 3 points), then t = mean dst - R mean src, summed in ``np.einsum``'s order (lanes 0 + 2, then
    1), so that the batched and the single fits give the same bits."""
    _horn_rotation(cov, rotation, a, v)
    if sums[0] < 3:
        for c in range(3):
            for e in range(3):
                rotation[c, e] = 1.0 if c == e else 0.0
    for c in range(3):
        moved = (rotation[c, 0] * sums[1] + rotation[c, 2] * sums[3]) + rotation[c, 1] * sums[2]
        translation[c] = sums[4 + c] - moved


@njit(cache=True, nogil=True)
def _fit_labels(src, dst, labels, count, rotation, translation):  # pragma: no cover - compiled
    """``fit_groups`` compiled, into ``rotation`` (count, 3, 3) and ``translation`` (count, 3)."""
    sums, cov = np.zeros((count, 7)), np.zeros((count, 3, 3))
    _group_moments(src, dst, labels, count, sums, cov)
    a, v = np.empty((4, 4)), np.empty((4, 4))
    for g in range(count):
        _finish_fit(sums[g], cov[g], rotation[g], translation[g], a, v)


@njit(cache=True, nogil=True)
def _fit_members(src, dst, members, use, rotation, translation):  # pragma: no cover - compiled
    """``fit_groups`` of the points ``members[k]`` with ``use[k]`` as one group: ``_group_moments``' sums in its
    order, then ``_finish_fit``."""
    sums, cov = np.zeros(7), np.zeros((3, 3))
    for k in range(members.size):
        if use[k]:
            i = members[k]
            sums[0] += 1.0
            for c in range(3):
                sums[1 + c] += src[i, c]
                sums[4 + c] += dst[i, c]
    if sums[0] > 0:
        for c in range(1, 7):
            sums[c] /= sums[0]
    for k in range(members.size):
        if use[k]:
            i = members[k]
            for a in range(3):
                for b in range(3):
                    cov[a, b] += (src[i, a] - sums[1 + a]) * (dst[i, b] - sums[4 + b])
    _finish_fit(sums, cov, rotation, translation, np.empty((4, 4)), np.empty((4, 4)))


@njit(cache=True, nogil=True)
def _ransac_members(src, dst, scale, members, base, hypotheses, rounds, threshold, rotation, translation,
                    inliers):  # pragma: no cover - compiled
    """``robust_rigid``'s sampling for the points ``members`` (increasing) with the draws of ``base``
    (``draws``): the best hypothesis, refitted on its inliers ``rounds`` times by ``_fit_members`` (Horn's
    rotation, as ``fit_groups``). Into ``rotation``, ``translation``, ``inliers[k]`` (of ``members[k]``);
    returns the inliers' count."""
    n = members.size
    picked_src, picked_dst = np.empty((hypotheses, 3, 3)), np.empty((hypotheses, 3, 3))
    for h in range(hypotheses):
        for c in range(3):
            i = members[min(int(_uniform_one(base, 3 * h + c) * n), n - 1)]
            for e in range(3):
                picked_src[h, c, e] = src[i, e]
                picked_dst[h, c, e] = dst[i, e]
    r, t = np.empty((hypotheses, 3, 3)), np.empty((hypotheses, 3))
    _fit_sets(picked_src, picked_dst, r, t)
    samples = members
    if n > SCORE_SAMPLE:
        keys = np.empty(n)
        for i in range(n):
            keys[i] = _uniform_one(base, 3 * hypotheses + i)
        samples = members[np.sort(np.argsort(keys, kind="mergesort")[:SCORE_SAMPLE])]
    best = np.zeros(1, np.int64)
    offsets = np.zeros(2, np.int64)
    offsets[1] = samples.size
    _best_hypotheses(src, dst, scale, samples, offsets, r, t, hypotheses, threshold, best)
    rotation[:, :] = r[best[0]]
    translation[:] = t[best[0]]
    kept = _member_inliers(src, dst, scale, members, rotation, translation, threshold, inliers)
    for _ in range(rounds):
        if kept < 3:
            break
        _fit_members(src, dst, members, inliers, rotation, translation)
        kept = _member_inliers(src, dst, scale, members, rotation, translation, threshold, inliers)
    return kept


@njit(cache=True, nogil=True)
def _robust_members(src, dst, scale, members, base, guessed, guess_rotation, guess_translation, hypotheses, rounds,
                    threshold, rotation, translation, inliers):  # pragma: no cover - compiled
    """``robust_rigid`` of the points ``members`` (``_ransac_members``' arguments and outputs): with ``guessed``,
    the guess refitted on its inliers where it explains half of them or more (``_refit_guess``)."""
    if guessed:
        kept = _member_inliers(src, dst, scale, members, guess_rotation, guess_translation, threshold, inliers)
        if kept >= max(3, members.size // 2):
            _fit_members(src, dst, members, inliers, rotation, translation)
            return _member_inliers(src, dst, scale, members, rotation, translation, threshold, inliers)
    return _ransac_members(src, dst, scale, members, base, hypotheses, rounds, threshold, rotation, translation,
                           inliers)


@njit(cache=True, nogil=True)
def _rigid_rounds(labels, count, src, dst, scale, threshold, min_points, min_share, max_parts, seed, hypotheses,
                  rounds, claimed, rotations, translations, found):  # pragma: no cover - compiled
    """``rigid_parts``' rounds, all groups at once: per round, each active group's least-squares fit of its
    points left, refitted on its inliers where it explains half of them or more, else ``_ransac_members``
    (key (seed, group, round)); a group whose fit explains ``min_points`` and ``min_share`` of its points left
    gets a part. Outputs: ``claimed`` (N,) the round whose part took each point (-1: none), ``rotations``
    (count, max_parts, 3, 3), ``translations`` (count, max_parts, 3) the parts' transforms by group and round,
    ``found`` (count,) each group's number of parts."""
    n = labels.size
    floor = max(min_points, 3)
    left = np.ones(n, np.bool_)
    totals = np.zeros(count, np.int64)
    for i in range(n):
        totals[labels[i]] += 1
    active = totals >= floor
    current, fitted = np.empty(n, np.int64), np.empty(n, np.int64)
    inliers = np.zeros(n, np.bool_)
    rotation, translation = np.empty((count, 3, 3)), np.empty((count, 3))
    sizes, kept = np.zeros(count, np.int64), np.zeros(count, np.int64)
    guessed, success = np.zeros(count, np.bool_), np.zeros(count, np.bool_)
    claimed[:] = -1
    found[:] = 0
    for r in range(max_parts):
        if not active.any():
            break
        sizes[:] = 0
        for i in range(n):
            g = labels[i]
            current[i] = g if left[i] and active[g] else -1
            if current[i] >= 0:
                sizes[g] += 1
        # the least-squares fit of all of a group's points left, refitted on its inliers where it explains half
        _fit_labels(src, dst, current, count, rotation, translation)
        _group_inliers(src, dst, scale, current, rotation, translation, threshold, inliers)
        kept[:] = 0
        for i in range(n):
            if inliers[i]:
                kept[current[i]] += 1
        for g in range(count):
            guessed[g] = kept[g] >= max(3, sizes[g] // 2)
        for i in range(n):
            fitted[i] = current[i] if inliers[i] and guessed[current[i]] else -1
        _fit_labels(src, dst, fitted, count, rotation, translation)
        for i in range(n):
            fitted[i] = current[i] if current[i] >= 0 and guessed[current[i]] else -1
        _group_inliers(src, dst, scale, fitted, rotation, translation, threshold, inliers)
        for g in range(count):  # the least-squares fit failed: sample
            if active[g] and not guessed[g]:
                members = np.flatnonzero(current == g)
                ok = np.empty(members.size, np.bool_)
                _ransac_members(src, dst, scale, members, _fold(_fold(_fold(np.uint64(0), seed), g), r), hypotheses,
                                rounds, threshold, rotation[g], translation[g], ok)
                for k in range(members.size):
                    inliers[members[k]] = ok[k]
        kept[:] = 0
        for i in range(n):
            if inliers[i]:
                kept[current[i]] += 1
        for g in range(count):
            success[g] = active[g] and kept[g] >= min_points and kept[g] >= min_share * sizes[g]
            if success[g]:
                rotations[g, r] = rotation[g]
                translations[g, r] = translation[g]
                found[g] += 1
        totals[:] = 0
        for i in range(n):
            if inliers[i] and success[current[i]]:
                left[i] = False
                claimed[i] = r
            if left[i]:
                totals[labels[i]] += 1
        for g in range(count):
            active[g] = success[g] and totals[g] >= floor


@dataclass(frozen=True)
class PartTable:
    """Rigid parts stacked (``find_parts``), in the order of their groups then of their rounds: ``group`` (P,)
    int64, ``rotation`` (P, 3, 3) and ``translation`` (P, 3) float64 of their interval transforms (position at
    n-k -> position at n), ``part`` (N,) int64 each point's part (-1: none)."""

    group: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    part: np.ndarray


def find_parts(labels: np.ndarray, count: int, points: np.ndarray, before: np.ndarray, scale: np.ndarray, *,
               threshold: float = 1.0, min_points: int = 32, min_share: float = 0.5, max_parts: int = 3,
               seed: int = 0) -> PartTable:
    """``rigid_parts`` as a ``PartTable``, in one compiled call (``_rigid_rounds``)."""
    labels = np.ascontiguousarray(labels, np.int64)
    n = labels.size
    claimed, found = np.empty(n, np.int64), np.empty(count, np.int64)
    rotations, translations = np.empty((count, max_parts, 3, 3)), np.empty((count, max_parts, 3))
    _rigid_rounds(labels, count, np.ascontiguousarray(before, np.float64), np.ascontiguousarray(points, np.float64),
                  np.ascontiguousarray(scale, np.float64), float(threshold), int(min_points), float(min_share),
                  int(max_parts), int(seed), HYPOTHESES, ROUNDS, claimed, rotations, translations, found)
    rounds = np.arange(max_parts)
    has = rounds[None, :] < found[:, None]  # (count, max_parts): the parts, by group then round
    first = np.concatenate([[0], np.cumsum(found)])  # each group's first part
    part = np.where(claimed >= 0, first[labels] + claimed, -1) if n else np.zeros(0, np.int64)
    return PartTable(np.nonzero(has)[0].astype(np.int64), rotations[has], translations[has], part.astype(np.int64))


def rigid_parts(labels: np.ndarray, count: int, points: np.ndarray, before: np.ndarray, scale: np.ndarray, *,
                threshold: float = 1.0, min_points: int = 32, min_share: float = 0.5, max_parts: int = 3,
                seed: int = 0) -> list[RigidPart]:
    """The rigid parts of the groups ``labels`` (``motion_components``): per group, ``robust_rigid`` of the
    points' positions ``before`` (n-k) -> ``points`` (n), kept when it explains at least ``min_points`` and
    ``min_share`` of the group's points not yet in a part; repeated on the rest, at most ``max_parts`` times.
    ``scale`` (M,) turns a 3D residual into pixels (f / z). Deterministic for a ``seed`` (each group draws its
    RANSAC draws from the key ``(seed, group, round)``).

    All groups are fitted at once, round by round, in one compiled call (``find_parts``: the least-squares
    fit of the points left, its inliers refitted, as ``robust_rigid`` does with that fit as its guess); a group
    whose least-squares fit explains less than half its points takes ``robust_rigid``'s sampling. The same
    parts as ``rigid_parts_reference`` (one group at a time), to rounding (``tests/predict/test_mvec_rigid.py``)."""
    table = find_parts(labels, count, points, before, scale, threshold=threshold, min_points=min_points,
                       min_share=min_share, max_parts=max_parts, seed=seed)
    return [RigidPart(np.flatnonzero(table.part == j), table.rotation[j], table.translation[j], int(g))
            for j, g in enumerate(table.group)]


def rigid_parts_reference(labels: np.ndarray, count: int, points: np.ndarray, before: np.ndarray, scale: np.ndarray,
                          *, threshold: float = 1.0, min_points: int = 32, min_share: float = 0.5, max_parts: int = 3,
                          seed: int = 0) -> list[RigidPart]:
    """``rigid_parts`` one group and one round at a time with ``robust_rigid`` (the test oracle)."""
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(count + 1))
    parts = []
    for g in range(count):
        left = order[bounds[g]:bounds[g + 1]]
        found: list = []
        for _ in range(max_parts):
            if left.size < max(min_points, 3):
                break
            # the least-squares fit of all of them first: a group that is one clean part needs no sampling
            rotation, translation, inliers = robust_rigid_reference(before[left], points[left], scale[left],
                                                                    (seed, g, len(found)), threshold=threshold,
                                                                    guess=fit_rigid(before[left], points[left]))
            kept = int(inliers.sum())
            if kept < min_points or kept < min_share * left.size:
                break
            found.append(RigidPart(left[inliers], rotation, translation, g))
            left = left[~inliers]
        parts += found
    return parts


@njit(cache=True, nogil=True)
def _group_moments(src, dst, labels, count, sums, cov):  # pragma: no cover - compiled
    """Per group (``labels`` >= 0): ``sums`` (count, 7) = (n, sum src, sum dst), then ``cov`` (count, 3, 3) the
    centred cross-covariance sum (src - mean src)(dst - mean dst)^T (``fit_groups``)."""
    for i in range(labels.size):
        g = labels[i]
        if g < 0:
            continue
        sums[g, 0] += 1.0
        for c in range(3):
            sums[g, 1 + c] += src[i, c]
            sums[g, 4 + c] += dst[i, c]
    for g in range(count):
        if sums[g, 0] > 0:
            for c in range(1, 7):
                sums[g, c] /= sums[g, 0]
    for i in range(labels.size):
        g = labels[i]
        if g < 0:
            continue
        for a in range(3):
            for b in range(3):
                cov[g, a, b] += (src[i, a] - sums[g, 1 + a]) * (dst[i, b] - sums[g, 4 + b])


def fit_groups(src: np.ndarray, dst: np.ndarray, labels: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """``fit_rigid`` of every group at once: the points with ``labels`` g (0 <= g < ``count``; -1: none) give
    group g's (R, t), stacked as (count, 3, 3), (count, 3); a group of fewer than 3 points gets the identity."""
    sums, cov = np.zeros((count, 7)), np.zeros((count, 3, 3))
    _group_moments(src, dst, np.ascontiguousarray(labels, np.int64), count, sums, cov)
    rotation = np.empty((count, 3, 3))
    _horn_rotations(cov, rotation)
    rotation[sums[:, 0] < 3] = np.eye(3)
    cs, cd = sums[:, 1:4], sums[:, 4:7]
    return rotation, cd - np.einsum("gij,gj->gi", rotation, cs)


@njit(cache=True, nogil=True)
def _horn_rotations(cov, out):  # pragma: no cover - compiled
    a = np.empty((4, 4))
    v = np.empty((4, 4))
    for g in range(cov.shape[0]):
        _horn_rotation(cov[g], out[g], a, v)


@njit(cache=True, nogil=True)
def _group_inliers(src, dst, scale, labels, rotation, translation, threshold, out):  # pragma: no cover - compiled
    for i in range(labels.size):
        g = labels[i]
        if g < 0:
            out[i] = False
            continue
        r2 = 0.0
        for c in range(3):
            d = src[i, 0] * rotation[g, c, 0] + src[i, 1] * rotation[g, c, 1] + src[i, 2] * rotation[g, c, 2]
            d = d + translation[g, c] - dst[i, c]
            r2 += d * d
        out[i] = math.sqrt(r2) * scale[i] <= threshold


def group_inliers(src: np.ndarray, dst: np.ndarray, scale: np.ndarray, labels: np.ndarray, rotation: np.ndarray,
                  translation: np.ndarray, threshold: float) -> np.ndarray:
    """Per point, whether its group's transform (``fit_groups``'s stacks) moves ``src`` to ``dst`` within
    ``threshold`` (residual times ``scale``, as ``robust_rigid`` counts inliers); False where ``labels`` < 0."""
    out = np.empty(len(labels), bool)
    _group_inliers(src, dst, scale, np.ascontiguousarray(labels, np.int64), np.ascontiguousarray(rotation),
                   np.ascontiguousarray(translation), float(threshold), out)
    return out


@njit(cache=True, nogil=True)
def _moving_points(depth, velocity, moving, width, k_inv, stride, now, speed, z, grid):  # pragma: no cover
    for i in range(moving.size):
        p = moving[i]
        y = p // width
        x = p - y * width
        d = np.float64(depth[p])
        u = x + 0.5
        v = y + 0.5
        for c in range(3):
            now[i, c] = (k_inv[c, 0] * u + k_inv[c, 1] * v + k_inv[c, 2]) * d
            speed[i, c] = velocity[p, c]
        z[i] = d
        grid[i] = y % stride == 0 and x % stride == 0


def moving_points(depth: np.ndarray, velocity: np.ndarray, moving: np.ndarray, intrinsics: np.ndarray,
                  stride: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The moving pixels' points ``z K^-1 (u, v, 1)`` (M, 3), velocities (M, 3) (``velocity`` (H, W, 3) read
    at ``moving``) and depths (M,), float64, and ``sample``: which of them lie on the grid of every
    ``stride``-th row and column (indices into ``moving``). ``moving_points_reference`` is its numpy oracle."""
    h, w = depth.shape
    moving = np.ascontiguousarray(moving, np.int64)
    now, speed, z = np.empty((moving.size, 3)), np.empty((moving.size, 3)), np.empty(moving.size)
    grid = np.empty(moving.size, bool)
    depth, velocity = np.ascontiguousarray(depth).reshape(-1), np.ascontiguousarray(velocity).reshape(-1, 3)
    k_inv = np.linalg.inv(np.asarray(intrinsics, np.float64))
    kernels.run_ranges(lambda a, b: _moving_points(depth, velocity, moving[a:b], w, k_inv, int(stride), now[a:b],
                                                   speed[a:b], z[a:b], grid[a:b]), kernels.split_points(moving.size))
    return now, speed, z, np.flatnonzero(grid)


def moving_points_reference(depth: np.ndarray, velocity: np.ndarray, moving: np.ndarray, intrinsics: np.ndarray,
                            stride: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``moving_points`` in numpy."""
    w = depth.shape[1]
    y, x = np.divmod(np.asarray(moving, np.int64), w)
    z = depth.reshape(-1)[moving].astype(np.float64)
    k_inv = np.linalg.inv(np.asarray(intrinsics, np.float64))
    u, v = x + 0.5, y + 0.5
    now = np.empty((moving.size, 3))
    for c in range(3):
        now[:, c] = (k_inv[c, 0] * u + k_inv[c, 1] * v + k_inv[c, 2]) * z
    speed = velocity.reshape(-1, 3)[moving].astype(np.float64)
    return now, speed, z, np.flatnonzero((y % stride == 0) & (x % stride == 0))


#: the steps (intervals after frame n) at which ``path_affine``'s parabola meets a path: the outer predicted frames of
#: k = 4 (the largest turns per interval); in between it is off by under 0.7 % of the radius for a turn of 60 degrees
#: per interval at s = 1/2, 0.07 % for 30 degrees
NODES = (0.25, 0.75)


def path_affine(moved) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The parabola ``P + s V + s (s + 1) / 2 A`` through a rigid path at s = 0 and the two ``NODES``, as
    (Vm, Vt, Am, At) with ``V = Vm P + Vt``, ``A = Am P + At`` (3x3, 3): ``moved(s)`` = (R_s, t_s), the path's
    transform after s intervals, so the displacement ``(R_s - I) P + t_s`` is affine in P, and V, A too."""
    a, b = NODES
    (ra, ta), (rb, tb) = moved(a), moved(b)
    ma, mb = ra - np.eye(3), rb - np.eye(3)
    # s V + s (s + 1) / 2 A = D(s) at s = a, b, for the matrix and the offset alike
    acc_m, acc_t = 2.0 * (mb / b - ma / a) / (b - a), 2.0 * (tb / b - ta / a) / (b - a)
    return ma / a - 0.5 * (a + 1.0) * acc_m, ta / a - 0.5 * (a + 1.0) * acc_t, acc_m, acc_t


def screw_affine(twist: np.ndarray, change: Optional[np.ndarray] = None):
    """``path_affine`` of the screw path ``exp(s xi + s (s + 1) / 2 dxi)`` (``xi`` = ``twist`` of an interval,
    ``dxi`` = ``change``, the twist's change since the interval before, or 0): a turn about a fixed axis (a
    wheel on its axle, a door, a carousel)."""
    change = np.zeros(6) if change is None else np.asarray(change, np.float64)
    return path_affine(lambda s: se3_exp(s * twist + 0.5 * s * (s + 1.0) * change))


def spin_affine(rotation: np.ndarray, centre: np.ndarray, velocity: np.ndarray, change: Optional[np.ndarray] = None):
    """``path_affine`` of points turning by ``rotation`` per interval about a ``centre`` (3,) that moves by
    ``velocity`` per interval (plus ``s (s + 1) / 2 change``): a thrown, tumbling body."""
    w = rotation_log(rotation)
    change = np.zeros(3) if change is None else np.asarray(change, np.float64)

    def moved(s: float) -> tuple[np.ndarray, np.ndarray]:
        r = rotation_exp(s * w)
        return r, centre + s * velocity + 0.5 * s * (s + 1.0) * change - r @ centre

    return path_affine(moved)


def screw_coefficients(points: np.ndarray, twist: np.ndarray,
                       change: Optional[np.ndarray] = None) -> tuple[np.ndarray, np.ndarray]:
    """The (V, A) (N, 3) of points (N, 3) on the screw path (``screw_affine``)."""
    vm, vt, am, at = screw_affine(twist, change)
    return transform_points(points, vm, vt), transform_points(points, am, at)


def part_motion(now: np.ndarray, then: np.ndarray, earlier: Optional[np.ndarray], seen: np.ndarray,
                rotation: np.ndarray, translation: np.ndarray, scale: np.ndarray, key: tuple = (0,), *,
                threshold: float = 1.0, limit: float = 0.5):
    """One rigid part's path, from (a sample of) its points: (``affine``, ``predicted``). ``affine`` is the
    path's ``path_affine`` (V and A of any of the part's points); ``predicted`` (N, 3) is where the motion of
    the interval before put the given points at frame n, or None when that interval is unknown.

    A part's two frames fix its transform over the interval, not its path: the same transform is a turn
    about a fixed axis (``screw_affine``) or a spin about the part's centre while the centre moves on
    a line (``spin_affine``). With the positions ``earlier`` (n-2k) of the points ``seen`` then (a
    boolean mask, at least half the part), the transform of the interval before is fitted (``robust_rigid``,
    from a tenth of them or more) and each path, continued over the last interval, predicts frame n: the path
    that predicts it better is taken, with its change since the interval before where that prediction is
    within ``limit`` of the motion (three frames agree; else constant velocities). Without them: the screw
    (constant angular and linear velocity on SE(3)), which holds for any rigid motion of constant twist."""
    twist = se3_log(rotation, translation)
    if earlier is None or seen.sum() < max(3, len(now) // 2):
        return screw_affine(twist), None
    idx = np.flatnonzero(seen)
    r0, t0, fits = robust_rigid(earlier[idx], then[idx], scale[idx], key, threshold=threshold,
                                guess=(rotation, translation))
    if fits.sum() < max(8, idx.size // 10):  # frame n-k's velocities are guesses where n-2k did not see
        return screw_affine(twist), None
    idx = idx[fits]
    # the screw continued, and the spin path: the centre (of the seen points) moving on, the part turning
    # about it by r0; their mean errors against frame n over the seen points, and the mean motion
    screw, turned, sums = np.empty((len(now), 3)), np.empty((len(now), 3)), np.zeros(9)
    _continued_paths(np.ascontiguousarray(now, np.float64), np.ascontiguousarray(then, np.float64),
                     np.ascontiguousarray(earlier, np.float64), idx, np.ascontiguousarray(r0, np.float64),
                     np.ascontiguousarray(t0, np.float64), screw, turned, sums)
    err_screw, err_spin, motion = sums[:3]
    c1, c0 = sums[3:6], sums[6:9]
    if err_screw <= err_spin:
        change = twist - se3_log(r0, t0) if err_screw <= limit * motion else None
        return screw_affine(twist, change), screw
    centre, centre_then = now.mean(axis=0), then.mean(axis=0)
    change = (centre - centre_then) - (c1 - c0) if err_spin <= limit * motion else None
    return spin_affine(rotation, centre, centre - centre_then, change), turned


@njit(cache=True, nogil=True)
def _continued_paths(now, then, earlier, idx, r0, t0, screw, turned, out):  # pragma: no cover - compiled
    """``part_motion``'s two paths of the interval before continued over the last one: ``screw`` = r0 then + t0,
    ``turned`` = r0 (then - c1) + 2 c1 - c0 (c1, c0: the mean of ``then``, ``earlier`` over ``idx``); ``out``
    = (mean |screw - now|, mean |turned - now|, mean |now - then| over ``idx``, c1, c0)."""
    m = idx.size
    for i in range(m):
        for c in range(3):
            out[3 + c] += then[idx[i], c] / m
            out[6 + c] += earlier[idx[i], c] / m
    for i in range(now.shape[0]):
        for c in range(3):
            screw[i, c] = r0[c, 0] * then[i, 0] + r0[c, 1] * then[i, 1] + r0[c, 2] * then[i, 2] + t0[c]
            turned[i, c] = (r0[c, 0] * (then[i, 0] - out[3]) + r0[c, 1] * (then[i, 1] - out[4])
                            + r0[c, 2] * (then[i, 2] - out[5]) + 2.0 * out[3 + c] - out[6 + c])
    for i in range(m):
        j = idx[i]
        a = 0.0
        b = 0.0
        d = 0.0
        for c in range(3):
            a += (screw[j, c] - now[j, c]) ** 2
            b += (turned[j, c] - now[j, c]) ** 2
            d += (now[j, c] - then[j, c]) ** 2
        out[0] += math.sqrt(a) / m
        out[1] += math.sqrt(b) / m
        out[2] += math.sqrt(d) / m


@njit(cache=True, nogil=True)
def _rotation_log_into(r, w):  # pragma: no cover - compiled
    """``rotation_log`` compiled, into ``w`` (3,)."""
    cos = min(1.0, max(-1.0, (r[0, 0] + r[1, 1] + r[2, 2] - 1.0) / 2.0))
    theta = math.acos(cos)
    w[0], w[1], w[2] = r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]
    if theta < 1e-6:
        for c in range(3):
            w[c] = 0.5 * w[c]
    elif math.pi - theta > 1e-4:
        f = theta / (2.0 * math.sin(theta))
        for c in range(3):
            w[c] = f * w[c]
    else:  # near a half turn: the axis is the largest column of (R + I) / 2, its sign from vee
        top = 0
        for c in range(1, 3):
            if r[c, c] > r[top, top]:
                top = c
        axis = np.empty(3)
        for c in range(3):
            axis[c] = 0.5 * (r[c, top] + (1.0 if c == top else 0.0))
        norm = math.sqrt(axis[0] ** 2 + axis[1] ** 2 + axis[2] ** 2)
        sign = 1.0 if axis[0] * w[0] + axis[1] * w[1] + axis[2] * w[2] >= 0 else -1.0
        for c in range(3):
            w[c] = theta * (sign * (axis[c] / norm))


@njit(cache=True, nogil=True)
def _so3_series(w, out, jacobian):  # pragma: no cover - compiled
    """``rotation_exp(w)`` (``jacobian`` False) or ``_left_jacobian(w)`` (True) into ``out`` (3, 3):
    I + a K + b K^2 with K = hat(w)."""
    theta = math.sqrt(w[0] ** 2 + w[1] ** 2 + w[2] ** 2)
    small = theta < (1e-6 if jacobian else 1e-12)
    if jacobian:
        a = 0.5 if small else (1.0 - math.cos(theta)) / theta ** 2
        b = 1.0 if small else (theta - math.sin(theta)) / theta ** 3
        d = 6.0 if small else 1.0
    else:
        a = 1.0 if small else math.sin(theta) / theta
        b = 0.0 if small else (1.0 - math.cos(theta)) / theta ** 2
        d = 1.0
    k = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    for c in range(3):
        for e in range(3):
            kk = k[c, 0] * k[0, e] + k[c, 1] * k[1, e] + k[c, 2] * k[2, e]
            out[c, e] = (1.0 if c == e else 0.0) + a * k[c, e] + b * kk / d


@njit(cache=True, nogil=True)
def _se3_log_into(rotation, translation, twist):  # pragma: no cover - compiled
    """``se3_log`` compiled, into ``twist`` (6,): rho solves J rho = t by elimination with partial pivoting."""
    _rotation_log_into(rotation, twist[:3])
    m = np.empty((3, 4))
    _so3_series(twist[:3], m[:, :3], True)
    for c in range(3):
        m[c, 3] = translation[c]
    for c in range(3):
        top = c
        for e in range(c + 1, 3):
            if abs(m[e, c]) > abs(m[top, c]):
                top = e
        for e in range(4):
            m[c, e], m[top, e] = m[top, e], m[c, e]
        for e in range(c + 1, 3):
            f = m[e, c] / m[c, c]
            for q in range(c, 4):
                m[e, q] -= f * m[c, q]
    for c in range(2, -1, -1):
        v = m[c, 3]
        for e in range(c + 1, 3):
            v -= m[c, e] * twist[3 + e]
        twist[3 + c] = v / m[c, c]


@njit(cache=True, nogil=True)
def _node_affine(rotations, translations, affine):  # pragma: no cover - compiled
    """``path_affine`` compiled, from the path's transforms at the two ``NODES`` (``rotations`` (2, 3, 3),
    ``translations`` (2, 3)) into ``affine`` (2, 3, 4): V then A, matrix then offset."""
    a, b = NODES
    for c in range(3):
        for e in range(4):
            if e < 3:
                da = rotations[0, c, e] - (1.0 if c == e else 0.0)
                db = rotations[1, c, e] - (1.0 if c == e else 0.0)
            else:
                da, db = translations[0, c], translations[1, c]
            acc = 2.0 * (db / b - da / a) / (b - a)
            affine[1, c, e] = acc
            affine[0, c, e] = da / a - 0.5 * (a + 1.0) * acc


@njit(cache=True, nogil=True)
def _screw_into(twist, change, affine):  # pragma: no cover - compiled
    """``screw_affine`` compiled, into ``affine`` (2, 3, 4)."""
    rotations, translations = np.empty((2, 3, 3)), np.empty((2, 3))
    step, jacobian = np.empty(6), np.empty((3, 3))
    for node in range(2):
        s = NODES[node]
        for c in range(6):
            step[c] = s * twist[c] + 0.5 * s * (s + 1.0) * change[c]
        _so3_series(step[:3], rotations[node], False)
        _so3_series(step[:3], jacobian, True)
        for c in range(3):
            translations[node, c] = jacobian[c, 0] * step[3] + jacobian[c, 1] * step[4] + jacobian[c, 2] * step[5]
    _node_affine(rotations, translations, affine)


@njit(cache=True, nogil=True)
def _spin_into(rotation, centre, velocity, change, affine):  # pragma: no cover - compiled
    """``spin_affine`` compiled, into ``affine`` (2, 3, 4)."""
    w, step = np.empty(3), np.empty(3)
    _rotation_log_into(rotation, w)
    rotations, translations = np.empty((2, 3, 3)), np.empty((2, 3))
    for node in range(2):
        s = NODES[node]
        for c in range(3):
            step[c] = s * w[c]
        r = rotations[node]
        _so3_series(step, r, False)
        for c in range(3):
            translations[node, c] = (centre[c] + s * velocity[c] + 0.5 * s * (s + 1.0) * change[c]
                                     - (r[c, 0] * centre[0] + r[c, 1] * centre[1] + r[c, 2] * centre[2]))
    _node_affine(rotations, translations, affine)


@njit(cache=True, nogil=True)
def _part_path(now, then, earlier, seen, scale, members, rotation, translation, base, threshold, limit, hypotheses,
               rounds, affine, hindcast):  # pragma: no cover - compiled
    """``part_motion`` compiled for the part of the points ``members`` (increasing): its path into ``affine``
    (2, 3, 4); returns whether the interval before gave a prediction of frame n, then in ``hindcast[k]`` for
    ``members[k]``."""
    m = members.size
    twist, change = np.empty(6), np.zeros(6)
    _se3_log_into(rotation, translation, twist)
    idx = members[seen[members]]
    if idx.size < max(3, m // 2):
        _screw_into(twist, change, affine)
        return False
    r0, t0, fits = np.empty((3, 3)), np.empty(3), np.empty(idx.size, np.bool_)
    kept = _robust_members(earlier, then, scale, idx, base, True, rotation, translation, hypotheses, rounds,
                           threshold, r0, t0, fits)
    if kept < max(8, idx.size // 10):  # frame n-k's velocities are guesses where n-2k did not see
        _screw_into(twist, change, affine)
        return False
    local = np.empty(kept, np.int64)  # the fitted points, as positions among the members
    n = 0
    f = 0
    for k in range(m):
        if seen[members[k]]:
            if fits[f]:
                local[n] = k
                n += 1
            f += 1
    screw, turned, sums = np.empty((m, 3)), np.empty((m, 3)), np.zeros(9)
    now_p, then_p = now[members], then[members]
    _continued_paths(now_p, then_p, earlier[members], local, r0, t0, screw, turned, sums)
    err_screw, err_spin, motion = sums[0], sums[1], sums[2]
    if err_screw <= err_spin:
        if err_screw <= limit * motion:
            _se3_log_into(r0, t0, change)
            for c in range(6):
                change[c] = twist[c] - change[c]
        _screw_into(twist, change, affine)
        hindcast[:m] = screw
        return True
    centre, centre_then, spin_change = np.zeros(3), np.zeros(3), np.zeros(3)
    for k in range(m):
        for c in range(3):
            centre[c] += now_p[k, c]
            centre_then[c] += then_p[k, c]
    for c in range(3):
        centre[c] /= m
        centre_then[c] /= m
        if err_spin <= limit * motion:
            spin_change[c] = (centre[c] - centre_then[c]) - (sums[3 + c] - sums[6 + c])
    _spin_into(rotation, centre, centre - centre_then, spin_change, affine)
    hindcast[:m] = turned
    return True


@njit(cache=True, nogil=True)
def _part_paths(part, rotations, translations, now, then, earlier, seen, scale, predicted, intrinsics, threshold,
                limit, max_turn, hypotheses, rounds, take, affines):  # pragma: no cover - compiled
    """``part_paths`` compiled: per part (``part`` (N,) each point's part, -1: none) turning by at most
    ``max_turn`` radians, ``_part_path`` with the key (0, j) (j: its number among those parts), taken (``take``)
    where its prediction of frame n beats ``predicted``'s in frame n's pixels (``rigid_explains_better``),
    ``predicted`` then replaced by it at its points."""
    count = rotations.shape[0]
    offsets = np.zeros(count + 1, np.int64)
    for i in range(part.size):
        if part[i] >= 0:
            offsets[part[i] + 1] += 1
    for j in range(count):
        offsets[j + 1] += offsets[j]
    order, fill = np.empty(offsets[count], np.int64), offsets[:count].copy()
    for i in range(part.size):
        if part[i] >= 0:
            order[fill[part[i]]] = i
            fill[part[i]] += 1
    w = np.empty(3)
    hindcast = np.empty((part.size, 3))
    numbered = 0
    for j in range(count):
        take[j] = False
        _rotation_log_into(rotations[j], w)
        if math.sqrt(w[0] ** 2 + w[1] ** 2 + w[2] ** 2) > max_turn:  # faster turns alias: lines
            continue
        members = order[offsets[j]:offsets[j + 1]]
        m = members.size
        base = _fold(_fold(np.uint64(0), 0), numbered)
        numbered += 1
        if not _part_path(now, then, earlier, seen, scale, members, rotations[j], translations[j], base, threshold,
                          limit, hypotheses, rounds, affines[j], hindcast):
            continue
        now_p = now[members]
        rigid, linear = np.empty(m), np.empty(m)
        _hindcast_errors(now_p, hindcast[:m], intrinsics, rigid)
        _hindcast_errors(now_p, predicted[members], intrinsics, linear)
        a = 0.0
        b = 0.0
        for k in range(m):
            if seen[members[k]] and np.isfinite(rigid[k]) and np.isfinite(linear[k]):
                a += rigid[k]
                b += linear[k]
        if a <= b:
            take[j] = True
            for k in range(m):
                for c in range(3):
                    predicted[members[k], c] = hindcast[k, c]


@dataclass(frozen=True)
class PartPaths:
    """Rigid parts with their paths, stacked (``part_paths``; ``apply_parts``' input), in the order of their
    groups: ``group`` (P,) int64, ``rotation`` (P, 3, 3), ``translation`` (P, 3) of their interval transforms,
    ``affine`` (P, 2, 3, 4) their paths' ``path_affine`` (V then A; the 3x3 matrix, then the offset)."""

    group: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    affine: np.ndarray

    @staticmethod
    def stack(parts: list, affines: list) -> "PartPaths":
        """The table of ``parts`` (``RigidPart``) and their ``path_affine`` tuples ``affines``."""
        table = np.zeros((len(parts), 2, 3, 4))
        for j, (vm, vt, am, at) in enumerate(affines):
            table[j, 0, :, :3], table[j, 0, :, 3], table[j, 1, :, :3], table[j, 1, :, 3] = vm, vt, am, at
        return PartPaths(np.array([p.group for p in parts], dtype=np.int64),
                         np.array([p.rotation for p in parts], dtype=np.float64).reshape(-1, 3, 3),
                         np.array([p.translation for p in parts], dtype=np.float64).reshape(-1, 3), table)


def part_paths(table: PartTable, now: np.ndarray, then: np.ndarray, earlier: np.ndarray, seen: np.ndarray,
               scale: np.ndarray, predicted: np.ndarray, intrinsics: np.ndarray, *, threshold: float = 1.0,
               limit: float = 0.5, max_turn: float = MAX_TURN) -> PartPaths:
    """The paths of the parts of ``table`` (``find_parts`` of the points ``now`` (N, 3) at n, ``then`` at n-k)
    that turn by at most ``max_turn`` per interval, and keep them where they explained the last interval:
    each part's ``part_motion`` (key (0, j), j its number among the parts within ``max_turn``; ``earlier`` the
    points at n-2k where ``seen``), taken where its prediction of frame n from the interval before beats the
    points' own, ``predicted`` (N, 3) (``rigid_explains_better``); ``predicted`` is then updated in place to
    the taken parts' predictions. Compiled, in one call; ``part_paths_reference`` is its numpy oracle."""
    if predicted.dtype != np.float64 or not predicted.flags.c_contiguous or predicted.shape != (len(table.part), 3):
        raise InputError(f"must be a C-contiguous float64 ({len(table.part)}, 3) array (updated in place), got "
                         f"{predicted.dtype} {predicted.shape}", field="predicted")
    count = len(table.group)
    take, affines = np.zeros(count, np.bool_), np.zeros((count, 2, 3, 4))
    _part_paths(np.ascontiguousarray(table.part, np.int64), np.ascontiguousarray(table.rotation, np.float64),
                np.ascontiguousarray(table.translation, np.float64), np.ascontiguousarray(now, np.float64),
                np.ascontiguousarray(then, np.float64), np.ascontiguousarray(earlier, np.float64),
                np.ascontiguousarray(seen, np.bool_), np.ascontiguousarray(scale, np.float64), predicted,
                np.asarray(intrinsics, np.float64), float(threshold), float(limit), float(max_turn), HYPOTHESES, ROUNDS,
                take, affines)
    return PartPaths(table.group[take], table.rotation[take], table.translation[take], affines[take])


def part_paths_reference(table: PartTable, now: np.ndarray, then: np.ndarray, earlier: np.ndarray,
                         seen: np.ndarray, scale: np.ndarray, predicted: np.ndarray, intrinsics: np.ndarray, *,
                         threshold: float = 1.0, limit: float = 0.5, max_turn: float = MAX_TURN) -> PartPaths:
    """``part_paths`` part by part with ``part_motion`` and ``rigid_explains_better`` (the test oracle)."""
    kept, affines, j = [], [], 0
    for p, g in enumerate(table.group):
        if np.linalg.norm(rotation_log(table.rotation[p])) > max_turn:
            continue
        m = np.flatnonzero(table.part == p)
        affine, hindcast = part_motion(now[m], then[m], earlier[m], seen[m], table.rotation[p],
                                       table.translation[p], scale[m], (0, j), threshold=threshold, limit=limit)
        j += 1
        if hindcast is None or not rigid_explains_better(now[m], hindcast, predicted[m], seen[m], intrinsics):
            continue
        predicted[m] = hindcast
        kept.append(RigidPart(m, table.rotation[p], table.translation[p], int(g)))
        affines.append(affine)
    return PartPaths.stack(kept, affines)


@njit(cache=True, nogil=True, inline="always")
def _first_part(i, now, speed, depth, g, starts, rotations, translations, focal, limit):  # pragma: no cover
    """The first part of group ``g`` whose transform explains moving pixel i within ``limit`` pixels, or -1."""
    for j in range(starts[g], starts[g + 1]):
        r2 = 0.0
        for c in range(3):
            moved = translations[j, c] - now[i, c]
            for e in range(3):
                moved += rotations[j, c, e] * (now[i, e] - speed[i, e])
            r2 += moved * moved
        if math.sqrt(r2) * focal / depth[i] > limit:
            continue
        return j
    return -1


@njit(cache=True, nogil=True, inline="always")
def _row_motion(i, j, now, speed, acceleration, has_acceleration, affine, out_v, row_v, out_a,
                row_a):  # pragma: no cover - compiled
    """Moving pixel i's V and A into ``out_v[row_v]``, ``out_a[row_a]``: part j's path, or (j < 0) its own."""
    for c in range(3):
        if j < 0:
            out_v[row_v, c] = speed[i, c]
            out_a[row_a, c] = acceleration[i, c] if has_acceleration else 0.0
            continue
        v = affine[j, 0, c, 3]
        a = affine[j, 1, c, 3]
        for e in range(3):
            v += affine[j, 0, c, e] * now[i, e]
            a += affine[j, 1, c, e] * now[i, e]
        out_v[row_v, c] = v
        out_a[row_a, c] = a


@njit(cache=True, nogil=True)
def _apply_parts(now, speed, depth, labels, acceleration, has_acceleration, starts, rotations, translations, affine,
                 focal, limit, offset, out_v, out_a, regions):  # pragma: no cover - compiled
    """``apply_parts`` compiled: per moving pixel the first part of its group whose transform explains it."""
    for i in range(now.shape[0]):
        g = labels[i]
        j = _first_part(i, now, speed, depth, g, starts, rotations, translations, focal, limit)
        regions[i] = g if j < 0 else offset + j
        _row_motion(i, j, now, speed, acceleration, has_acceleration, affine, out_v, i, out_a, i)


@njit(cache=True, nogil=True)
def _kept_part_motion(now, speed, depth, labels, acceleration, has_acceleration, starts, rotations, translations,
                      affine, focal, limit, offset, moving, keep, velocity, moving_out, acceleration_out, own,
                      own_rows, lo, hi):  # pragma: no cover - compiled
    """``kept_part_motion`` compiled for the moving pixels [lo, hi): ``_apply_parts`` per pixel, its kept rows
    scattered and compacted in the same pass (rows lo, lo + 1, ..); with ``own``, the kept pixels that keep
    their own motion get no acceleration row but their row in ``own_rows`` (from lo on). Returns (the count of
    kept rows, of those)."""
    n = 0
    m = 0
    for i in range(lo, hi):
        g = labels[i]
        j = _first_part(i, now, speed, depth, g, starts, rotations, translations, focal, limit)
        if not keep[g if j < 0 else offset + j]:
            continue
        p = moving[i]
        row = lo + n
        if j < 0 and own:
            for c in range(3):
                velocity[p, c] = speed[i, c]
            own_rows[lo + m] = row
            m += 1
        else:
            _row_motion(i, j, now, speed, acceleration, has_acceleration, affine, velocity, p, acceleration_out, row)
        moving_out[row] = p
        n += 1
    return n, m


def _part_tables(paths: PartPaths, count: int):
    """``apply_parts``' stacks: each group's first part (``starts`` (count + 1,)), the parts' rotations,
    translations and affines (``paths``), contiguous."""
    starts = np.searchsorted(paths.group, np.arange(count + 1)).astype(np.int64)
    return (starts, np.ascontiguousarray(paths.rotation, np.float64),
            np.ascontiguousarray(paths.translation, np.float64), np.ascontiguousarray(paths.affine, np.float64))


def apply_parts(now: np.ndarray, speed: np.ndarray, depth: np.ndarray, labels: np.ndarray, count: int, paths: PartPaths,
                focal: float, limit: float,
                acceleration: Optional[np.ndarray] = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The moving pixels' motion with their rigid parts' paths: (V (M, 3), A (M, 3) float32, regions (M,) int64).

    Every moving pixel (``now`` (M, 3), its velocity ``speed``, depth ``depth`` (M,), group ``labels`` in
    [0, ``count``)) that the transform of a part of its group (``paths``, in the order of their groups) explains
    within ``limit`` pixels (residual times ``focal / depth``) takes that part's path: the V and A of its
    ``affine`` entry (``path_affine``), its region the part's number plus ``count`` (the regions of the
    fall-back). The others keep their own velocity, their ``acceleration`` row (or 0) and their group as
    region. Compiled; ``apply_parts_reference`` is its numpy oracle."""
    m = len(labels)
    starts, rotations, translations, table = _part_tables(paths, count)
    has_acceleration = acceleration is not None
    acceleration = np.zeros((1, 3), np.float32) if acceleration is None else acceleration
    out_v, out_a, regions = np.empty((m, 3), np.float32), np.empty((m, 3), np.float32), np.empty(m, np.int64)
    _apply_parts(np.ascontiguousarray(now, np.float64), np.ascontiguousarray(speed, np.float64),
                 np.ascontiguousarray(depth, np.float64), np.ascontiguousarray(labels, np.int64),
                 np.ascontiguousarray(acceleration, np.float32), has_acceleration, starts, rotations, translations,
                 table, float(focal), float(limit), int(count), out_v, out_a, regions)
    return out_v, out_a, regions


def apply_parts_reference(now: np.ndarray, speed: np.ndarray, depth: np.ndarray, labels: np.ndarray, count: int,
                          paths: PartPaths, focal: float, limit: float,
                          acceleration: Optional[np.ndarray] = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``apply_parts`` in numpy, part by part (the test oracle; the sums in the kernel's order)."""
    _, rotations, translations, table = _part_tables(paths, count)
    out_v = speed.astype(np.float32)
    out_a = np.zeros_like(out_v) if acceleration is None else np.array(acceleration, np.float32)
    regions = np.array(labels, np.int64)
    taken = np.zeros(len(labels), bool)
    for j, group in enumerate(paths.group):
        on = np.flatnonzero((labels == group) & ~taken)
        p, v = now[on], speed[on]
        r2 = np.zeros(on.size)
        for c in range(3):
            moved = translations[j, c] - p[:, c]
            for e in range(3):
                moved = moved + rotations[j, c, e] * (p[:, e] - v[:, e])
            r2 = r2 + moved * moved
        on = on[~(np.sqrt(r2) * focal / depth[on] > limit)]
        for c in range(3):
            vel, acc = np.full(on.size, table[j, 0, c, 3]), np.full(on.size, table[j, 1, c, 3])
            for e in range(3):
                vel = vel + table[j, 0, c, e] * now[on, e]
                acc = acc + table[j, 1, c, e] * now[on, e]
            out_v[on, c], out_a[on, c] = vel, acc
        regions[on], taken[on] = count + j, True
    return out_v, out_a, regions


def kept_part_motion(shape: tuple[int, int], moving: np.ndarray, now: np.ndarray, speed: np.ndarray,
                     depth: np.ndarray, labels: np.ndarray, count: int, paths: PartPaths, focal: float,
                     limit: float, acceleration: Optional[np.ndarray], keep: np.ndarray,
                     change: Optional[tuple] = None,
                     out: Optional[np.ndarray] = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``apply_parts`` of the moving pixels ``moving`` (flat indices into ``shape``), keeping those whose region
    is kept (``keep`` (count + parts,) bool): (velocity (H, W, 3) float32, 0 elsewhere, the kept pixels
    (N,), their acceleration (N, 3) float32), in one pass. With ``change`` (``motion.velocity_change_args``)
    in place of ``acceleration``, the change of velocity is computed there for the kept pixels that keep their
    own motion only (the others take their part's path or the camera-only warp): ``velocity_change``'s rows of
    those pixels. ``out``: an all-zero (H, W, 3) float32 array (contiguous) the velocity is written into and
    returned as, in place of a new one (a caller can zero it beside other work). Compiled;
    ``kept_part_motion_reference`` is its numpy oracle."""
    h, w = shape
    starts, rotations, translations, table = _part_tables(paths, count)
    has_acceleration = acceleration is not None
    acceleration = np.zeros((1, 3), np.float32) if acceleration is None else acceleration
    if out is None:
        velocity = np.zeros((h, w, 3), np.float32)  # pages without moving pixels stay untouched
    elif out.shape != (h, w, 3) or out.dtype != np.float32 or not (out.flags.c_contiguous and out.flags.writeable):
        raise InputError(f"must be a writeable contiguous float32 ({h}, {w}, 3) array, got {out.dtype} {out.shape}",
                         field="out")
    else:
        velocity = out
    moving_out, acceleration_out = np.empty(len(moving), np.int64), np.empty((len(moving), 3), np.float32)
    own_rows = np.empty(len(moving) if change is not None else 0, np.int64)
    args = (np.ascontiguousarray(now, np.float64), np.ascontiguousarray(speed, np.float64),
            np.ascontiguousarray(depth, np.float64), np.ascontiguousarray(labels, np.int64),
            np.ascontiguousarray(acceleration, np.float32), has_acceleration, starts, rotations, translations, table,
            float(focal), float(limit), int(count), np.ascontiguousarray(moving, np.int64),
            np.ascontiguousarray(keep, np.bool_), velocity.reshape(-1, 3), moving_out, acceleration_out,
            change is not None, own_rows)

    def run(lo: int, hi: int) -> int:  # rows [lo, lo + n) of the outputs; each pixel's rows are its own
        n, m = _kept_part_motion(*args, lo, hi)
        if m:  # the change of velocity of the pixels that keep their own motion, and of those only
            rows = own_rows[lo:lo + m]
            own = np.empty((m, 3), np.float32)
            kernels.velocity_change(*change[:3], moving_out[rows], *change[3:], own)
            acceleration_out[rows] = own
        return n

    ranges = kernels.split_points(len(moving))
    counts = kernels.run_ranges(run, ranges)
    if all(n == hi - lo for (lo, hi), n in zip(ranges[:-1], counts)):  # every range but the last kept all: in place
        return velocity, moving_out[:ranges[-1][0] + counts[-1]], acceleration_out[:ranges[-1][0] + counts[-1]]
    return (velocity, np.concatenate([moving_out[lo:lo + n] for (lo, _), n in zip(ranges, counts)]),
            np.concatenate([acceleration_out[lo:lo + n] for (lo, _), n in zip(ranges, counts)]))


def kept_part_motion_reference(shape: tuple[int, int], moving: np.ndarray, now: np.ndarray, speed: np.ndarray,
                               depth: np.ndarray, labels: np.ndarray, count: int, paths: PartPaths,
                               focal: float, limit: float, acceleration: Optional[np.ndarray],
                               keep: np.ndarray, change: Optional[tuple] = None) -> tuple[np.ndarray, np.ndarray,
                                                                                         np.ndarray]:
    """``kept_part_motion`` in numpy: ``velocity_change`` of every moving pixel (with ``change``),
    ``apply_parts_reference``, then the kept rows by boolean masks."""
    if change is not None:
        acceleration = np.empty((len(moving), 3), np.float32)
        kernels.velocity_change(*change[:3], np.asarray(moving, np.int64), *change[3:], acceleration)
    rows_v, rows_a, regions = apply_parts_reference(now, speed, depth, labels, count, paths, focal, limit,
                                                    acceleration)
    kept = np.asarray(keep, bool)[regions]
    velocity = np.zeros(tuple(shape) + (3,), np.float32)
    velocity.reshape(-1, 3)[moving[kept]] = rows_v[kept]
    return velocity, np.asarray(moving, np.int64)[kept], rows_a[kept]


@njit(cache=True, nogil=True)
def _vector_end(vectors, p, width):  # pragma: no cover - compiled
    y = p // width
    x = p - y * width
    return x + 0.5 + np.float64(vectors[y, x, 0]), y + 0.5 + np.float64(vectors[y, x, 1])


@njit(cache=True, nogil=True)
def _refined_before(before, vectors, moving, relative, prev_depth, k_inv, smooth, out):  # pragma: no cover
    """``refined_before`` compiled, point by point (``refined_before_reference`` states it)."""
    w = vectors.shape[1]
    ph, pw = prev_depth.shape
    seen = np.empty(3)
    for i in range(moving.size):
        qx, qy = _vector_end(vectors, moving[i], w)
        for c in range(3):
            out[i, c] = before[i, c]
        fx, fy = qx - 0.5, qy - 0.5
        x0, y0 = math.floor(fx), math.floor(fy)
        if not (x0 >= 0 and x0 + 1 < pw and y0 >= 0 and y0 + 1 < ph):
            continue
        xi, yi = int(x0), int(y0)
        ax, ay = fx - xi, fy - yi
        bz = (before[i, 0] * relative[2, 0] + before[i, 1] * relative[2, 1] + before[i, 2] * relative[2, 2]
              + relative[2, 3])
        inverse = 0.0
        ok = True
        for corner in range(4):
            dy, dx = corner // 2, corner % 2
            weight = (ax if dx else 1.0 - ax) * (ay if dy else 1.0 - ay)
            c = np.float64(prev_depth[yi + dy, xi + dx])
            if not (np.isfinite(c) and max(c / bz, bz / c) <= smooth):
                ok = False
                break
            inverse += weight / c
        if not ok or not inverse > 0:
            continue
        depth = 1.0 / inverse
        for c in range(3):
            seen[c] = (qx * k_inv[c, 0] + qy * k_inv[c, 1] + k_inv[c, 2]) * depth - relative[c, 3]
        for c in range(3):  # R^T (p - t): frame n's axes
            out[i, c] = seen[0] * relative[0, c] + seen[1] * relative[1, c] + seen[2] * relative[2, c]


def refined_before(before: np.ndarray, vectors: np.ndarray, moving: np.ndarray, relative: np.ndarray,
                   prev_depth: np.ndarray, prev_intrinsics: np.ndarray, *, smooth: float = 1.1) -> np.ndarray:
    """The moving points' positions at frame n-k (M, 3) with their depth read between frame n-k's pixels.

    ``before`` (frame n's axes) took its depth from one of the 4 pixels of frame n-k around the vector's end q
    (``scene_velocity``): off by up to the depth's change over a pixel, a millimetre-to-centimetre error that
    a rigid fit on a slanted face would see as a pixel of residual. Where the 4 pixels all lie within the ratio
    ``smooth`` of that depth (one smooth surface), the depth is instead their bilinear blend at q in inverse
    depth (exact on a plane); elsewhere (silhouettes, the frame's edge) ``before`` is kept. ``relative``: frame
    n's camera -> frame n-k's camera (4x4). Compiled; ``refined_before_reference`` is its numpy oracle."""
    out = np.empty((len(moving), 3))
    _refined_before(np.ascontiguousarray(before, np.float64), np.ascontiguousarray(vectors),
                    np.ascontiguousarray(moving, np.int64), np.ascontiguousarray(relative, np.float64),
                    np.ascontiguousarray(prev_depth),
                    np.linalg.inv(np.asarray(prev_intrinsics, np.float64)), float(smooth), out)
    return out


@njit(cache=True, nogil=True)
def _previous_positions(vectors, moving, before, relative, prev_depth, prev_velocity, interval_ratio, band,
                        has_first, first_depth, first_k, view, check, earlier, valid):  # pragma: no cover
    """``previous_positions`` compiled, point by point (``previous_positions_reference`` states it)."""
    w = vectors.shape[1]
    ph, pw = prev_depth.shape
    fh, fw = first_depth.shape
    there = np.empty(3)
    for i in range(moving.size):
        qx, qy = _vector_end(vectors, moving[i], w)
        inside = qx >= 0 and qx < pw and qy >= 0 and qy < ph
        xi = int(qx) if inside else 0
        yi = int(qy) if inside else 0
        bz = (before[i, 0] * relative[2, 0] + before[i, 1] * relative[2, 1] + before[i, 2] * relative[2, 2]
              + relative[2, 3])
        seen = np.float64(prev_depth[yi, xi])
        ok = inside and bz > 0 and np.isfinite(seen) and max(seen / bz, bz / seen) <= band
        for c in range(3):  # R^T v: frame n's axes
            v = (np.float64(prev_velocity[yi, xi, 0]) * relative[0, c]
                 + np.float64(prev_velocity[yi, xi, 1]) * relative[1, c]
                 + np.float64(prev_velocity[yi, xi, 2]) * relative[2, c])
            earlier[i, c] = before[i, c] - v * interval_ratio
        if ok and has_first:
            for c in range(3):
                there[c] = (earlier[i, 0] * view[c, 0] + earlier[i, 1] * view[c, 1] + earlier[i, 2] * view[c, 2]
                            + view[c, 3])
            ok = there[2] > 1e-9
            if ok:
                ax = first_k[0, 0] * there[0] / there[2] + first_k[0, 1] * there[1] / there[2] + first_k[0, 2]
                ay = first_k[1, 1] * there[1] / there[2] + first_k[1, 2]
                ok = np.isfinite(ax) and np.isfinite(ay) and ax >= 0 and ax < fw and ay >= 0 and ay < fh
                if ok:
                    seen0 = np.float64(first_depth[int(ay), int(ax)])
                    ok = max(seen0 / there[2], there[2] / seen0) <= check
        valid[i] = ok


def previous_positions(depth: np.ndarray, vectors: np.ndarray, moving: np.ndarray, before: np.ndarray,
                       relative: np.ndarray, prev_depth: np.ndarray, prev_velocity: np.ndarray,
                       interval_ratio: float = 1.0, band: float = 1.5, first=None,
                       check: float = 1.05) -> tuple[np.ndarray, np.ndarray]:
    """Each moving pixel's position one interval before frame n-k (at n-2k), in frame n's camera axes:
    (positions (M, 3) float64, valid (M,) bool).

    ``before`` (M, 3) are the points' positions at n-k (frame n's axes); frame n-k's velocity ``prev_velocity``
    (its own camera axes, per its interval) is read at the pixel of frame n-k the vector lands in (nearest),
    where that pixel shows the point (its depth within the ratio ``band`` of the point's depth there),
    rotated into frame n's axes (``relative``: frame n's camera -> frame n-k's camera, 4x4) and scaled by
    ``interval_ratio`` (the last interval over the one before); invalid elsewhere (unseen, off screen).
    ``first`` = (depth (h, w), intrinsics, 4x4 frame n's camera -> frame n-2k's camera) checks each position
    against frame n-2k itself: valid only where frame n-2k's depth at its pixel is within the ratio ``check``
    of its depth there (frame n-k's velocity is a guess where frame n-2k did not see the point: a face
    turning into view). Compiled; ``previous_positions_reference`` is its numpy oracle."""
    sizes: dict = {}
    checked_array(depth, "depth", ("H", "W"), sizes)
    vectors = checked_array(vectors, "motion_vectors", ("H", "W", 2), sizes)
    prev_sizes: dict = {}
    prev_depth = checked_array(prev_depth, "prev_depth", ("h", "w"), prev_sizes)
    prev_velocity = checked_array(prev_velocity, "prev_velocity", ("h", "w", 3), prev_sizes)
    relative = checked_matrix(relative, "relative", 4)
    earlier, valid = np.empty((len(moving), 3)), np.empty(len(moving), bool)
    has_first = first is not None
    if not has_first:
        first = (np.zeros((1, 1), np.float32), np.eye(3), np.eye(4))
    _previous_positions(np.ascontiguousarray(vectors), np.ascontiguousarray(moving, np.int64),
                        np.ascontiguousarray(before, np.float64), relative, np.ascontiguousarray(prev_depth),
                        np.ascontiguousarray(prev_velocity), float(interval_ratio), float(band), has_first,
                        np.ascontiguousarray(first[0], np.float32), np.asarray(first[1], np.float64),
                        np.asarray(first[2], np.float64), float(check), earlier, valid)
    return earlier, valid


def refined_before_reference(before: np.ndarray, vectors: np.ndarray, moving: np.ndarray, relative: np.ndarray,
                             prev_depth: np.ndarray, prev_intrinsics: np.ndarray, *,
                             smooth: float = 1.1) -> np.ndarray:
    """``refined_before`` in numpy, by arrays (the test oracle; that docstring states it)."""
    h, w = vectors.shape[:2]
    ph, pw = prev_depth.shape
    y, x = np.divmod(np.asarray(moving, np.int64), w)
    qx = x + 0.5 + vectors[y, x, 0].astype(np.float64)
    qy = y + 0.5 + vectors[y, x, 1].astype(np.float64)
    fx, fy = qx - 0.5, qy - 0.5
    x0, y0 = np.floor(fx), np.floor(fy)
    ok = (x0 >= 0) & (x0 + 1 < pw) & (y0 >= 0) & (y0 + 1 < ph)
    x0 = np.where(ok, x0, 0).astype(np.int64)
    y0 = np.where(ok, y0, 0).astype(np.int64)
    ax, ay = fx - x0, fy - y0
    bz = before @ relative[2, :3] + relative[2, 3]
    inverse = np.zeros(len(x0))
    for dy, dx, weight in ((0, 0, (1 - ax) * (1 - ay)), (0, 1, ax * (1 - ay)), (1, 0, (1 - ax) * ay), (1, 1, ax * ay)):
        c = prev_depth[y0 + dy, x0 + dx].astype(np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            ok &= np.isfinite(c) & (np.maximum(c / bz, bz / c) <= smooth)
            inverse += weight / c
    ok &= inverse > 0
    depth = np.where(ok, 1.0 / np.where(ok, inverse, 1.0), 0.0)
    k_inv = np.linalg.inv(np.asarray(prev_intrinsics, np.float64))
    seen = transform_points(np.stack([qx, qy, np.ones_like(qx)], axis=-1), k_inv) * depth[:, None]  # n-k's camera
    back = transform_points(seen - relative[:3, 3], relative[:3, :3].T)  # into frame n's axes (R^T (p - t))
    return np.where(ok[:, None], back, before)


def previous_positions_reference(depth: np.ndarray, vectors: np.ndarray, moving: np.ndarray, before: np.ndarray,
                                 relative: np.ndarray, prev_depth: np.ndarray, prev_velocity: np.ndarray,
                                 interval_ratio: float = 1.0, band: float = 1.5, first=None,
                                 check: float = 1.05) -> tuple[np.ndarray, np.ndarray]:
    """``previous_positions`` in numpy, by arrays (the test oracle; that docstring states it)."""
    sizes: dict = {}
    depth = checked_array(depth, "depth", ("H", "W"), sizes)
    vectors = checked_array(vectors, "motion_vectors", ("H", "W", 2), sizes)
    prev_sizes: dict = {}
    prev_depth = checked_array(prev_depth, "prev_depth", ("h", "w"), prev_sizes)
    prev_velocity = checked_array(prev_velocity, "prev_velocity", ("h", "w", 3), prev_sizes)
    relative = checked_matrix(relative, "relative", 4)
    h, w = depth.shape
    ph, pw = prev_depth.shape
    y, x = np.divmod(np.asarray(moving, np.int64), w)
    qx = x + 0.5 + vectors[y, x, 0].astype(np.float64)
    qy = y + 0.5 + vectors[y, x, 1].astype(np.float64)
    inside = (qx >= 0) & (qx < pw) & (qy >= 0) & (qy < ph)
    xi = np.where(inside, qx, 0).astype(np.int64)
    yi = np.where(inside, qy, 0).astype(np.int64)
    bz = before @ relative[2, :3] + relative[2, 3]  # the point's depth in frame n-k's camera
    seen = prev_depth[yi, xi].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.maximum(seen / bz, bz / seen)
    valid = inside & (bz > 0) & np.isfinite(seen) & (off <= band)
    velocity = transform_points(prev_velocity[yi, xi], relative[:3, :3].T) * interval_ratio  # R^T v: n's axes
    earlier = before - velocity
    if first is not None:
        first_depth, first_k, view = first
        fh, fw = first_depth.shape
        there = transform_points(earlier, view[:3, :3], view[:3, 3])
        at = project_points(there, first_k)
        ok = np.isfinite(at).all(axis=1) & (at[:, 0] >= 0) & (at[:, 0] < fw) & (at[:, 1] >= 0) & (at[:, 1] < fh)
        fx = np.where(ok, at[:, 0], 0).astype(np.int64)
        fy = np.where(ok, at[:, 1], 0).astype(np.int64)
        seen0 = first_depth[fy, fx].astype(np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            valid &= ok & (np.maximum(seen0 / there[:, 2], there[:, 2] / seen0) <= check)
    return earlier, valid


@njit(cache=True, nogil=True)
def _hindcast_errors(now, predicted, k, out):  # pragma: no cover - compiled
    """``hindcast_errors`` compiled: ``project_points``' arithmetic, point by point."""
    for i in range(now.shape[0]):
        az, bz = predicted[i, 2], now[i, 2]
        if not (az > 1e-9 and bz > 1e-9):
            out[i] = np.nan
            continue
        dx = (k[0, 0] * predicted[i, 0] / az + k[0, 1] * predicted[i, 1] / az + k[0, 2]) - (
            k[0, 0] * now[i, 0] / bz + k[0, 1] * now[i, 1] / bz + k[0, 2])
        dy = (k[1, 1] * predicted[i, 1] / az + k[1, 2]) - (k[1, 1] * now[i, 1] / bz + k[1, 2])
        out[i] = math.sqrt(dx * dx + dy * dy)


def hindcast_errors(now: np.ndarray, predicted: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """Per point, how far (frame n's pixels) ``predicted`` (M, 3) lands from where frame n shows it (``now``);
    NaN where either is behind the camera. Compiled; ``hindcast_errors_reference`` is its numpy oracle."""
    out = np.empty(len(now))
    _hindcast_errors(np.ascontiguousarray(now, np.float64), np.ascontiguousarray(predicted, np.float64),
                     np.ascontiguousarray(intrinsics, np.float64), out)
    return out


def hindcast_errors_reference(now: np.ndarray, predicted: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """``hindcast_errors`` in numpy (``project_points``)."""
    return np.linalg.norm(project_points(predicted, intrinsics) - project_points(now, intrinsics), axis=-1)


def rigid_explains_better(now: np.ndarray, rigid: np.ndarray, linear: np.ndarray, valid: np.ndarray,
                          intrinsics: np.ndarray) -> bool:
    """Whether a rigid part's path, continued from the interval before (``rigid`` (N, 3): where it put the
    part's points at frame n), explained the last interval at least as well as each point's own straight line
    (``linear``), summed over the points ``valid`` then (pixels of frame n)."""
    a, b = hindcast_errors(now, rigid, intrinsics), hindcast_errors(now, linear, intrinsics)
    ok = valid & np.isfinite(a) & np.isfinite(b)
    return bool(a[ok].sum() <= b[ok].sum())


def hindcast_keeps(regions: np.ndarray, count: int, now: np.ndarray, before: np.ndarray, predicted: np.ndarray,
                   valid: np.ndarray, intrinsics: np.ndarray, *, ratio: float = 1.0,
                   min_share: float = 0.25) -> np.ndarray:
    """Per region, whether a motion model explained the last interval: (count,) bool.

    ``predicted`` (M, 3) is where the model (fitted on the interval before) put each point at frame n,
    starting from its position ``before`` (n-k); ``now`` is where frame n shows it. A region keeps its
    extrapolated motion unless, summed over its ``valid`` points and measured in frame n's pixels, the model's
    error exceeds ``ratio`` times the error of no object motion (the point left at ``before``: camera-only
    warp); a tie keeps it (an object that starts to move: neither explained the interval).
    Regions with fewer than ``min_share`` of their points valid have no evidence and keep their motion."""
    model, still = hindcast_errors(now, predicted, intrinsics), hindcast_errors(now, before, intrinsics)
    return region_keeps(regions, count, model, still, valid, ratio=ratio, min_share=min_share)
