"""Motion vectors of rigid scenes (``engine.geometry.motion``) and the compiled velocity kernel against its oracle."""
from __future__ import annotations

import numpy as np
import pytest

from engine import geometry
from engine.geometry import kernels
from engine.core.errors import InputError
from engine.core.frames import Camera
from engine.geometry.motion import (camera_motion_vectors, compose_motion_vectors, extrapolated_flow,
                                    rigid_motion_vectors, sample_depths, sample_footprint, scene_velocity,
                                    undilate_motion_vectors, upsample_motion_vectors, velocity_change,
                                    velocity_change_args)
from engine.geometry.reference import scene_velocity_reference
from tests.synthetic import rigid

W, H = 48, 32
K = np.array([[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]])


def _camera(angle=0.0, t=(0.0, 0.0, 0.0)) -> Camera:
    return Camera(K, rigid([0, 1, 0], angle, t))


def _depth(seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.uniform(2.0, 9.0, (H, W)).astype(np.float32)
    d[:4] = np.inf  # sky band
    return d


def test_camera_vectors_are_the_reprojection_back_to_the_previous_camera():
    depth, now, before = _depth(), _camera(0.02, (0.1, 0.0, 0.05)), _camera()
    vectors = camera_motion_vectors(depth, now, before)
    uv, _, valid = geometry.reproject(depth, now.intrinsics, now.world_to_camera, before.intrinsics,
                                      before.world_to_camera)
    pixels = geometry.pixel_centers(H, W)
    np.testing.assert_allclose(vectors[valid], (uv - pixels)[valid], atol=2e-3)
    # the sky moves with the rotation alone: the same vector for any depth of a sky pixel
    assert np.all(np.isfinite(vectors[:4]))


def test_object_motion_is_added_where_the_object_is():
    depth = np.full((H, W), 5.0, np.float32)
    ids = np.zeros((H, W), np.int32)
    ids[10:20, 10:20] = 3
    cam = _camera()
    motion = np.eye(4)
    motion[0, 3] = -0.5  # the object was 0.5 to the left in the previous frame
    vectors = rigid_motion_vectors(depth, cam, cam, ids, {3: motion})
    np.testing.assert_allclose(vectors[15, 15], [-0.5 * 40.0 / 5.0, 0.0], atol=1e-4)
    np.testing.assert_allclose(vectors[0, 0], [0.0, 0.0], atol=1e-6)


def test_a_point_behind_the_previous_camera_has_no_vector():
    depth = np.full((H, W), 0.5, np.float32)
    vectors = camera_motion_vectors(depth, _camera(), _camera(t=(0.0, 0.0, -1.0)))  # it stood 1 unit ahead
    assert np.isnan(vectors).all()


def test_a_point_at_the_previous_cameras_plane_has_no_vector():
    # an object brushing past the camera: in the previous frame a point lay 1e-7 in front of its plane, 2 units
    # to the side, which projects 8e8 px away: no screen position (and the rgbd-seq format refuses such vectors)
    depth = np.full((H, W), 5.0, np.float32)
    ids = np.zeros((H, W), np.int32)
    ids[:, :8] = 1
    cam = _camera()
    motion = np.eye(4)
    motion[:3, 3] = [2.0, 0.0, 1e-7 - 5.0]  # every point of the object was at z = 1e-7 (x about 2 units off)
    vectors = rigid_motion_vectors(depth, cam, cam, ids, {1: motion})
    assert np.isnan(vectors[:, :8]).all()
    np.testing.assert_allclose(vectors[:, 8:], 0.0, atol=1e-6)  # the static rest keeps its vectors
    motion[2, 3] = 0.5 - 5.0  # at z = 0.5 it is a long vector, not a missing one
    assert np.isfinite(rigid_motion_vectors(depth, cam, cam, ids, {1: motion})).all()


def test_composing_two_steps_equals_the_direct_vectors_on_a_plane():
    depth = np.full((H, W), 4.0, np.float32)
    a, b, c = _camera(t=(0.0, 0.0, 0.0)), _camera(t=(-0.1, 0.0, 0.0)), _camera(t=(-0.25, 0.0, 0.0))
    direct = camera_motion_vectors(depth, c, a)
    chained = compose_motion_vectors(camera_motion_vectors(depth, c, b), camera_motion_vectors(depth, b, a))
    inside = np.isfinite(chained[..., 0])
    assert inside.mean() > 0.8
    np.testing.assert_allclose(chained[inside], direct[inside], atol=1e-4)
    assert np.isnan(chained[~inside]).all()  # left the middle frame: unknown, not guessed


def _plane_depth(camera: Camera, normal=(0.1, 0.05, 1.0), offset: float = 4.0) -> np.ndarray:
    """Planar depth (H, W) of the world plane ``normal . X = offset`` seen by ``camera`` (ray casting)."""
    v, u = np.mgrid[0:H, 0:W] + 0.5
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(camera.intrinsics).T @ camera.world_to_camera[:3, :3]
    n = np.asarray(normal, np.float64)
    return ((offset - n @ camera.position) / (rays @ n)).astype(np.float32)


def test_composing_a_turning_camera_needs_no_half_pixel_of_error():
    """Vectors that vary across the frame (a turn and a step towards a tilted plane): the nearest pixel's
    vector is up to half a pixel of their gradient off (here 8.8e-3 px median, 0.033 max; 0.23 px median on
    a dynamic field's orbit, which ``mvec`` read as motion); interpolating within one surface leaves the
    curvature of the projection (here 1.6e-4 median, 0.017 max, at the border where it clamps)."""
    a, b, c = _camera(0.0), _camera(0.04, (0.05, 0.0, 0.1)), _camera(0.09, (0.1, 0.02, 0.25))
    direct = camera_motion_vectors(_plane_depth(c), c, a)
    chained = compose_motion_vectors(camera_motion_vectors(_plane_depth(c), c, b),
                                     camera_motion_vectors(_plane_depth(b), b, a))
    inside = np.isfinite(chained[..., 0])
    assert inside.mean() > 0.7
    error = np.abs(chained[inside] - direct[inside]).max(axis=-1)
    assert np.median(error) < 1e-3 and error.max() < 1 / 32  # mvec's test of a static surface
    # across a silhouette (the four vectors around the landing point disagree) the nearest one, not a blend
    step = np.zeros((H, W, 2), np.float32)
    step[:, W // 2:] = 5.0
    across = compose_motion_vectors(np.full((H, W, 2), 0.5, np.float32), step)
    assert set(np.unique(across[:-1, W // 2 - 2:W // 2 + 1, 0]).tolist()) <= {0.5, 5.5}  # the last row leaves


def _velocity_inputs(seed=0):
    rng = np.random.default_rng(seed)
    depth = _depth(seed)
    vectors = rng.normal(0, 3, (H, W, 2)).astype(np.float32)
    vectors[5, :6] = np.nan
    vectors[6, 0] = (1000.0, -1000.0)  # far off screen
    vectors[7, :5] = 0.0
    prev_depth = _depth(seed + 1)
    now, before = _camera(0.03, (0.1, 0.05, 0.2)), _camera()
    return depth, vectors, prev_depth, now, before


def test_velocity_kernel_matches_its_numpy_oracle():
    depth, vectors, prev_depth, now, before = _velocity_inputs()
    fast, moving = scene_velocity(depth, vectors, prev_depth, now, before)
    rel = before.world_to_camera @ now.camera_to_world
    slow = scene_velocity_reference(depth, vectors, prev_depth, np.linalg.inv(K), K, np.linalg.inv(K), rel[:3, :3],
                                    rel[:3, 3], 1 / 32, 2.0 ** -10, 1.5)
    np.testing.assert_allclose(fast, slow, rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(moving, np.flatnonzero(np.any(slow != 0, axis=-1)))
    assert np.all(np.isfinite(fast))
    assert np.all(fast[:4] == 0) and np.all(fast[5, :6] == 0)  # sky and missing vectors do not move
    # the rows split over threads as every third row from row 0, 1 and 2: the same bits as one pass
    args = (depth, vectors, prev_depth, np.linalg.inv(K), K, np.linalg.inv(K), np.ascontiguousarray(rel[:3, :3]),
            np.ascontiguousarray(rel[:3, 3]), 1 / 32, 2.0 ** -10, 1.5)
    out, found, row_counts = np.zeros_like(fast), np.full((3, H * W), -1, np.int64), np.full(H, -1, np.int64)
    counts = [kernels.scene_velocity(*args, first, H, 3, out, found[first], row_counts) for first in range(3)]
    assert min(counts) > 0 and sum(counts) == moving.size
    np.testing.assert_array_equal(out, fast)
    # each call lists its rows' moving pixels row by row, each row's count in row_counts; merged: the moving pixels
    np.testing.assert_array_equal(row_counts, np.any(slow != 0, axis=-1).sum(axis=1))
    for first in range(3):
        np.testing.assert_array_equal(found[first, :counts[first]], moving[moving // W % 3 == first])
    merged = np.full(moving.size + 1, -1, np.int64)
    assert kernels.merge_rows(found, row_counts, 3, merged) == moving.size
    np.testing.assert_array_equal(merged[:-1], moving)


def test_a_static_scene_has_exactly_zero_velocity_even_from_half_float_vectors():
    depth, now, before = _depth(), _camera(0.04, (8.0, 0.0, 0.1)), _camera()
    vectors = camera_motion_vectors(depth, now, before)
    assert np.nanmax(np.abs(vectors)) > 128  # half floats round these by up to 1/16 px
    for stored in (vectors, vectors.astype(np.float16).astype(np.float32)):
        velocity, moving = scene_velocity(depth, stored, _depth(3), now, before)
        assert moving.size == 0 and not velocity.any()


def test_velocity_of_a_plane_approaching_a_moving_camera_is_exact():
    # frame n: a plane at z = 3 (this camera); frame n-k: the same plane 0.6 farther and 0.2 to the left, seen
    # by a camera that has since turned and moved
    now, before = _camera(0.05, (0.1, 0.0, 0.0)), _camera()
    depth = np.full((H, W), 3.0, np.float32)
    motion = np.eye(4)
    shift = np.array([-0.2, 0.0, 0.6])  # world-space displacement from now to before, in this camera's axes
    motion[:3, 3] = now.camera_to_world[:3, :3] @ shift
    vectors = rigid_motion_vectors(depth, now, before, np.ones((H, W), np.int32), {1: motion})
    # the previous frame's depth where each point was
    before_points = geometry.unproject(depth, K)[..., :3] + shift  # in this camera's axes
    world = before_points @ now.camera_to_world[:3, :3].T + now.camera_to_world[:3, 3]
    prev_z = (world @ before.world_to_camera[:3, :3].T + before.world_to_camera[:3, 3])[..., 2]
    prev_depth = np.full((H, W), float(np.median(prev_z)), np.float32)  # a fronto-parallel plane there
    velocity, moving = scene_velocity(depth, vectors, prev_depth, now, before, band=2.0)
    assert moving.size > 0
    inside = np.abs(prev_z - np.median(prev_z)) < 1e-3  # where the previous plane is exactly that depth
    np.testing.assert_allclose(velocity[inside], np.broadcast_to(-shift, velocity[inside].shape), atol=2e-3)


def test_extrapolated_flow_moves_points_in_3d_and_drops_those_crossing_the_camera():
    depth = np.full((H, W), 2.0, np.float32)
    velocity = np.zeros((H, W, 3), np.float32)
    velocity[10, 10] = (0.1, 0.0, 0.0)
    velocity[11, 11] = (0.0, 0.0, -3.0)  # through the camera plane within one step
    flow = extrapolated_flow(depth, velocity, K, 1.0)
    np.testing.assert_allclose(flow[10, 10], [0.1 * 40.0 / 2.0, 0.0, 0.0], atol=1e-4)
    assert np.isnan(flow[11, 11]).all()
    assert not flow[0, 0].any()


def test_low_resolution_vectors_take_the_sample_of_their_own_surface():
    depth = np.full((H, W), 8.0, np.float32)
    depth[:, : W // 2 + 1] = 2.0  # a near surface on the left, one pixel past the half-resolution edge
    small_depth = depth[1::2, 1::2]  # the surfaces at the small grid's sample centres, (2j + 1, 2i + 1)
    small = np.zeros((H // 2, W // 2, 2), np.float32)
    small[small_depth == 2.0] = (5.0, 0.0)
    full = upsample_motion_vectors(small, depth)
    assert full.shape == (H, W, 2)
    np.testing.assert_array_equal(full[depth == 2.0], np.broadcast_to([5.0, 0.0], full[depth == 2.0].shape))
    np.testing.assert_array_equal(full[depth == 8.0], 0.0)
    with pytest.raises(InputError):
        upsample_motion_vectors(np.zeros((H * 2, W, 2), np.float32), depth)


@pytest.mark.parametrize("small", [(16, 24), (8, 12), (32 // 3, 16), (5, 7), (1, 1)])
def test_a_sample_is_the_point_at_its_pixel_centre_and_takes_the_depth_there(small):
    """Sample (i, j) of an (h, w) grid spanning the frame is the point ((j + 0.5) W / w, (i + 0.5) H / h);
    the pixels bracketing it and its depth there (inverse depth interpolated: exact on a plane)."""
    h, w = small
    px, py = (np.arange(w) + 0.5) * W / w, (np.arange(h) + 0.5) * H / h
    for points, (lo, hi, frac) in ((px, sample_footprint(w, W)), (py, sample_footprint(h, H))):
        np.testing.assert_allclose(lo + 0.5 + frac, points, atol=1e-12)  # lo's centre plus the fraction
        np.testing.assert_array_equal(hi, np.where(frac > 0, lo + 1, lo))
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    inverse = lambda x, y: 0.15 + 0.01 * x + 0.004 * y  # noqa: E731 (a plane's inverse depth is affine)
    x, y = np.meshgrid(px, py)
    np.testing.assert_allclose(sample_depths((1.0 / inverse(u, v)).astype(np.float32), small), 1.0 / inverse(x, y),
                               rtol=1e-5)
    assert np.isposinf(sample_depths(np.full((H, W), np.inf, np.float32), small)).all()


@pytest.mark.parametrize("ratio, edge", [(2, 21), (4, 22), (2, 20)])
def test_a_sample_between_two_surfaces_is_not_given_to_either(ratio, edge):
    """At even ratios a sample's point lies between two full-resolution pixels; where they show different
    surfaces the sample's vector may be either's (here it holds neither: (99, 99)). Every pixel takes a
    sample of its own surface instead (issue 41, item 7: the depth of the pixel below-right of the point
    gave such samples to the far surface)."""
    depth = np.full((H, W), 8.0, np.float32)
    depth[:, :edge] = 2.0  # a near surface on the left
    lo, hi, _ = sample_footprint(W // ratio, W)
    near, far = depth[0, lo] == 2.0, depth[0, hi] == 2.0
    small = np.zeros((H // ratio, W // ratio, 2), np.float32)
    small[:, near & far] = (5.0, 0.0)
    small[:, near != far] = (99.0, 99.0)
    assert (near != far).any() == (edge % ratio == ratio // 2)  # the edge is under a sample's point
    full = upsample_motion_vectors(small, depth)
    np.testing.assert_array_equal(full[depth == 2.0], np.broadcast_to([5.0, 0.0], full[depth == 2.0].shape))
    np.testing.assert_array_equal(full[depth == 8.0], 0.0)


def test_undilation_removes_the_foreground_vector_from_background_pixels_only():
    depth = np.full((H, W), 8.0, np.float32)
    depth[10:20, 10:20] = 2.0
    truth = np.zeros((H, W, 2), np.float32)
    truth[10:20, 10:20] = (6.0, -2.0)
    # FSR-style dilation: every pixel takes the vector of the nearest surface of its 3x3 neighbourhood
    dilated = truth.copy()
    for y in range(H):
        for x in range(W):
            ys, xs = slice(max(y - 1, 0), y + 2), slice(max(x - 1, 0), x + 2)
            win = depth[ys, xs]
            j = np.unravel_index(np.argmin(win), win.shape)
            dilated[y, x] = truth[ys, xs][j]
    assert (dilated != truth).any()
    fixed = undilate_motion_vectors(dilated, depth)
    np.testing.assert_array_equal(fixed[10:20, 10:20], truth[10:20, 10:20])
    ring = (dilated != truth).any(axis=-1)
    assert np.isnan(fixed[ring]).all()
    np.testing.assert_array_equal(fixed[~ring & (depth == 8.0)], 0.0)


def test_velocity_change_and_extrapolation_kernels_match_their_numpy_oracles(point_split):
    from engine.geometry.reference import extrapolated_flow_reference, velocity_change_reference
    depth, vectors, prev_depth, now, before = _velocity_inputs(4)
    vectors = np.nan_to_num(vectors)
    rng = np.random.default_rng(5)
    velocity = rng.normal(0, 0.2, (H, W, 3)).astype(np.float32)
    prev_velocity = (velocity + rng.normal(0, 0.05, (H, W, 3))).astype(np.float32)
    moving = np.flatnonzero(np.isfinite(depth))
    rel = before.world_to_camera @ now.camera_to_world
    fast = velocity_change(depth, vectors, velocity, moving, now, before, prev_depth, prev_velocity, 1.25,
                           band=3.0, limit=0.5)
    slow = velocity_change_reference(depth, vectors, velocity, moving, np.linalg.inv(K), rel[:3, :3], rel[:3, 3],
                                     prev_depth, prev_velocity, 1.25, 3.0, 0.5)
    np.testing.assert_allclose(fast, slow, rtol=1e-5, atol=1e-6)
    assert 0 < np.count_nonzero(np.any(fast != 0, axis=-1)) < moving.size  # some kept, some refused
    # split over threads (point_split): the same bits as one call of the kernel over all the points
    assert len(kernels.split_points(moving.size)) == (3 if point_split == "three threads" else 1)
    args = velocity_change_args(depth, vectors, velocity, now, before, prev_depth, prev_velocity, 1.25, band=3.0,
                                limit=0.5)
    whole = np.empty_like(fast)
    kernels.velocity_change(*args[:3], moving.astype(np.int64), *args[3:], whole)
    np.testing.assert_array_equal(fast, whole)
    for accel in (None, fast):
        out = extrapolated_flow(depth, velocity, K, 0.75, moving, accel)
        ref = extrapolated_flow_reference(depth, velocity, moving, accel, K, np.linalg.inv(K), 0.75)
        np.testing.assert_allclose(out, ref, rtol=1e-5, atol=1e-5)
        whole = np.zeros_like(out)
        kernels.extrapolate_points(depth, velocity, moving.astype(np.int64), np.zeros((1, 3), np.float32) if accel
                                   is None else accel, accel is not None, K, np.linalg.inv(K), 0.75, whole)
        np.testing.assert_array_equal(out, whole)


def test_velocity_kernel_marks_the_same_static_pixels_as_its_oracle_near_the_tolerance():
    # camera-only vectors plus offsets inside, near and beyond the static tolerance (1/32 px): the kernel's
    # folded static test (one homography a row) marks exactly the pixels the oracle's marks
    depth, _, prev_depth, now, before = _velocity_inputs(7)
    rng = np.random.default_rng(8)
    offsets = rng.choice([0.0, 0.02, -0.03, 0.0315, 0.033, -0.05, 0.5, 4.0], size=(H, W, 2)).astype(np.float32)
    vectors = (camera_motion_vectors(depth, now, before) + offsets).astype(np.float32)
    fast, moving = scene_velocity(depth, vectors, prev_depth, now, before)
    rel = before.world_to_camera @ now.camera_to_world
    slow = scene_velocity_reference(depth, vectors, prev_depth, np.linalg.inv(K), K, np.linalg.inv(K), rel[:3, :3],
                                    rel[:3, 3], 1 / 32, 2.0 ** -10, 1.5)
    np.testing.assert_array_equal(moving, np.flatnonzero(np.any(slow != 0, axis=-1)))
    np.testing.assert_allclose(fast, slow, rtol=1e-5, atol=1e-5)
    assert 0.2 < moving.size / np.isfinite(depth).sum() < 0.9  # both kinds present


def test_the_warp_reads_a_channel_first_flow_without_a_copy_and_gets_the_same_frame():
    depth, vectors, prev_depth, now, before = _velocity_inputs(4)
    velocity, moving = scene_velocity(depth, np.nan_to_num(vectors), prev_depth, now, before)
    planar = np.zeros((3, H, W), np.float32)
    flow = extrapolated_flow(depth, velocity, K, 0.5, moving, out=np.moveaxis(planar, 0, -1))
    np.testing.assert_array_equal(flow, extrapolated_flow(depth, velocity, K, 0.5, moving))
    assert np.any(planar != 0)
    color = np.random.default_rng(9).uniform(0, 1, (H, W, 3)).astype(np.float32)
    target = _camera(0.01, (0.02, 0.0, 0.0))
    args = (color, depth, K, now.world_to_camera, K, target.world_to_camera)
    for a, b in zip(geometry.forward_warp_frame(*args, flow), geometry.forward_warp_frame(*args, flow.copy())):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("threads", [1, 3])
def test_the_warp_that_extrapolates_the_moving_pixels_itself_gives_the_warp_of_their_flows_bits(monkeypatch,
                                                                                               threads):
    # forward_warp_moved_frame against extrapolated_flow + forward_warp_frame: constant velocity and a parabola,
    # steps ahead and back, points sent behind the camera (NaN flow, dropped), one range and three (pass 1 cut
    # by rows weighted by the moving pixels, pass 2 by points as the plain warp cuts it: the same bits)
    from engine.geometry import splat
    monkeypatch.setenv(kernels.THREADS_ENV, str(threads))
    monkeypatch.setattr(splat, "MIN_POINTS_PER_THREAD", 64)
    depth, vectors, prev_depth, now, before = _velocity_inputs(4)
    velocity, moving = scene_velocity(depth, np.nan_to_num(vectors), prev_depth, now, before)
    rng = np.random.default_rng(10)
    velocity[np.unravel_index(moving[::7], (H, W))] = [0.0, 0.0, -50.0]  # these reach the camera plane
    acceleration = rng.normal(0, 0.05, (moving.size, 3)).astype(np.float32)
    color = rng.uniform(0, 1, (H, W, 3)).astype(np.float32)
    target = _camera(0.01, (0.02, 0.0, 0.0))
    args = (color, depth, K, now.world_to_camera, K, target.world_to_camera)
    assert len(splat._moved_rows(moving, H, W)) == threads
    from engine.geometry.reference import extrapolated_flow_reference
    for step, accel in ((0.5, None), (1.5, acceleration), (-1.0, acceleration), (3.0, None)):
        flow = extrapolated_flow(depth, velocity, K, step, moving, accel)
        np.testing.assert_array_equal(flow, extrapolated_flow_reference(depth, velocity, moving, accel, K,
                                                                        np.linalg.inv(K), step))
        assert np.isnan(flow).any() == (step > 0)
        plain = geometry.forward_warp_frame(*args, flow)
        moved = geometry.forward_warp_moved_frame(*args, velocity, moving, step, accel)
        for a, b in zip(moved, plain):
            np.testing.assert_array_equal(a, b)
        assert not np.array_equal(moved[0], geometry.forward_warp_frame(*args)[0])
    # no moving pixel: the plain warp
    for a, b in zip(geometry.forward_warp_moved_frame(*args, velocity, moving[:0], 1.0), geometry.forward_warp_frame(*args)):
        np.testing.assert_array_equal(a, b)


def test_the_moved_warps_rows_hold_even_shares_of_pixels_and_moving_pixels(monkeypatch):
    from engine.geometry import splat
    monkeypatch.setenv(kernels.THREADS_ENV, "2")
    monkeypatch.setattr(splat, "MIN_POINTS_PER_THREAD", 64)
    monkeypatch.setattr(splat, "MOVED_POINT_COST", 1.0)
    top = np.arange(8 * W)  # every pixel of the first 8 rows moves
    assert splat._moved_rows(top[:0], H, W) == [(0, H // 2), (H // 2, H)]
    ranges = splat._moved_rows(top, H, W)  # (32 + 8) rows' worth: 20 each, the first 8 rows count twice
    assert ranges == [(0, 12), (12, H)]
    monkeypatch.setattr(splat, "MOVED_POINT_COST", 2.0)  # (32 + 16) rows' worth: the first 8 rows count thrice
    assert splat._moved_rows(top, H, W) == [(0, 8), (8, H)]


@pytest.mark.parametrize("threads", [1, 3])
def test_the_moved_warp_refuses_moving_pixels_out_of_order_or_outside_the_frame(monkeypatch, threads):
    from engine.geometry import splat
    monkeypatch.setenv(kernels.THREADS_ENV, str(threads))
    monkeypatch.setattr(splat, "MIN_POINTS_PER_THREAD", 64)
    depth, vectors, prev_depth, now, before = _velocity_inputs(4)
    velocity, moving = scene_velocity(depth, np.nan_to_num(vectors), prev_depth, now, before)
    color = np.zeros((H, W, 3), np.float32)
    args = (color, depth, K, now.world_to_camera, K, now.world_to_camera, velocity)
    swapped = moving.copy()
    swapped[[5, -5]] = swapped[[-5, 5]]
    for bad in (moving[::-1], swapped, np.repeat(moving, 2), np.append(moving, H * W), np.insert(moving, 0, -1)):
        with pytest.raises(InputError, match="moving"):
            geometry.forward_warp_moved_frame(*args, bad, 1.0)
    with pytest.raises(InputError, match="acceleration"):
        geometry.forward_warp_moved_frame(*args, moving, 1.0, np.zeros((moving.size + 1, 3), np.float32))
    with pytest.raises(InputError, match="velocity"):
        geometry.forward_warp_moved_frame(*args[:-1], velocity[:, :-1], moving, 1.0)
