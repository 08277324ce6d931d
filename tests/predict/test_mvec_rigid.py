"""``mvec[extrapolation=rigid]`` and ``mvec[fallback=true]``: rigid parts from vectors + depth, their screw
extrapolation (``engine.geometry.rigid``), and the fall-back to the camera-only warp where the motion of the
interval before did not explain the last one (a bounce, a spin reversal, a stop; never constant motion)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from engine.core.errors import InputError
from engine.core.frames import Camera, Frame, SceneObject, rigid_inverse
from engine.geometry import motion as rg_motion
from engine.geometry import rigid as rg
from engine.geometry.motion import extrapolated_flow
from engine.predict import Mvec, MvecConfig, Reproject, Target, make_predictor
from tests.synthetic import rigid, rotation, two_layer_sequence, with_vectors

SIZE = (64, 96)  # (H, W)
#: the motion before issue 42's defaults: each pixel on its line, no fall-back
LINEAR = MvecConfig(extrapolation="linear", fallback=False)
FOCAL = 80.0
SQUARE_Z = 4.0
BACKGROUND_Z = 12.0


def _k() -> np.ndarray:
    h, w = SIZE
    return np.array([[FOCAL, 0, w / 2], [0, FOCAL, h / 2], [0, 0, 1]], dtype=np.float64)


def spinning_square(angles, axis=(0.3, 0.2, 1.0), pivot=(0.5, 0.3, 0.0), half: float = 1.1,
                    drift=(0.0, 0.0, 0.0)) -> tuple[list[Frame], list[SceneObject]]:
    """A textured square (plane z = 0 of its object, |x|, |y| <= half) turning by ``angles[i]`` radians at frame
    i about ``axis`` through ``pivot`` (object coordinates: off its centre), its centre at (0, 0, SQUARE_Z),
    drifting by ``drift`` a frame, before a textured wall at BACKGROUND_Z; a still camera at the origin."""
    h, w = SIZE
    k = _k()
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    rays = np.stack([(u - k[0, 2]) / FOCAL, (v - k[1, 2]) / FOCAL, np.ones_like(u)], axis=-1)
    frames, transforms = [], []
    pivot = np.asarray(pivot, np.float64)
    for i, angle in enumerate(angles):
        about = rigid(axis, angle, pivot) @ rigid((0, 0, 1), 0.0, -pivot)  # turn about the pivot
        place = np.eye(4)
        place[:3, 3] = (0.0, 0.0, SQUARE_Z) + i * np.asarray(drift, np.float64)
        world_from_object = place @ about @ rigid((1, 0, 0), 0.4, (0, 0, 0))  # tilted towards the camera
        transforms.append(world_from_object)
        inv = rigid_inverse(world_from_object)
        origin = inv[:3, 3]
        d = rays @ inv[:3, :3].T
        t = -origin[2] / d[..., 2]
        local = origin + t[..., None] * d
        on = (t > 0) & (np.abs(local[..., 0]) <= half) & (np.abs(local[..., 1]) <= half)
        depth = np.where(on, t, BACKGROUND_Z).astype(np.float32)
        square = 0.5 + 0.4 * np.sin(7.0 * local[..., 0:1] + np.array([0.0, 1.0, 2.0])) * np.cos(5.0 * local[..., 1:2])
        wall = 0.5 + 0.3 * np.sin(3.0 * rays[..., 0:1] * BACKGROUND_Z + np.array([2.0, 0.0, 1.0]))
        color = np.where(on[..., None], square, wall).astype(np.float32)
        frames.append(Frame(index=i, time=i / 30.0, color=color, depth=depth, camera=Camera(k, np.eye(4)),
                            object_id=on.astype(np.int32), moving=on.copy()))
    return frames, [SceneObject(id=1, name="square", moving=True, world_from_object=np.stack(transforms))]


def _history(frames, objects, rendered):
    """The rendered frames (frame indices ``rendered``, oldest first), each but the first with vectors to the
    one before it, as an engine rendering only those writes them."""
    out = [frames[rendered[0]]]
    for older, newest in zip(rendered, rendered[1:]):
        out.append(with_vectors(frames, objects, older, newest))
    return out


def _true_flow(frame, objects, target_index):
    """Frame n's pixels' true screen displacement to frame ``target_index`` (still camera), (H, W, 2)."""
    obj = objects[0]
    motion = obj.world_from_object[target_index] @ rigid_inverse(obj.world_from_object[frame.index])
    h, w = frame.depth.shape
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    k = frame.camera.intrinsics
    p = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones_like(u)], -1) * frame.depth[..., None]
    q = p @ motion[:3, :3].T + motion[:3, 3]
    return np.stack([k[0, 0] * q[..., 0] / q[..., 2] + k[0, 2] - u, k[1, 1] * q[..., 1] / q[..., 2] + k[1, 2] - v], -1)


def _flow(state, frame, step):
    motion = state.data.motion
    return extrapolated_flow(frame.depth, motion.velocity, frame.camera.intrinsics, step, motion.moving,
                             motion.acceleration)[..., :2]


# ---------------------------------------------------------------------------------------------------------
# the numpy pieces
# ---------------------------------------------------------------------------------------------------------

def test_se3_log_and_exp_are_inverse_and_powers_follow_the_screw():
    rng = np.random.default_rng(3)
    for angle in (1e-8, 0.2, 1.0, 3.0):
        r, t = rotation(rng.normal(size=3), angle), rng.normal(size=3)
        twist = rg.se3_log(r, t)
        r2, t2 = rg.se3_exp(twist)
        np.testing.assert_allclose(r2, r, atol=1e-9)
        np.testing.assert_allclose(t2, t, atol=1e-9)
        half_r, half_t = rg.se3_exp(0.5 * twist)  # two half screws make the whole
        np.testing.assert_allclose(half_r @ half_r, r, atol=1e-9)
        np.testing.assert_allclose(half_r @ half_t + half_t, t, atol=1e-9)


def test_robust_rigid_recovers_a_turn_through_outliers():
    rng = np.random.default_rng(1)
    src = rng.uniform(-1, 1, (400, 3)) + (0, 0, 5)
    r, t = rotation((0.2, 1.0, 0.3), np.radians(14.0)), np.array([0.3, -0.1, 0.2])
    dst = src @ r.T + t
    dst[:100] += rng.normal(0, 0.3, (100, 3))  # a quarter of the points are wrong
    rot, trans, inliers = rg.robust_rigid(src, dst, np.full(400, 100.0), (1,))
    np.testing.assert_allclose(rot, r, atol=1e-6)
    np.testing.assert_allclose(trans, t, atol=1e-6)
    assert inliers[100:].all() and inliers[:100].mean() < 0.1


def test_robust_rigids_compiled_scores_pick_the_same_fit_as_its_reference():
    # sampled RANSAC (no guess, or a guess that fails): the compiled scores and inliers give the reference's bits,
    # for groups smaller and larger than the score sample, inliers on the threshold's edge among them
    rng = np.random.default_rng(7)
    for n, wrong in ((12, 0.3), (200, 0.5), (1500, 0.4)):
        src = rng.uniform(-1, 1, (n, 3)) + (0, 0, 5)
        dst = src @ rotation(rng.normal(size=3), np.radians(20.0)).T + rng.normal(0, 0.2, 3)
        dst += rng.normal(0, 0.004, (n, 3))  # residuals of about the threshold (0.01 * 100 px)
        bad = rng.random(n) < wrong
        dst[bad] += rng.normal(0, 0.3, (bad.sum(), 3))
        scale = rng.uniform(80.0, 120.0, n)
        for guess in (None, (np.eye(3), np.zeros(3))):
            fast = rg.robust_rigid(src, dst, scale, (n, 3), guess=guess)
            slow = rg.robust_rigid_reference(src, dst, scale, (n, 3), guess=guess)
            for a, b in zip(fast, slow):
                np.testing.assert_array_equal(a, b)
            assert 0 < fast[2].sum() < n



def test_ransacs_scoring_picks_the_first_hypothesis_with_the_most_inliers():
    # the compiled scoring stops counting a hypothesis that can no longer win: it still picks the first of the
    # hypotheses with the most inliers (ties among near-identical ones, the best late or first), per group
    rng = np.random.default_rng(11)
    n, hypotheses = 300, 32
    src = rng.uniform(-1, 1, (n, 3)) + (0, 0, 5)
    truth = rotation(rng.normal(size=3), np.radians(15.0))
    dst = src @ truth.T + 0.1 + rng.normal(0, 0.004, (n, 3))
    scale = rng.uniform(80.0, 120.0, n)
    samples = np.sort(rng.choice(n, 256, replace=False)).astype(np.int64)
    offsets = np.array([0, 100, 100, 256], np.int64)  # three groups of samples, the second one empty
    half = 3 * hypotheses // 2
    turns = [rotation(rng.normal(size=3), rng.choice([0.0, 1e-4, 0.05])) @ truth for _ in range(half)]
    r = np.repeat(np.array(turns), 2, axis=0)  # each hypothesis twice: the best one ties
    t = np.repeat(0.1 + rng.choice([0.0, 0.0, 0.002, 0.2], size=(half, 1)) * rng.normal(size=(half, 3)), 2, axis=0)
    for order in (slice(None), slice(None, None, -1)):
        r, t = np.ascontiguousarray(r[order]), np.ascontiguousarray(t[order])
        best = np.full(3, -1, np.int64)
        rg._best_hypotheses(src, dst, scale, samples, offsets, r, t, hypotheses, 1.0, best)
        for f in range(3):
            points = samples[offsets[f]:offsets[f + 1]]
            counts = []
            for j in range(f * hypotheses, (f + 1) * hypotheses):
                d = [r[j, c, 0] * src[points, 0] + r[j, c, 1] * src[points, 1] + r[j, c, 2] * src[points, 2]
                     + t[j, c] - dst[points, c] for c in range(3)]
                counts.append(int((np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) * scale[points] <= 1.0).sum()))
            assert best[f] == int(np.argmax(counts))
            if points.size:
                assert counts.count(max(counts)) > 1 and min(counts) < max(counts)

def test_screw_coefficients_follow_the_turn_between_the_predicted_frames():
    # points 1 m off the axis: the parabola meets the screw at s = 1/4 and 3/4 and stays within 7 mm of it
    # between for a turn of 60 degrees per interval (15 a frame at k = 4), within 1 mm for 30 (k = 2)
    p = np.array([[1.0, 0.0, 5.0], [0.0, -1.0, 5.0]])
    for degrees, tolerance in ((60.0, 7e-3), (30.0, 1e-3)):
        r, t = rotation((0, 0, 1), np.radians(degrees)), np.array([0.1, 0.0, 0.05])
        twist = rg.se3_log(r, t)
        velocity, acceleration = rg.screw_coefficients(p, twist)
        for s in (0.25, 1 / 3, 0.5, 2 / 3, 0.75):
            rs, ts = rg.se3_exp(s * twist)
            exact = p @ rs.T + ts
            mine = p + s * velocity + 0.5 * s * (s + 1) * acceleration
            assert np.abs(mine - exact).max() < (1e-12 if s in rg.NODES else tolerance)
        straight = p + 0.5 * (p @ r.T + t - p)  # constant velocity along the chord
        rh, th = rg.se3_exp(0.5 * twist)
        assert np.abs(straight - (p @ rh.T + th)).max() > 10 * tolerance


def _grid_points(velocity_of):
    """The pixels of a slanted patch (rows 16-47, columns 24-71 of SIZE) as moving pixels: flat indices,
    points (M, 3) and their velocities ``velocity_of(points)``."""
    h, w = SIZE
    k = _k()
    v, u = np.mgrid[16:48, 24:72]
    z = 4.0 + 0.01 * (u - 48)  # a slanted plane
    pts = np.stack([(u + 0.5 - k[0, 2]) / FOCAL * z, (v + 0.5 - k[1, 2]) / FOCAL * z, z], -1).reshape(-1, 3)
    return (v * w + u).reshape(-1), pts, velocity_of(pts)


def test_a_spinning_patch_is_one_rigid_part_with_its_rotation():
    r, t = rotation((0.2, 0.3, 1.0), np.radians(12.0)), np.array([0.05, -0.02, 0.03])
    pivot = np.array([0.8, 0.4, 4.0])  # off the patch's centre
    moving, now, velocity = _grid_points(lambda p: p - ((p - pivot - t) @ r + pivot))  # now = R (then - c) + c + t
    labels, count = rg.motion_components(SIZE, moving, now, velocity)
    assert count == 1
    parts = rg.rigid_parts(labels, count, now, now - velocity, np.full(len(now), FOCAL / 4.0))
    assert len(parts) == 1 and parts[0].members.size == len(now)
    np.testing.assert_allclose(parts[0].rotation, r, atol=1e-6)


def test_a_non_rigid_field_has_no_rigid_part():
    rng = np.random.default_rng(0)
    centre = np.array([0.0, 0.0, 4.0])
    # expanding by 20 % an interval plus a swirl that grows with the distance: no rigid motion fits
    def field(p):
        d = p - centre
        return 0.2 * d + 0.3 * np.cross(d, (0, 0, 1)) * np.linalg.norm(d, axis=1)[:, None] + rng.normal(0, 1e-4, p.shape)

    moving, now, velocity = _grid_points(field)
    labels, count = rg.motion_components(SIZE, moving, now, velocity)
    parts = rg.rigid_parts(labels, count, now, now - velocity, np.full(len(now), FOCAL / 4.0))
    assert sum(p.members.size for p in parts) < 0.5 * len(now)


def test_the_batched_fits_match_the_per_group_ones():
    # Horn's quaternion fit (compiled) against the SVD Kabsch, then the batched parts against the loop over groups
    rng = np.random.default_rng(5)
    for n in (3, 4, 20, 300):
        src = rng.normal(size=(n, 3)) + (0, 0, 5)
        r, t = rotation(rng.normal(size=3), rng.uniform(0.0, 3.0)), rng.normal(size=3)
        dst = src @ r.T + t + rng.normal(0, 0.05, (n, 3))
        (r_many, t_many), (r_one, t_one) = rg._fit_many(src[None], dst[None]), rg.fit_rigid(src, dst)
        np.testing.assert_allclose(r_many[0], r_one, atol=1e-10)
        np.testing.assert_allclose(t_many[0], t_one, atol=1e-10)
    # groups: clean turns, one with a third of outliers (its least-squares fit fails: sampled), one of two bodies
    # (two parts), one too small, one with no rigid motion (no part), one on a line (any turn about it fits), one
    # of 3 points (fewer than min_points)
    labels, src, dst = [], [], []
    for g, (size, wrong, split) in enumerate([(400, 0.0, False), (600, 0.35, False), (500, 0.0, True), (5, 0.0, False),
                                              (300, 1.0, False), (350, 0.1, False), (200, 0.0, False),
                                              (3, 0.0, False)]):
        points = rng.uniform(-1, 1, (size, 3)) + (0, 0, 5)
        if g == 6:
            points = (0.1, -0.2, 5.0) + rng.uniform(-1, 1, (size, 1)) * rng.normal(size=3)
        moved = points @ rotation(rng.normal(size=3), np.radians(12.0)).T + rng.normal(0, 0.2, 3)
        if split:
            moved[size // 2:] = points[size // 2:] @ rotation(rng.normal(size=3), 0.3).T + (0.2, 0.1, 0.0)
        bad = rng.random(size) < wrong
        moved[bad] += rng.normal(0, 0.3, (bad.sum(), 3))
        labels.append(np.full(size, g)), src.append(points), dst.append(moved)
    labels, src, dst = np.concatenate(labels), np.concatenate(src), np.concatenate(dst)
    order = rng.permutation(len(labels))  # the groups interleaved, as pixels are
    labels, src, dst = labels[order], src[order], dst[order]
    scale = np.full(len(labels), 100.0)
    fast = rg.rigid_parts(labels, 8, dst, src, scale)
    slow = rg.rigid_parts_reference(labels, 8, dst, src, scale)
    assert [p.group for p in fast] == [p.group for p in slow] == [0, 1, 2, 2, 5, 6]
    for a, b in zip(fast, slow):
        np.testing.assert_array_equal(a.members, b.members)
        np.testing.assert_allclose(a.rotation, b.rotation, atol=1e-9)
        np.testing.assert_allclose(a.translation, b.translation, atol=1e-9)
    # the table the compiled call gives holds the same parts, each point's part among them
    table = rg.find_parts(labels, 8, dst, src, scale)
    np.testing.assert_array_equal(table.group, [p.group for p in fast])
    part = np.full(len(labels), -1)
    for j, p in enumerate(slow):
        part[p.members] = j
    np.testing.assert_array_equal(table.part, part)
    # no points, or none in a group large enough: no part
    assert rg.rigid_parts(np.zeros(0, np.int64), 0, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)) == []
    assert rg.rigid_parts(labels % 8, 8, dst, src, scale, min_points=10 ** 6) == []


def test_the_compiled_fits_give_the_numpy_fits_bits():
    # fit_groups (moments compiled, the translation by np.einsum) against the fits inside the compiled rounds:
    # per group of labels (groups of 0, 1, 2, 3 and many points, noisy turns) and for one group of members
    rng = np.random.default_rng(12)
    sizes = [0, 1, 2, 3, 40, 700]
    labels = rng.permutation(np.repeat(np.arange(len(sizes)), sizes))
    labels[rng.random(labels.size) < 0.1] = -1  # points in no group
    src = rng.normal(size=(labels.size, 3)) * 3 + (0, 0, 5)
    dst = src @ rotation(rng.normal(size=3), 0.7).T + rng.normal(0, 1, 3) + rng.normal(0, 0.05, src.shape)
    r, t = rg.fit_groups(src, dst, labels, len(sizes))
    r_nb, t_nb = np.empty_like(r), np.empty_like(t)
    rg._fit_labels(src, dst, labels, len(sizes), r_nb, t_nb)
    np.testing.assert_array_equal(r_nb, r)
    np.testing.assert_array_equal(t_nb, t)
    members = np.flatnonzero(labels == 5)
    use = rng.random(members.size) < 0.7
    r_one, t_one = rg.fit_groups(src, dst, np.where(np.isin(np.arange(labels.size), members[use]), 0, -1), 1)
    r_nb, t_nb = np.empty((3, 3)), np.empty(3)
    rg._fit_members(src, dst, members, use, r_nb, t_nb)
    np.testing.assert_array_equal(r_nb, r_one[0])
    np.testing.assert_array_equal(t_nb, t_one[0])


def test_the_compiled_sampling_matches_robust_rigid():
    # the compiled robust fit of a group's members: a guess that explains half refitted (the same bits as
    # robust_rigid), else the same RANSAC draws and hypothesis, refitted by Horn's rotation where robust_rigid
    # uses the SVD (the same inliers, the transform to rounding); groups smaller and larger than the score sample
    rng = np.random.default_rng(13)
    for n, wrong in ((12, 0.3), (200, 0.5), (1500, 0.4)):
        src = rng.uniform(-1, 1, (n, 3)) + (0, 0, 5)
        dst = src @ rotation(rng.normal(size=3), np.radians(20.0)).T + rng.normal(0, 0.2, 3)
        dst += rng.normal(0, 1e-4, (n, 3))
        bad = rng.random(n) < wrong
        dst[bad] += rng.normal(0, 0.3, (bad.sum(), 3))
        scale = rng.uniform(80.0, 120.0, n)
        members = np.arange(n)
        for guess in (None, (np.eye(3), np.zeros(3)), rg.fit_rigid(src[~bad], dst[~bad])):
            slow = rg.robust_rigid(src, dst, scale, (n, 3), guess=guess)
            rotation_nb, translation_nb, inliers = np.empty((3, 3)), np.empty(3), np.empty(n, bool)
            given = guess if guess is not None else (np.eye(3), np.zeros(3))
            kept = rg._robust_members(src, dst, scale, members, np.uint64(rg._key_base((n, 3))), guess is not None,
                                      *given, rg.HYPOTHESES, rg.ROUNDS, 1.0, rotation_nb, translation_nb, inliers)
            np.testing.assert_array_equal(inliers, slow[2])
            assert kept == inliers.sum() and 0 < kept < n
            atol = 0 if rg._refit_guess(src, dst, scale, guess, 1.0) is not None else 1e-9
            np.testing.assert_allclose(rotation_nb, slow[0], rtol=0, atol=atol)
            np.testing.assert_allclose(translation_nb, slow[1], rtol=0, atol=atol)


def _part_histories(rng):
    """Points of six rigid parts at n-2k, n-k and n (``earlier``, ``then``, ``now``), their groups and which
    frame n-2k saw: a steady screw; a turn that changed since the interval before, with outliers then (its
    guess fails: sampled); a spin about the part's centre while the centre moves on; one that n-2k mostly did
    not see; one turning faster than MAX_TURN; one whose turn reversed (its path loses to the lines)."""
    earlier, then, now, labels, seen = [], [], [], [], []
    for g, (size, seen_share) in enumerate([(400, 0.9), (300, 0.9), (350, 0.9), (200, 0.3), (150, 0.9), (250, 0.9)]):
        a = rng.uniform(-0.5, 0.5, (size, 3)) + (rng.uniform(-1, 1), rng.uniform(-1, 1), 5.0)
        turn = rotation(rng.normal(size=3), 1.5 if g == 4 else 0.25)
        shift = rng.normal(0, 0.1, 3)
        if g == 2:  # the centre moves on a line, the part turning about it
            c0 = a.mean(axis=0)
            b = (a - c0) @ turn.T + c0 + shift
            c = (b - b.mean(axis=0)) @ turn.T + b.mean(axis=0) + shift
        else:
            before = (rotation(rng.normal(size=3), 0.2) @ turn if g == 1 else turn, shift)
            if g == 5:
                before = (turn.T, -shift)
            b = a @ before[0].T + before[1]
            c = b @ turn.T + shift
        if g == 1:
            a[rng.random(size) < 0.6] += rng.normal(0, 0.05, 3)
        earlier.append(a), then.append(b + rng.normal(0, 2e-4, b.shape)), now.append(c)
        labels.append(np.full(size, g)), seen.append(rng.random(size) < seen_share)
    order = rng.permutation(sum(map(len, labels)))
    return tuple(np.concatenate(x)[order] for x in (earlier, then, now, labels, seen))


def test_the_compiled_part_paths_match_part_motion():
    # each part's path (screw or spin, with the change of twist where three frames agree, or the screw alone
    # without evidence), which parts keep it, and the predictions of frame n: the compiled pass against
    # part_motion and rigid_explains_better part by part
    rng = np.random.default_rng(14)
    earlier, then, now, labels, seen = _part_histories(rng)
    scale = FOCAL / now[:, 2]
    table = rg.find_parts(labels, 6, now, then, scale)
    assert list(table.group) == list(range(6))
    for limit in (0.5, -1.0):
        predicted = 2.0 * then - earlier
        slow_predicted = predicted.copy()
        fast = rg.part_paths(table, now, then, earlier, seen, scale, predicted, _k(), limit=limit)
        slow = rg.part_paths_reference(table, now, then, earlier, seen, scale, slow_predicted, _k(), limit=limit)
        assert list(fast.group) == list(slow.group) == [0, 2, 5]
        np.testing.assert_array_equal(fast.rotation, slow.rotation)
        np.testing.assert_array_equal(fast.translation, slow.translation)
        np.testing.assert_allclose(fast.affine, slow.affine, rtol=0, atol=1e-12)
        np.testing.assert_allclose(predicted, slow_predicted, rtol=0, atol=1e-12)
        assert (predicted != 2.0 * then - earlier).any(axis=1).sum() == 1000  # the kept parts' points
    with pytest.raises(InputError) as err:  # updated in place: a copy would drop the update
        rg.part_paths(table, now, then, earlier, seen, scale, predicted.astype(np.float32), _k())
    assert err.value.field == "predicted"


def test_the_rigid_pass_predicts_what_its_numpy_pieces_predict(tmp_path, monkeypatch):
    # a pair of the spin set (tools.spin_set, small): the compiled parts and paths against rigid_parts_reference
    # and part_paths_reference in the predictor, with and without the fall-back: the same parts, motion and frames
    from engine.eval.protocol import rendered_history
    from engine.io.rgbd import read_sequence
    from engine.predict import mvec as mvec_module
    from tools.spin_set import render_spin

    sequence = read_sequence(render_spin(tmp_path, 4101, 240, 136, 5))
    history = rendered_history(sequence, 2, 4, with_vectors=True, three=True)
    target = Target(sequence.cameras[3], float(sequence.times[3]), 3)

    def reference_table(labels, count, points, before, scale, **options):
        parts = rg.rigid_parts_reference(labels, count, points, before, scale, **options)
        part = np.full(len(labels), -1)
        for j, p in enumerate(parts):
            part[p.members] = j
        return rg.PartTable(np.array([p.group for p in parts], np.int64),
                            np.array([p.rotation for p in parts]).reshape(-1, 3, 3),
                            np.array([p.translation for p in parts]).reshape(-1, 3), part)

    for config in (MvecConfig(extrapolation="rigid"), MvecConfig(extrapolation="rigid", fallback=True)):
        fast = Mvec(config)
        fast_state = fast.prepare(history)
        fast_frame = fast.render(fast_state, target).color
        with monkeypatch.context() as patch:
            patch.setattr(mvec_module, "find_parts", reference_table)
            patch.setattr(mvec_module, "part_paths", rg.part_paths_reference)
            slow = Mvec(config)
            slow_state = slow.prepare(history)
            slow_frame = slow.render(slow_state, target).color
        assert fast_state.data.parts == slow_state.data.parts >= 2
        a, b = fast_state.data.motion, slow_state.data.motion
        np.testing.assert_array_equal(a.moving, b.moving)
        np.testing.assert_allclose(a.velocity, b.velocity, rtol=0, atol=1e-6)
        np.testing.assert_allclose(a.acceleration, b.acceleration, rtol=0, atol=1e-6)
        np.testing.assert_allclose(fast_frame, slow_frame, rtol=0, atol=1e-5)


def test_motion_components_match_the_indexed_reference(point_split):
    # random moving masks (holes, row ends, frame edges) with bodies of unlike motion and depth steps; split, the
    # rows are linked in 3 ranges on 3 threads, then across the cuts
    rng = np.random.default_rng(4)
    h, w = SIZE
    for share in (0.3, 0.7, 1.0):
        moving = np.flatnonzero(rng.random(SIZE) < share)
        y, x = np.divmod(moving, w)
        z = np.where(x < w // 2, 4.0, 4.0 * rng.choice([1.05, 1.2], size=moving.size))
        points = np.stack([(x - w / 2) / FOCAL * z, (y - h / 2) / FOCAL * z, z], axis=-1)
        velocity = np.where((y < h // 2)[:, None], (0.02, 0.0, 0.0), (0.0, 0.03, 0.01))
        velocity = velocity + rng.normal(0, 0.004, velocity.shape) * (rng.random(moving.size) < 0.2)[:, None]
        labels, count = rg.motion_components(SIZE, moving, points, velocity)
        ref_labels, ref_count = rg.motion_components_reference(SIZE, moving, points, velocity)
        assert len(rg._row_cuts(moving, w)) == (3 if point_split == "three threads" else 1)
        assert count == ref_count > 2
        np.testing.assert_array_equal(labels, ref_labels)


def test_previous_positions_and_refined_depths_match_their_numpy_references():
    rng = np.random.default_rng(8)
    h, w = SIZE
    k = _k()
    v, u = np.mgrid[0:h, 0:w]
    plane = (4.0 + 0.01 * u + 0.02 * v).astype(np.float32)  # a slanted wall: smooth between pixels
    rough = np.where(rng.random(SIZE) < 0.2, plane * 1.3, plane).astype(np.float32)  # with steps
    rough[rng.random(SIZE) < 0.05] = np.inf  # and sky
    vectors = rng.normal(0, 4, SIZE + (2,)).astype(np.float32)  # some ends leave the frame
    prev_velocity = rng.normal(0, 0.05, SIZE + (3,)).astype(np.float32)
    moving = np.flatnonzero(rng.random(SIZE) < 0.4)
    y, x = np.divmod(moving, w)
    before = np.stack([(x + 0.5 - k[0, 2]) / FOCAL, (y + 0.5 - k[1, 2]) / FOCAL, np.ones(moving.size)], -1)
    before *= plane.reshape(-1)[moving, None] * rng.uniform(0.97, 1.03, (moving.size, 1))
    relative = rigid((0.1, 1.0, 0.2), 0.02, (0.03, -0.01, 0.02))
    view = rigid((0.0, 1.0, 0.1), 0.04, (0.05, 0.0, 0.03))
    for prev_depth in (plane, rough):
        for first in (None, (rough, k, view)):
            args = (plane, vectors, moving, before, relative, prev_depth, prev_velocity, 1.25)
            earlier, valid = rg.previous_positions(*args, first=first)
            ref_earlier, ref_valid = rg.previous_positions_reference(*args, first=first)
            assert 0.05 < valid.mean() < 0.95
            np.testing.assert_array_equal(valid, ref_valid)
            np.testing.assert_allclose(earlier, ref_earlier, rtol=0, atol=1e-12)
        refined = rg.refined_before(before, vectors, moving, relative, prev_depth, k)
        assert (refined != before).any(axis=1).mean() > 0.2
        np.testing.assert_allclose(refined, rg.refined_before_reference(before, vectors, moving, relative,
                                                                       prev_depth, k), rtol=0, atol=1e-12)


def test_the_continued_paths_match_numpy():
    rng = np.random.default_rng(6)
    now, then, earlier = (rng.normal(size=(50, 3)) for _ in range(3))
    idx = np.sort(rng.choice(50, 30, replace=False))
    r0, t0 = rotation(rng.normal(size=3), 0.3), rng.normal(size=3)
    screw, turned, sums = np.empty((50, 3)), np.empty((50, 3)), np.zeros(9)
    rg._continued_paths(now, then, earlier, idx, r0, t0, screw, turned, sums)
    c1, c0 = then[idx].mean(axis=0), earlier[idx].mean(axis=0)
    np.testing.assert_allclose(screw, then @ r0.T + t0, atol=1e-12)
    np.testing.assert_allclose(turned, (then - c1) @ r0.T + 2 * c1 - c0, atol=1e-12)
    np.testing.assert_allclose(sums, [np.linalg.norm(screw[idx] - now[idx], axis=-1).mean(),
                                      np.linalg.norm(turned[idx] - now[idx], axis=-1).mean(),
                                      np.linalg.norm(now[idx] - then[idx], axis=-1).mean(), *c1, *c0], atol=1e-12)


def test_moving_points_match_their_numpy_reference(point_split):
    rng = np.random.default_rng(2)
    depth = rng.uniform(1.0, 9.0, SIZE).astype(np.float32)
    velocity = rng.normal(size=SIZE + (3,)).astype(np.float32)
    moving = np.flatnonzero(rng.random(SIZE) < 0.3)
    for stride in (1, 3):
        for a, b in zip(rg.moving_points(depth, velocity, moving, _k(), stride),
                        rg.moving_points_reference(depth, velocity, moving, _k(), stride)):
            np.testing.assert_allclose(a, b, rtol=1e-14, atol=0)


def test_motion_components_split_at_depth_edges_and_unlike_motion():
    h, w = SIZE
    moving, now, _ = _grid_points(lambda p: np.zeros_like(p))
    velocity = np.zeros_like(now)
    left = (moving % w) < 48
    velocity[left] = (0.1, 0.0, 0.0)
    velocity[~left] = (-0.1, 0.0, 0.0)  # two bodies side by side moving apart
    _, count = rg.motion_components(SIZE, moving, now, velocity)
    assert count == 2
    far = now.copy()
    far[~left] *= 1.5  # one body, but behind a depth edge
    _, count = rg.motion_components(SIZE, moving, far, np.zeros_like(now) + 0.1)
    assert count == 2


# ---------------------------------------------------------------------------------------------------------
# mvec with the rigid extrapolation
# ---------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("k", [2, 4])
def test_rigid_extrapolation_follows_a_spin_about_an_off_centre_axis(k):
    angles = [np.radians(10.0) * i for i in range(3 * k + 1)]  # 10 degrees a frame
    frames, objects = spinning_square(angles)
    history = _history(frames, objects, [0, k, 2 * k])
    rigid_state = Mvec(MvecConfig(extrapolation="rigid")).prepare(history)
    linear_state = Mvec(LINEAR).prepare(history)
    assert rigid_state.data.parts == 1
    moving = history[-1].moving
    for step in range(1, k):
        truth = _true_flow(history[-1], objects, 2 * k + step)
        mine = _flow(rigid_state, history[-1], step / k)
        straight = _flow(linear_state, history[-1], step / k)
        err = np.linalg.norm(mine - truth, axis=-1)[moving]  # a few silhouette pixels n-2k did not see: lines
        assert np.median(err) < 0.1 and np.percentile(err, 99) < 0.5
        assert np.median(np.linalg.norm(straight - truth, axis=-1)[moving]) > 4 * max(np.median(err), 0.01)
    # and the picture: closer to the truth than the straight lines
    target = Target(frames[2 * k + k // 2].camera, frames[2 * k + k // 2].time, 2 * k + k // 2)
    truth = frames[2 * k + k // 2].color
    ours = Mvec(MvecConfig(extrapolation="rigid")).predict(history, target).color
    straight = Mvec(LINEAR).predict(history, target).color
    assert np.abs(ours - truth).mean() < np.abs(straight - truth).mean()


def test_a_rigid_path_needs_the_interval_before_to_support_it():
    # two frames: no evidence that the turn is steady (a tumbling throw and an aliased fast spin look alike),
    # so the pixels keep their lines; with frame n-2k the steady turn explains the last interval: a part
    frames, objects = spinning_square([np.radians(10.0) * i for i in range(7)])
    two = Mvec(MvecConfig(extrapolation="rigid")).prepare(_history(frames, objects, [2, 4]))
    linear = Mvec(LINEAR).prepare(_history(frames, objects, [2, 4]))
    assert two.data.parts == 0
    np.testing.assert_array_equal(_flow(two, frames[4], 0.5), _flow(linear, frames[4], 0.5))
    three = Mvec(MvecConfig(extrapolation="rigid")).prepare(_history(frames, objects, [0, 2, 4]))
    assert three.data.parts == 1


def test_object_ids_make_the_groups_when_asked():
    # one spinning square whose halves carry two ids: by motion it is one part, by ids two (each half a part)
    frames, objects = spinning_square([np.radians(10.0) * i for i in range(7)])
    history = _history(frames, objects, [0, 2, 4])
    half = np.zeros(SIZE, bool)
    half[:, SIZE[1] // 2:] = True
    newest = history[-1]
    history[-1] = dataclasses.replace(newest, object_id=np.where(newest.moving, 1 + half, 0).astype(np.int32))
    by_motion = Mvec(MvecConfig(extrapolation="rigid")).prepare(history)
    by_ids = Mvec(MvecConfig(extrapolation="rigid", grouping="ids")).prepare(history)
    assert by_motion.data.parts == 1 and by_ids.data.parts == 2
    # both halves turn with the square: the same motion either way
    np.testing.assert_allclose(_flow(by_ids, history[-1], 0.5), _flow(by_motion, history[-1], 0.5), atol=0.15)
    # a frame without ids: grouped by motion
    history[-1] = dataclasses.replace(newest, object_id=None)
    assert Mvec(MvecConfig(extrapolation="rigid", grouping="ids")).prepare(history).data.parts == 1


def test_a_drifting_square_without_turn_is_extrapolated_as_before():
    frames, objects = two_layer_sequence(9, width=96, height=64, camera_speed=0.03, object_speed=0.1)
    history = [frames[0], with_vectors(frames, objects, 0, 4)]
    rigid_state = Mvec(MvecConfig(extrapolation="rigid")).prepare(history)
    linear_state = Mvec(LINEAR).prepare(history)
    for step in (0.25, 0.5, 0.75):
        np.testing.assert_allclose(_flow(rigid_state, history[-1], step), _flow(linear_state, history[-1], step),
                                   atol=2e-3)


def test_the_options_are_checked():
    with pytest.raises(InputError) as err:
        MvecConfig(extrapolation="spline")
    assert err.value.field == "extrapolation"
    with pytest.raises(InputError):
        MvecConfig(fallback_ratio=0.0)
    with pytest.raises(InputError):
        MvecConfig(grouping="colour")
    assert make_predictor("mvec[extrapolation=rigid,fallback=true]").config.fallback


# ---------------------------------------------------------------------------------------------------------
# the fall-back to the camera-only warp
# ---------------------------------------------------------------------------------------------------------

def _falls_back(history, config):
    state = Mvec(config).prepare(history)
    return state, state.data.held, state.data.moving.size


@pytest.mark.parametrize("case", ["bounce", "stop"])
@pytest.mark.parametrize("extrapolation", ["linear", "rigid"])
def test_a_bounce_or_a_stop_falls_back_to_reprojection(case, extrapolation):
    path = {"bounce": lambda i: 0.1 * (i if i <= 4 else 8 - i),  # off a wall between frames 4 and 6
            "stop": lambda i: 0.1 * min(i, 4.5)}[case]  # stops half way through the last interval
    frames, objects = two_layer_sequence(8, width=96, height=64, camera_speed=0.02, object_path=path)
    history = _history(frames, objects, [2, 4, 6])
    config = MvecConfig(extrapolation=extrapolation, fallback=True)
    state, held, moving = _falls_back(history, config)
    assert moving > 0 and held == moving and state.data.motion is None
    target = Target(frames[7].camera, frames[7].time, 7)
    np.testing.assert_array_equal(Mvec(config).predict(history, target).color,
                                  Reproject().predict(history, target).color)
    # without the fall-back the old motion carries on
    assert Mvec(MvecConfig(extrapolation=extrapolation, fallback=False)).prepare(history).data.motion is not None


def test_a_spin_reversal_falls_back_and_a_steady_spin_does_not():
    step = np.radians(10.0)
    reversing = [step * (i if i <= 4 else 8 - i) for i in range(9)]
    frames, objects = spinning_square(reversing)
    config = MvecConfig(extrapolation="rigid", fallback=True)
    _, held, moving = _falls_back(_history(frames, objects, [0, 2, 4, 6]), config)
    assert moving > 0 and held > 0.9 * moving
    frames, objects = spinning_square([step * i for i in range(9)], drift=(0.02, 0.0, 0.0))
    state, held, moving = _falls_back(_history(frames, objects, [0, 2, 4, 6]), config)
    assert held == 0 and state.data.parts == 1


@pytest.mark.parametrize("extrapolation", ["linear", "rigid"])
def test_constant_motion_never_falls_back(extrapolation):
    frames, objects = two_layer_sequence(8, width=96, height=64, camera_speed=0.02, object_speed=0.1)
    state, held, moving = _falls_back(_history(frames, objects, [2, 4, 6]),
                                      MvecConfig(extrapolation=extrapolation, fallback=True))
    assert moving > 0 and held == 0 and state.data.motion is not None


def test_with_two_frames_the_fall_back_has_no_evidence_and_keeps_the_motion():
    path = lambda i: 0.1 * (i if i <= 4 else 8 - i)  # noqa: E731
    frames, objects = two_layer_sequence(8, width=96, height=64, camera_speed=0.02, object_path=path)
    state, held, _ = _falls_back(_history(frames, objects, [4, 6]), MvecConfig(fallback=True))
    assert held == 0 and state.data.motion is not None


def test_on_gl_the_rigid_motion_and_the_fall_back_predict_what_the_cpu_predicts():
    """The parts, screws and fall-back are decided on the CPU in ``prepare`` for both backends; the GL pass
    extrapolates the resulting motion as it extrapolates any (``motion_extrapolate.comp``)."""
    from engine.geometry.backends import gl as glb

    if not glb.available():
        pytest.skip("no EGL context with compute shaders")
    frames, objects = spinning_square([np.radians(10.0) * i for i in range(9)], drift=(0.02, 0.0, 0.0))
    history = _history(frames, objects, [0, 2, 4, 6])[1:]
    method = "mvec[extrapolation=rigid,fallback=true]"
    cpu, gl = make_predictor(method, backend="cpu"), make_predictor(method, backend="gl")
    cpu_state, gl_state = cpu.prepare(history), gl.prepare(history)
    assert cpu_state.data.parts == gl_state.data.parts == 1
    for index in (7, 8):
        target = Target(frames[index].camera, frames[index].time, index)
        a, b = cpu.render(cpu_state, target), gl.render(gl_state, target)
        assert "motion" in b.gpu_ms
        close = (np.abs(a.color - b.color) <= 1e-3 * np.maximum(1.0, np.abs(a.color))).all(axis=-1)
        assert close.mean() >= 0.995 and np.mean(a.holes == b.holes) >= 0.999


# ---------------------------------------------------------------------------------------------------------
# object ids through the Session
# ---------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("flip_rows", [False, True])
def test_a_session_takes_the_engines_object_ids_for_the_grouping(flip_rows):
    from engine.runtime.session import Session, SessionConfig

    frames, objects = spinning_square([np.radians(10.0) * i for i in range(7)])
    history = _history(frames, objects, [0, 2, 4])
    half = np.zeros(SIZE, bool)
    half[:, SIZE[1] // 2:] = True
    h, w = SIZE
    parts = {}
    for grouping in ("motion", "ids"):
        method = f"mvec[extrapolation=rigid,grouping={grouping}]"
        session = Session(SessionConfig(engine="opencv", width=w, height=h, method=method, flip_rows=flip_rows))
        for i, f in enumerate(history):
            ids = np.where(f.moving, 1 + half, 0)
            rows = (lambda a: a[::-1]) if flip_rows else (lambda a: a)
            session.submit(rows(f.color), rows(f.depth), f.camera.world_to_camera, f.camera.intrinsics, f.time,
                           motion_vectors=None if i == 0 else rows(f.motion_vectors),
                           object_ids=rows(ids))
        prepared = session._loop.prepared
        np.testing.assert_array_equal(prepared.frames[-1].object_id, np.where(history[-1].moving, 1 + half, 0))
        parts[grouping] = prepared.state.data.parts
    assert parts == {"motion": 1, "ids": 2}
    with pytest.raises(InputError) as err:
        session.submit(frames[6].color, frames[6].depth, np.eye(4), _k(), 1.0, object_ids=-np.ones(SIZE))
    assert err.value.field == "object_ids"
    with pytest.raises(InputError):
        session.submit(frames[6].color, frames[6].depth, np.eye(4), _k(), 1.0, object_ids=np.ones((2, 2)))


def test_apply_parts_and_kept_part_motion_match_their_numpy_references(point_split):
    # three groups: one with two parts (pixels of either, and some near the assignment limit), one with a part
    # whose transform explains none of them, one without parts; with and without the pixels' own acceleration
    rng = np.random.default_rng(9)
    h, w = SIZE
    moving = np.sort(rng.choice(h * w, 900, replace=False))
    labels = rng.choice(3, size=moving.size)
    now = rng.uniform(-1, 1, (moving.size, 3)) + (0, 0, 5)
    depth = now[:, 2].copy()
    turns = [(rotation(rng.normal(size=3), 0.2), rng.normal(0, 0.1, 3)) for _ in range(3)]
    speed = rng.normal(0, 0.05, (moving.size, 3))
    for j, g in ((0, 0), (1, 0)):
        on = (labels == g) & (np.arange(moving.size) % 2 == j)
        r, t = turns[j]  # speed = now - (R^T (now - t)): the pixel's point at n-k moved by (R, t)
        speed[on] = now[on] - (now[on] - t) @ r + rng.normal(0, 0.1, (on.sum(), 3))  # about 3 px off
    parts = [rg.RigidPart(np.zeros(0, np.int64), *turns[0], 0), rg.RigidPart(np.zeros(0, np.int64), *turns[1], 0),
             rg.RigidPart(np.zeros(0, np.int64), *turns[2], 1)]
    paths = rg.PartPaths.stack(parts, [rg.screw_affine(rg.se3_log(*turn)) for turn in turns])
    for acceleration in (None, rng.normal(0, 0.01, (moving.size, 3)).astype(np.float32)):
        fast = rg.apply_parts(now, speed, depth, labels, 3, paths, FOCAL, 3.0, acceleration)
        slow = rg.apply_parts_reference(now, speed, depth, labels, 3, paths, FOCAL, 3.0, acceleration)
        for a, b in zip(fast, slow):
            np.testing.assert_array_equal(a, b)
        regions = fast[2]
        assert 0.5 < np.isin(regions, (3, 4)).sum() / (labels == 0).sum() < 1 and not (regions == 5).any()
        for keep in (np.ones(6, bool), np.array([True, False, True, True, False, True])):
            args = (SIZE, moving, now, speed, depth, labels, 3, paths, FOCAL, 3.0, acceleration, keep)
            got = rg.kept_part_motion(*args)
            for a, b in zip(got, rg.kept_part_motion_reference(*args)):
                np.testing.assert_array_equal(a, b)
            assert got[1].size == keep[regions].sum()
            np.testing.assert_array_equal(got[0].reshape(-1, 3)[got[1]], fast[0][keep[regions]])
    # the change of velocity computed in the pass, for the kept pixels that keep their own motion only: the rows
    # of velocity_change there (frames of a slanted wall, small vectors, a camera turning a little)
    v, u = np.mgrid[0:h, 0:w]
    wall = (4.0 + 0.01 * u + 0.02 * v).astype(np.float32)
    vectors = rng.normal(0, 1.5, SIZE + (2,)).astype(np.float32)
    frame_velocity = ((0.03, -0.02, 0.01) + rng.normal(0, 0.004, SIZE + (3,))).astype(np.float32)
    prev_velocity = (frame_velocity + rng.normal(0, 0.01, SIZE + (3,))).astype(np.float32)
    now_camera, then_camera = Camera(_k(), np.eye(4)), Camera(_k(), rigid((0, 1, 0), 0.002, (0.002, 0.0, 0.0)))
    frames = (wall, vectors, frame_velocity, now_camera, then_camera, wall, prev_velocity, 1.0)
    change = rg_motion.velocity_change_args(*frames)
    rows = rg_motion.velocity_change(*frames[:3], moving, *frames[3:])
    assert 0.2 < np.abs(rows).max(axis=1).astype(bool).mean() < 1
    keep = np.array([True, True, False, True, True, True])
    args = (SIZE, moving, now, speed, depth, labels, 3, paths, FOCAL, 3.0, None, keep)
    got = rg.kept_part_motion(*args, change)
    for a, b in zip(got, rg.kept_part_motion_reference(*args, change)):
        np.testing.assert_array_equal(a, b)
    out = np.zeros(SIZE + (3,), np.float32)  # a zero array of the caller's: written in place, the same result
    into = rg.kept_part_motion(*args, change, out)
    assert into[0] is out
    for a, b in zip(into, got):
        np.testing.assert_array_equal(a, b)
    for bad in (np.zeros(SIZE + (3,)), np.zeros((3,) + SIZE, np.float32).transpose(1, 2, 0), out[:-1]):
        with pytest.raises(InputError, match="out"):
            rg.kept_part_motion(*args, change, bad)
    own = np.isin(got[1], moving[labels == 1])  # group 1: its part explains none of them
    assert own.any() and not np.isin(got[1], moving[labels == 2]).any()
    np.testing.assert_array_equal(got[2][own], rows[np.isin(moving, got[1][own])])


def test_hindcast_errors_match_their_numpy_reference():
    rng = np.random.default_rng(10)
    now = rng.uniform(-1, 1, (500, 3)) + (0, 0, 3)
    predicted = now + rng.normal(0, 0.3, now.shape)
    predicted[:20, 2] = -0.5  # behind the camera: NaN
    now[20:30, 2] = 0.0
    fast, slow = rg.hindcast_errors(now, predicted, _k()), rg.hindcast_errors_reference(now, predicted, _k())
    np.testing.assert_array_equal(fast, slow)
    assert np.isnan(fast[:30]).all() and np.isfinite(fast[30:]).all()
