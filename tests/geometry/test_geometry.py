"""Geometry core: the numpy mirror (engine/geometry/ops.py) against the torch reference (models/geometry.py).

Matrix per op (kornia style): smoke + shapes, parity numpy vs torch on random scenes with sky and moving
cameras, exceptions, empty batch (torch), gradients (float64 gradcheck), extreme-but-legal values.

Tolerances of the mirror (stated in docs/geometry.md):
- points, uv, depths before splatting: float32 round-off, 1e-5 relative (+1e-4 px absolute on uv);
- MPI construction: exact (same float32 operations, plane depths composed in float64 in both);
- warps: the two modules may differ only where float32 round-off flips a plane or a pixel choice (the
  torch reference sums in float32, the mirror in float64), so at least 99.5% of the MPI pixels must agree
  on alpha, colour within 2e-4 (colours in [0, 1]) and depth within 1e-4 relative.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from engine import geometry as ng
from engine.core.errors import InputError
from engine.geometry import reference, splat
from models import geometry as tg
from tests.random_scenes import extreme_scene, intrinsics, moving_cameras, pose, random_scene, rotation

# ----------------------------------------------------------------------------------------------------
# Scenes


def tb(*arrays, dtype=torch.float32):
    """numpy arrays -> torch tensors with a batch axis of 1."""
    out = tuple(torch.as_tensor(np.asarray(a)).to(dtype)[None] for a in arrays)
    return out if len(out) > 1 else out[0]


def mpi_to_torch(mpi: ng.Mpi) -> tg.Mpi:
    return tg.Mpi(tb(mpi.color), tb(mpi.depth)[:, None], tb(mpi.alpha)[:, None], tb(mpi.plane_depths))


def mpi_to_numpy(mpi: tg.Mpi, item: int = 0) -> ng.Mpi:
    return ng.Mpi(mpi.color[item].detach().numpy(), mpi.depth[item, 0].detach().numpy(),
                  mpi.alpha[item, 0].detach().numpy(), mpi.plane_depths[item].detach().numpy())


def close_depth(a: np.ndarray, b: np.ndarray, rtol: float = 1e-4) -> np.ndarray:
    """Elementwise: equal infinities, or finite values within rtol."""
    both_inf = np.isinf(a) & np.isinf(b)
    with np.errstate(invalid="ignore"):
        near = np.abs(a - b) <= rtol * np.maximum(np.abs(a), 1e-6)
    return both_inf | (np.isfinite(a) & np.isfinite(b) & near)


def warp_agreement(np_mpi: ng.Mpi, np_cov: np.ndarray, t_mpi: tg.Mpi, t_cov: torch.Tensor) -> float:
    """Fraction of MPI pixels where the two warps agree (alpha, coverage, colour, depth)."""
    other = mpi_to_numpy(t_mpi)
    agree = (np_mpi.alpha == other.alpha) & (np.abs(np_cov - t_cov[0, 0].numpy()) <= 1e-4)
    agree &= (np.abs(np_mpi.color - other.color) <= 2e-4).all(axis=0)
    agree &= close_depth(np_mpi.depth, other.depth) | ((np_mpi.depth == 0) & (other.depth == 0))
    return float(agree.mean())


# ----------------------------------------------------------------------------------------------------
# Pixels, points, projection


def test_pixel_centers_are_half_integers_and_match():
    grid = ng.pixel_centers(3, 4)
    assert grid.shape == (3, 4, 2) and grid.dtype == np.float32
    assert grid[2, 3].tolist() == [3.5, 2.5]
    np.testing.assert_array_equal(grid, tg.pixel_centers(3, 4).numpy())
    grid[0, 0] = -1  # callers get a copy, not the cached grid
    assert ng.pixel_centers(3, 4)[0, 0].tolist() == [0.5, 0.5]


def test_unproject_parity_sky_is_a_direction():
    rng = np.random.default_rng(0)
    color, depth = random_scene(rng)
    k = intrinsics(*depth.shape)
    points = ng.unproject(depth, k)
    assert points.shape == depth.shape + (4,) and points.dtype == np.float32
    sky = np.isinf(depth)
    assert np.all(points[sky, 3] == 0) and np.all(points[~sky, 3] == 1) and np.all(np.isfinite(points))
    np.testing.assert_allclose(points[~sky, 2], depth[~sky])
    np.testing.assert_allclose(points, tg.unproject(tb(depth), tb(k))[0].numpy(), rtol=1e-5, atol=1e-6)
    # leading axes (an MPI's depth channel) unproject with one K
    stacked = ng.unproject(np.stack([depth, depth]), k)
    np.testing.assert_array_equal(stacked[1], points)


def test_relative_transform_is_dst_times_rigid_inverse():
    rng = np.random.default_rng(1)
    t_src, t_dst = pose(rng.normal(size=3), rng.normal(size=3)), pose(rng.normal(size=3), rng.normal(size=3))
    rel = ng.relative_transform(t_src, t_dst)
    np.testing.assert_allclose(rel, t_dst @ np.linalg.inv(t_src), atol=1e-12)
    np.testing.assert_allclose(ng.relative_transform(t_src, t_src), np.eye(4), atol=1e-12)
    rel_t = tg.relative_transform(tb(t_src, dtype=torch.float64)[0], tb(t_dst, dtype=torch.float64)[0])
    np.testing.assert_allclose(rel_t.numpy(), rel, atol=1e-12)


def test_project_parity_behind_camera_is_invalid_not_garbage():
    k = intrinsics(12, 16)
    points = np.array([[0.5, -0.2, 2.0, 1.0],   # in front
                       [0.5, -0.2, -2.0, 1.0],  # behind
                       [0.0, 0.0, 0.0, 1.0],    # at the camera centre
                       [1.0, 0.0, 1e-9, 1.0],   # grazing the camera plane
                       [0.1, 0.1, 1.0, 0.0],    # at infinity, in front
                       [0.1, 0.1, -1.0, 0.0]])  # at infinity, behind
    uv, z, valid = ng.project(points, k)
    assert valid.tolist() == [True, False, False, False, True, False]
    np.testing.assert_allclose(uv[0], [0.25 * 16 + 8, -0.1 * 16 + 6], rtol=1e-6)
    assert z[0] == 2.0 and z[4] == np.inf
    assert np.all(uv[~valid] == 0) and np.all(z[~valid] == 0) and np.all(np.isfinite(uv))
    uv_t, z_t, valid_t = tg.project(tb(points), tb(k))
    np.testing.assert_allclose(uv_t[0].numpy(), uv, rtol=1e-6)
    np.testing.assert_array_equal(z_t[0].numpy(), z)
    np.testing.assert_array_equal(valid_t[0].numpy(), valid)


@pytest.mark.parametrize("flow_channels", [None, 2, 3])
def test_reproject_parity_with_flow(flow_channels):
    rng = np.random.default_rng(2)
    _, depth = random_scene(rng, 16, 20)
    k, t_src, t_dst = moving_cameras(rng, 16, 20)
    flow = None if flow_channels is None else rng.normal(0, 1, (16, 20, flow_channels)).astype(np.float32)
    uv, z, valid = ng.reproject(depth, k, t_src, k, t_dst, flow)
    assert uv.shape == (16, 20, 2) and z.shape == valid.shape == (16, 20)
    uv_t, z_t, valid_t = tg.reproject(tb(depth), tb(k), tb(t_src), tb(k), tb(t_dst),
                                      None if flow is None else tb(flow))
    np.testing.assert_array_equal(valid, valid_t[0].numpy())
    np.testing.assert_allclose(uv, uv_t[0].numpy(), rtol=1e-5, atol=1e-3)
    assert np.all(close_depth(z, z_t[0].numpy(), 1e-5))


def test_reproject_follows_eq_6_2():
    """X = (d + dz) K^-1 [x + du, y + dv, 1], then T_dst T_src^-1, then K_dst (checked in float64)."""
    rng = np.random.default_rng(3)
    depth = rng.uniform(2, 5, (6, 8)).astype(np.float32)
    flow = rng.normal(0, 0.5, (6, 8, 3)).astype(np.float32)
    k_src, k_dst = intrinsics(6, 8, 1.0), intrinsics(6, 8, 1.3)
    t_src, t_dst = pose((0.1, -0.2, 0.05), (0.3, 0, 1)), pose((0.0, 0.1, 0.0), (0, 0.2, 0.5))
    uv, z, valid = ng.reproject(depth, k_src, t_src, k_dst, t_dst, flow)
    pix = ng.pixel_centers(6, 8).astype(np.float64) + flow[..., :2]
    rays = np.concatenate([pix, np.ones((6, 8, 1))], -1) @ np.linalg.inv(k_src).T
    cam = rays * (depth + flow[..., 2])[..., None]
    dst = np.concatenate([cam, np.ones((6, 8, 1))], -1) @ (t_dst @ np.linalg.inv(t_src)).T
    img = dst[..., :3] @ k_dst.T
    assert valid.all()
    np.testing.assert_allclose(uv, img[..., :2] / img[..., 2:], rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(z, dst[..., 2], rtol=1e-5)


def test_sky_moves_with_rotation_only():
    depth = np.full((8, 10), np.inf, np.float32)
    k = intrinsics(8, 10)
    uv, z, valid = ng.reproject(depth, k, np.eye(4), k, pose(translation=(5.0, -3.0, 100.0)))
    np.testing.assert_allclose(uv, ng.pixel_centers(8, 10), atol=1e-5)
    assert np.all(z == np.inf) and valid.all()
    rot = pose(rotvec=(0.0, 0.05, 0.0))
    uv, _, _ = ng.reproject(depth, k, np.eye(4), k, rot)
    rays = np.concatenate([ng.pixel_centers(8, 10), np.ones((8, 10, 1))], -1) @ np.linalg.inv(k).T
    img = rays @ rot[:3, :3].T @ k.T
    np.testing.assert_allclose(uv, img[..., :2] / img[..., 2:], atol=1e-4)


# ----------------------------------------------------------------------------------------------------
# Planes and MPI construction


def test_plane_depths_uniform_in_inverse_depth_and_parity():
    depth = np.array([[2.0, 8.0, np.inf], [4.0, 3.0, 5.0]], np.float32)
    planes = ng.plane_depths(depth, 5)
    assert planes[0] == 2.0 and planes[-1] == 8.0 and np.all(np.diff(planes) > 0)
    np.testing.assert_allclose(np.diff(1 / planes.astype(np.float64)), -(0.5 - 0.125) / 4, rtol=1e-6)
    np.testing.assert_array_equal(planes, tg.plane_depths(tb(depth), 5)[0].numpy())
    # no cap at 1000
    assert ng.plane_depths(np.array([[1.0, 1e5]], np.float32), 2)[-1] == 1e5


@pytest.mark.parametrize("depth, num_planes, expected", [
    (np.array([[3.0, 3.0, np.inf]]), 4, [3.0] * 4),              # a single finite value
    (np.full((2, 3), np.inf), 3, [np.inf] * 3),                  # all sky
    (np.array([[1.0, 4.0]]), 1, [1.6]),                          # one plane: halfway in inverse depth
])
def test_plane_depths_degenerate(depth, num_planes, expected):
    depth = depth.astype(np.float32)
    np.testing.assert_allclose(ng.plane_depths(depth, num_planes), expected, rtol=1e-6)
    np.testing.assert_allclose(tg.plane_depths(tb(depth), num_planes)[0].numpy(), expected, rtol=1e-6)


@pytest.mark.parametrize("num_planes", [1, 2, 4, 7])
def test_build_mpi_one_hot_nearest_in_inverse_depth_and_parity(num_planes):
    rng = np.random.default_rng(4)
    color, depth = random_scene(rng, 16, 20)
    mpi = ng.build_mpi(color, depth, num_planes)
    assert mpi.color.shape == (3, num_planes, 16, 20) and mpi.alpha.shape == mpi.depth.shape == (num_planes, 16, 20)
    assert set(np.unique(mpi.alpha)) <= {0.0, 1.0} and np.all(mpi.alpha.sum(0) == 1)
    index = mpi.alpha.argmax(0)
    sky = np.isinf(depth)
    assert np.all(index[sky] == num_planes - 1)
    distance = np.abs(1 / depth[None].astype(np.float64) - 1 / mpi.plane_depths[:, None, None].astype(np.float64))
    chosen = np.take_along_axis(distance, index[None], 0)[0]
    assert np.all(chosen <= distance.min(0) + 1e-6)
    np.testing.assert_array_equal(mpi.depth.sum(0), depth)  # true depth where alpha = 1, 0 elsewhere
    np.testing.assert_array_equal(mpi.color.sum(1), np.moveaxis(color, -1, 0))
    t_mpi = tg.build_mpi(tb(color), tb(depth), num_planes)
    for a, b in zip(mpi, mpi_to_numpy(t_mpi)):
        np.testing.assert_array_equal(a, b)


# ----------------------------------------------------------------------------------------------------
# Compositing


def soft_mpi(rng, num_planes=3, height=5, width=6, sky=True) -> ng.Mpi:
    alpha = rng.uniform(0, 1, (num_planes, height, width)).astype(np.float32)
    alpha[rng.uniform(size=alpha.shape) < 0.3] = 0
    depth = np.where(alpha > 0, rng.uniform(1, 10, alpha.shape), 0).astype(np.float32)
    if sky:
        depth[-1][alpha[-1] > 0] = np.inf
    color = (rng.uniform(0, 1, (3,) + alpha.shape) * (alpha > 0)).astype(np.float32)
    return ng.Mpi(color, depth, alpha, np.linspace(1, 10, num_planes).astype(np.float32))


def test_composite_visibility_and_holes_parity():
    rng = np.random.default_rng(5)
    mpi = soft_mpi(rng)
    mpi.alpha[:, 0, 0] = 0  # a hole
    color, depth, acc = ng.composite(mpi)
    assert color.shape == (5, 6, 3) and depth.shape == acc.shape == (5, 6)
    t_color, t_depth, t_acc = tg.composite(mpi_to_torch(mpi))
    np.testing.assert_allclose(color, t_color[0].numpy(), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(acc, t_acc[0].numpy(), rtol=1e-5, atol=1e-6)
    assert np.all(close_depth(depth, t_depth[0].numpy(), 1e-5))
    vis = ng.visibility(mpi)
    np.testing.assert_allclose(vis, tg.visibility(mpi_to_torch(mpi))[0, 0].numpy(), rtol=1e-6)
    np.testing.assert_allclose(vis[1], 1 - mpi.alpha[0], rtol=1e-6)
    holes = ng.disocclusion_mask(mpi)
    assert holes[0, 0] and holes.sum() == np.sum(~(mpi.alpha > 0).any(0))
    np.testing.assert_array_equal(holes, tg.disocclusion_mask(mpi_to_torch(mpi))[0].numpy())
    assert depth[0, 0] == np.inf and np.all(color[0, 0] == 0) and acc[0, 0] == 0
    assert not np.isnan(depth).any()
    # "over" back to front gives the same colour
    over = np.zeros((3, 5, 6), np.float64)
    for z in range(mpi.alpha.shape[0] - 1, -1, -1):
        over = mpi.color[:, z] * mpi.alpha[z] + (1 - mpi.alpha[z]) * over
    np.testing.assert_allclose(color, np.moveaxis(over, 0, -1), rtol=1e-5, atol=1e-6)


def test_composite_sky_only_gives_inf_depth():
    color = np.full((2, 3, 3), 0.5, np.float32)
    depth = np.array([[np.inf, 2.0, np.inf], [3.0, np.inf, 4.0]], np.float32)
    mpi = ng.build_mpi(color, depth, 3)
    out_color, out_depth, acc = ng.composite(mpi)
    np.testing.assert_array_equal(out_depth, depth)
    np.testing.assert_array_equal(out_color, color)
    assert np.all(acc == 1)


# ----------------------------------------------------------------------------------------------------
# Forward warping


@pytest.mark.parametrize("num_planes", [1, 4])
@pytest.mark.parametrize("with_flow", [False, True])
def test_forward_warp_mpi_parity_moving_cameras(num_planes, with_flow):
    rng = np.random.default_rng(10 + num_planes + 2 * with_flow)
    for _ in range(3):
        color, depth = random_scene(rng, 24, 32, sky=rng.uniform(0, 0.3))
        k, t_src, t_dst = moving_cameras(rng, 24, 32)
        mpi = ng.build_mpi(color, depth, num_planes)
        flow = None
        if with_flow:
            flow = rng.normal(0, [[[[1.5]]], [[[1.5]]], [[[0.3]]]], (3, num_planes, 24, 32)).astype(np.float32)
        warped, coverage = ng.forward_warp_mpi(mpi, k, t_src, k, t_dst, flow)
        t_warped, t_coverage = tg.forward_warp_mpi(mpi_to_torch(mpi), tb(k), tb(t_src), tb(k), tb(t_dst),
                                                   None if flow is None else tb(flow))
        assert warped.alpha.sum() > 0.2 * warped.alpha[0].size
        assert warp_agreement(warped, coverage, t_warped, t_coverage) > 0.995
        np.testing.assert_array_equal(warped.plane_depths, mpi.plane_depths)


def test_forward_warp_mpi_out_size_and_other_intrinsics():
    rng = np.random.default_rng(20)
    color, depth = random_scene(rng, 20, 24)
    k_src, t_src, t_dst = moving_cameras(rng, 20, 24, angle=0.05, shift=0.1)
    k_dst = intrinsics(15, 30, 0.7)
    mpi = ng.build_mpi(color, depth, 3)
    warped, coverage = ng.forward_warp_mpi(mpi, k_src, t_src, k_dst, t_dst, out_size=(15, 30))
    assert warped.color.shape == (3, 3, 15, 30) and coverage.shape == (3, 15, 30)
    t_warped, t_coverage = tg.forward_warp_mpi(mpi_to_torch(mpi), tb(k_src), tb(t_src), tb(k_dst), tb(t_dst),
                                               out_size=(15, 30))
    assert warp_agreement(warped, coverage, t_warped, t_coverage) > 0.995


def test_forward_warp_frame_parity_and_same_path_as_mpi():
    rng = np.random.default_rng(21)
    color, depth = random_scene(rng, 24, 32)
    k, t_src, t_dst = moving_cameras(rng, 24, 32)
    flow = rng.normal(0, 1, (24, 32, 2)).astype(np.float32)
    out_color, out_depth, holes = ng.forward_warp_frame(color, depth, k, t_src, k, t_dst, flow)
    t_color, t_depth, t_holes = tg.forward_warp_frame(tb(color), tb(depth), tb(k), tb(t_src), tb(k), tb(t_dst),
                                                      tb(flow))
    assert (holes == t_holes[0].numpy()).mean() > 0.995
    same = (holes == t_holes[0].numpy()) & ~holes
    assert (np.abs(out_color - t_color[0].numpy()) <= 2e-4).all(-1)[same].mean() > 0.995
    assert close_depth(out_depth, t_depth[0].numpy())[same].mean() > 0.995
    assert np.all(out_depth[holes] == np.inf) and np.all(out_color[holes] == 0)
    # the same code path as a one-plane MPI warp + composite
    object_flow = np.concatenate([np.moveaxis(flow, -1, 0), np.zeros((1, 24, 32), np.float32)])[:, None]
    warped, _ = ng.forward_warp_mpi(ng.build_mpi(color, depth, 1), k, t_src, k, t_dst, object_flow)
    ref_color, ref_depth, _ = ng.composite(warped)
    np.testing.assert_array_equal(out_color, ref_color)
    np.testing.assert_array_equal(out_depth, ref_depth)
    np.testing.assert_array_equal(holes, ng.disocclusion_mask(warped))


def test_object_flow_moves_points_and_depth():
    rng = np.random.default_rng(22)
    color = rng.uniform(0, 1, (6, 10, 3)).astype(np.float32)
    depth = np.full((6, 10), 4.0, np.float32)
    k = intrinsics(6, 10)
    flow = np.zeros((6, 10, 3), np.float32)
    flow[..., 0], flow[..., 2] = 3.0, 0.5  # 3 px right; 0.5 further away, still along the same ray
    for module, wrap in ((ng, lambda *a: a), (tg, lambda *a: tb(*a))):
        out = module.forward_warp_frame(*wrap(color, depth, k, np.eye(4), k, np.eye(4), flow))
        out_color, out_depth, holes = (np.asarray(o[0] if module is tg else o) for o in out)
        np.testing.assert_allclose(out_color[:, 3:], color[:, :7], atol=1e-6)
        np.testing.assert_allclose(out_depth[:, 3:], 4.5, rtol=1e-6)
        assert holes[:, :3].all() and not holes[:, 3:].any()


def test_points_off_screen_are_dropped_not_piled_at_the_border():
    color = np.zeros((4, 8, 3), np.float32)
    color[..., 0] = np.arange(8)[None] / 8  # colour encodes the source column
    depth = np.full((4, 8), 2.0, np.float32)
    k = intrinsics(4, 8)
    flow = np.zeros((4, 8, 2), np.float32)
    flow[..., 0] = 5.0
    out_color, _, holes = ng.forward_warp_frame(color, depth, k, np.eye(4), k, np.eye(4), flow)
    mpi = ng.build_mpi(color, depth, 1)
    object_flow = np.zeros((3, 1, 4, 8), np.float32)
    object_flow[0] = 5.0
    _, coverage = ng.forward_warp_mpi(mpi, k, np.eye(4), k, np.eye(4), object_flow)
    np.testing.assert_allclose(coverage[0, :, 5:], 1.0, atol=1e-6)  # exactly one point per pixel
    np.testing.assert_allclose(out_color[:, 5:, 0], np.tile(np.arange(3) / 8, (4, 1)), atol=1e-6)
    assert holes[:, :5].all() and not holes[:, 5:].any()
    # behind the destination camera: nothing lands, nothing wraps
    out_color, out_depth, holes = ng.forward_warp_frame(color, depth, k, np.eye(4), k,
                                                        pose(translation=(0, 0, -3.0)))
    assert holes.all() and np.all(out_depth == np.inf)


def test_soft_zbuffer_nearest_surface_wins_and_sky_loses():
    color = np.zeros((1, 3, 3), np.float32)
    color[0, 0] = [1, 0, 0]  # near
    color[0, 1] = [0, 1, 0]  # far
    color[0, 2] = [0, 0, 1]  # sky
    depth = np.array([[1.0, 1e4, np.inf]], np.float32)
    k = intrinsics(1, 3)
    flow = np.zeros((1, 3, 3), np.float32)
    flow[0, 0, 0], flow[0, 2, 0] = 1.0, -1.0  # near and sky onto the far point's pixel
    for module, wrap in ((ng, lambda *a: a), (tg, lambda *a: tb(*a))):
        out = module.forward_warp_frame(*wrap(color, depth, k, np.eye(4), k, np.eye(4), flow))
        out_color, out_depth = (np.asarray(o[0] if module is tg else o) for o in out[:2])
        np.testing.assert_allclose(out_color[0, 1], [1, 0, 0], atol=1e-6)
        np.testing.assert_allclose(out_depth[0, 1], 1.0, rtol=1e-5)
        flow[0, 0, 0] = 0.0  # without the near point: the far finite point beats the sky
        out = module.forward_warp_frame(*wrap(color, depth, k, np.eye(4), k, np.eye(4), flow))
        np.testing.assert_allclose(np.asarray(out[0][0] if module is tg else out[0])[0, 1], [0, 1, 0], atol=1e-6)
        flow[0, 0, 0] = 1.0


def test_sky_alone_keeps_infinite_depth_after_warp():
    color = np.full((6, 8, 3), 0.25, np.float32)
    depth = np.full((6, 8), np.inf, np.float32)
    k = intrinsics(6, 8)
    out_color, out_depth, holes = ng.forward_warp_frame(color, depth, k, np.eye(4), k, pose((0, 0.1, 0), (1, 2, 3)))
    assert np.all(out_depth == np.inf) and not np.isnan(out_color).any()
    np.testing.assert_allclose(out_color[~holes], 0.25, rtol=1e-6)
    t_out = tg.forward_warp_frame(tb(color), tb(depth), tb(k), tb(np.eye(4)), tb(k), tb(pose((0, 0.1, 0), (1, 2, 3))))
    np.testing.assert_array_equal(t_out[2][0].numpy(), holes)
    assert torch.all(torch.isinf(t_out[1]))


def _flow_warp_case(seed: int, h: int, w: int, num_planes: int, sky: float):
    """(MPI, K, T_src, T_dst, object flow ~ N(0, 1) px) of a random scene seen by two moving cameras."""
    rng = np.random.default_rng(seed)
    color, depth = random_scene(rng, h, w, sky=sky)
    k, t_src, t_dst = moving_cameras(rng, h, w)
    flow = rng.normal(0, 1, (3, num_planes, h, w)).astype(np.float32)
    return ng.build_mpi(color, depth, num_planes), k, t_src, t_dst, flow


@pytest.mark.parametrize("num_planes", [1, 3])
def test_numpy_warp_chunking_does_not_change_results(monkeypatch, num_planes):
    monkeypatch.setattr(splat, "forward_warp_mpi_unchecked", reference.forward_warp_mpi_reference)  # chunks: the numpy body's
    mpi, k, t_src, t_dst, flow = _flow_warp_case(27, 16, 20, num_planes, 0.3)
    whole = ng.forward_warp_mpi(mpi, k, t_src, k, t_dst, flow)
    monkeypatch.setattr(reference, "CHUNK", 37)
    chunked = ng.forward_warp_mpi(mpi, k, t_src, k, t_dst, flow)
    for a, b in zip(whole[0] + (whole[1],), chunked[0] + (chunked[1],)):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("num_planes", [1, 3])
def test_box_output_splats_only_the_landing_points_and_matches_the_whole_warp(monkeypatch, num_planes):
    monkeypatch.setattr(splat, "forward_warp_mpi_unchecked", reference.forward_warp_mpi_reference)  # compaction: the numpy body's
    mpi, k, t_src, t_dst, flow = _flow_warp_case(28, 40, 48, num_planes, 0.2)
    y0, y1, x0, x1 = 10, 26, 14, 38
    k_box = k.copy()
    k_box[0, 2] -= x0
    k_box[1, 2] -= y0
    box = ng.forward_warp_mpi(mpi, k, t_src, k_box, t_dst, flow, out_size=(y1 - y0, x1 - x0))
    monkeypatch.setattr(reference, "COMPACT_BELOW", 0.0)  # the reference: every point goes through the splat pass
    box_all_points = ng.forward_warp_mpi(mpi, k, t_src, k_box, t_dst, flow, out_size=(y1 - y0, x1 - x0))
    for a, b in zip(box[0] + (box[1],), box_all_points[0] + (box_all_points[1],)):
        np.testing.assert_array_equal(a, b)
    whole = ng.forward_warp_mpi(mpi, k, t_src, k, t_dst, flow)
    crop = (Ellipsis, slice(y0, y1), slice(x0, x1))
    assert box[0].alpha.sum() > 0.5 * box[0].alpha[0].size
    # coverage is the whole warp's (colours differ where points of several depths mix: the soft z-buffer's
    # depth range spans only the points that land)
    np.testing.assert_array_equal(box[0].alpha, whole[0].alpha[crop])
    np.testing.assert_allclose(box[1], whole[1][crop], rtol=1e-5, atol=1e-5)  # float32 taps shifted by the box


def test_warping_an_empty_mpi_gives_only_holes():
    mpi = ng.build_mpi(np.ones((4, 5, 3), np.float32), np.full((4, 5), 2.0, np.float32), 3)
    mpi = ng.Mpi(mpi.color * 0, mpi.depth * 0, mpi.alpha * 0, mpi.plane_depths)
    k = intrinsics(4, 5)
    warped, coverage = ng.forward_warp_mpi(mpi, k, np.eye(4), k, pose(translation=(0.1, 0, 0)))
    assert not warped.alpha.any() and not coverage.any() and ng.disocclusion_mask(warped).all()
    t_warped, t_coverage = tg.forward_warp_mpi(mpi_to_torch(mpi), tb(k), tb(np.eye(4)), tb(k),
                                               tb(pose(translation=(0.1, 0, 0))))
    assert not t_warped.alpha.any() and not t_coverage.any()


def test_torch_batch_matches_items():
    rng = np.random.default_rng(23)
    scenes = [random_scene(rng, 12, 16) for _ in range(2)]
    cams = [moving_cameras(rng, 12, 16) for _ in range(2)]
    color = torch.cat([tb(s[0]) for s in scenes])
    depth = torch.cat([tb(s[1]) for s in scenes])
    k, t_src, t_dst = (torch.cat([tb(c[i]) for c in cams]) for i in range(3))
    batch, batch_cov = tg.forward_warp_mpi(tg.build_mpi(color, depth, 3), k, t_src, k, t_dst)
    for i in range(2):
        item, item_cov = tg.forward_warp_mpi(tg.build_mpi(color[i:i + 1], depth[i:i + 1], 3), k[i:i + 1],
                                             t_src[i:i + 1], k[i:i + 1], t_dst[i:i + 1])
        for a, b in zip(item, batch):
            torch.testing.assert_close(a[0], b[i])
        torch.testing.assert_close(item_cov[0], batch_cov[i])


def test_torch_empty_batch():
    color, depth = torch.rand(0, 5, 6, 3), torch.rand(0, 5, 6) + 1
    k, t = torch.zeros(0, 3, 3), torch.zeros(0, 4, 4)
    mpi = tg.build_mpi(color, depth, 3)
    assert mpi.color.shape == (0, 3, 3, 5, 6) and mpi.plane_depths.shape == (0, 3)
    warped, coverage = tg.forward_warp_mpi(mpi, k, t, k, t)
    assert warped.alpha.shape == coverage.shape == (0, 1, 3, 5, 6)
    out = tg.forward_warp_frame(color, depth, k, t, k, t)
    assert out[0].shape == (0, 5, 6, 3) and out[2].shape == (0, 5, 6)
    assert tg.composite(mpi)[1].shape == (0, 5, 6) and tg.reproject(depth, k, t, k, t)[0].shape == (0, 5, 6, 2)
    assert tg.unproject(depth, k).shape == (0, 5, 6, 4)


def test_torch_float64_matches_float32():
    rng = np.random.default_rng(24)
    color, depth = random_scene(rng, 12, 16)
    k, t_src, t_dst = moving_cameras(rng, 12, 16)
    out32 = tg.forward_warp_frame(tb(color), tb(depth), tb(k), tb(t_src), tb(k), tb(t_dst))
    out64 = tg.forward_warp_frame(*(tb(a, dtype=torch.float64) for a in (color, depth, k, t_src, k, t_dst)))
    assert out64[0].dtype == torch.float64
    same = ~(out32[2] | out64[2])
    assert (out32[2] == out64[2]).float().mean() > 0.99
    assert ((out32[0] - out64[0]).abs() < 2e-4).all(-1)[same].float().mean() > 0.99


def test_inputs_are_not_modified():
    rng = np.random.default_rng(25)
    color, depth = random_scene(rng)
    k, t_src, t_dst = moving_cameras(rng, 12, 16)
    flow = rng.normal(0, 1, (12, 16, 3)).astype(np.float32)
    copies = [a.copy() for a in (color, depth, k, t_src, t_dst, flow)]
    ng.forward_warp_frame(color, depth, k, t_src, k, t_dst, flow)
    ng.reproject(depth, k, t_src, k, t_dst, flow)
    tensors = [tb(a) for a in (color, depth, k, t_src, t_dst, flow)]
    tensor_copies = [t.clone() for t in tensors]
    tg.forward_warp_frame(tensors[0], tensors[1], tensors[2], tensors[3], tensors[2], tensors[4], tensors[5])
    for a, b in zip((color, depth, k, t_src, t_dst, flow), copies):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(tensors, tensor_copies):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_extreme_but_legal_values_stay_finite():
    color, depth, k, poses = extreme_scene(26)
    for t_dst in poses:
        for num_planes in (1, 4):
            mpi = ng.build_mpi(color, depth, num_planes)
            warped, coverage = ng.forward_warp_mpi(mpi, k, np.eye(4), k, t_dst)
            t_warped, t_coverage = tg.forward_warp_mpi(mpi_to_torch(mpi), tb(k), tb(np.eye(4)), tb(k), tb(t_dst))
            for arrays in (warped, mpi_to_numpy(t_warped), (coverage, t_coverage.numpy())):
                for a in arrays:
                    assert not np.isnan(a).any()
            assert np.isfinite(warped.color).all() and torch.isfinite(t_warped.color).all()
            out = ng.composite(warped)
            assert not any(np.isnan(o).any() for o in out)


# ----------------------------------------------------------------------------------------------------
# Gradients


def test_gradcheck_composite_color_and_alpha():
    rng = np.random.default_rng(30)
    mpi = soft_mpi(rng, num_planes=3, height=2, width=3, sky=False)
    color = torch.tensor(mpi.color[None], dtype=torch.float64, requires_grad=True)
    alpha = torch.tensor(rng.uniform(0.1, 0.9, (1, 1, 3, 2, 3)), dtype=torch.float64, requires_grad=True)
    depth = torch.tensor(rng.uniform(1, 5, (1, 1, 3, 2, 3)), dtype=torch.float64)
    planes = torch.tensor([[1.0, 2.0, 4.0]], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda c, a: tg.composite(tg.Mpi(c, depth, a, planes)), (color, alpha))


def test_gradcheck_splat_color_flow_alpha():
    """Warped colour and depth w.r.t. colour, object flow and (soft) alpha, on a tiny float64 MPI.

    Depths sit on the planes and flows are small, so no point changes plane; fractional positions are
    random, so no finite difference straddles a pixel boundary or the snap zone (with probability ~1).
    """
    rng = np.random.default_rng(31)
    h, w, num_planes = 3, 4, 2
    depth = np.where(rng.uniform(size=(h, w)) < 0.5, 2.0, 4.0)
    k = torch.tensor(intrinsics(h, w)[None], dtype=torch.float64)
    t_src = torch.eye(4, dtype=torch.float64)[None]
    t_dst = torch.tensor(pose((0.0, 0.01, 0.0), (0.05, 0.02, 0.0))[None], dtype=torch.float64)
    mpi = tg.build_mpi(torch.tensor(rng.uniform(0, 1, (1, h, w, 3))), torch.tensor(depth[None]), num_planes)
    color = mpi.color.clone().requires_grad_(True)
    flow = torch.tensor(rng.normal(0, 0.2, (1, 3, num_planes, h, w)) * np.array([1, 1, 0.05])[:, None, None, None],
                        requires_grad=True)
    alpha = (mpi.alpha * torch.tensor(rng.uniform(0.5, 1.0, mpi.alpha.shape))).requires_grad_(True)

    def warp(c, f, a):
        warped, coverage = tg.forward_warp_mpi(tg.Mpi(c, mpi.depth, a, mpi.plane_depths), k, t_src, k, t_dst, f)
        return warped.color, warped.depth, coverage

    assert torch.autograd.gradcheck(warp, (color, flow, alpha), eps=1e-7, atol=1e-5)


def test_gradients_are_finite_with_sky_and_points_behind():
    color, depth = random_scene(np.random.default_rng(32), 8, 10, sky=0.3)
    c = tb(color).requires_grad_(True)
    flow = torch.zeros(1, 8, 10, 3, requires_grad=True)
    k = tb(intrinsics(8, 10))
    out = tg.forward_warp_frame(c, tb(depth), k, tb(np.eye(4)), k, tb(pose((0, 2.5, 0), (0, 0, 3.0))), flow)
    (out[0].sum() + torch.where(torch.isfinite(out[1]), out[1], 0).sum()).backward()
    assert torch.isfinite(c.grad).all() and torch.isfinite(flow.grad).all()


# ----------------------------------------------------------------------------------------------------
# Exceptions


def _numpy_calls():
    c, d, k, t = np.zeros((4, 5, 3), np.float32), np.ones((4, 5), np.float32), intrinsics(4, 5), np.eye(4)
    mpi = ng.build_mpi(c, d, 2)
    return {
        "unproject depth 1-D": (lambda: ng.unproject(np.ones(5, np.float32), k), "depth"),
        "unproject K 4x4": (lambda: ng.unproject(d, np.eye(4)), "intrinsics"),
        "project points 3": (lambda: ng.project(np.ones((5, 3)), k), "points_h"),
        "relative 3x3": (lambda: ng.relative_transform(np.eye(3), t), "src_world_to_camera"),
        "reproject flow 4ch": (lambda: ng.reproject(d, k, t, k, t, np.zeros((4, 5, 4))), "flow"),
        "reproject flow size": (lambda: ng.reproject(d, k, t, k, t, np.zeros((4, 6, 3))), "flow"),
        "reproject T_dst": (lambda: ng.reproject(d, k, t, k, np.eye(3)), "T_dst"),
        "plane_depths Z=0": (lambda: ng.plane_depths(d, 0), "num_planes"),
        "build color size": (lambda: ng.build_mpi(np.zeros((4, 6, 3), np.float32), d, 2), "color"),
        "build int depth": (lambda: ng.build_mpi(c, np.ones((4, 5), np.int32), 2), "depth"),
        "build Z=0": (lambda: ng.build_mpi(c, d, 0), "num_planes"),
        "composite Z=0": (lambda: ng.composite(ng.Mpi(*(a[:, :0] if a.ndim == 4 else a[:0] for a in mpi))), "mpi"),
        "composite not mpi": (lambda: ng.composite(c), "mpi"),
        "warp alpha shape": (lambda: ng.forward_warp_mpi(mpi._replace(alpha=mpi.alpha[:1]), k, t, k, t), "mpi.alpha"),
        "warp flow shape": (lambda: ng.forward_warp_mpi(mpi, k, t, k, t, np.zeros((2, 2, 4, 5))), "object_flow"),
        "warp sharpness": (lambda: ng.forward_warp_mpi(mpi, k, t, k, t, sharpness=-1), "sharpness"),
        "warp out_size": (lambda: ng.forward_warp_mpi(mpi, k, t, k, t, out_size=(0, 4)), "out_size"),
        "frame K_src": (lambda: ng.forward_warp_frame(c, d, np.eye(4), t, k, t), "K_src"),
        "frame flow": (lambda: ng.forward_warp_frame(c, d, k, t, k, t, np.zeros((4, 5, 1))), "flow"),
        "visibility": (lambda: ng.visibility(mpi._replace(plane_depths=np.ones(3, np.float32))), "mpi.plane_depths"),
    }


def _torch_calls():
    c, d = torch.zeros(1, 4, 5, 3), torch.ones(1, 4, 5)
    k, t = tb(intrinsics(4, 5)), torch.eye(4)[None]
    mpi = tg.build_mpi(c, d, 2)
    return {
        "unproject K batch": (lambda: tg.unproject(d, k.expand(2, 3, 3)), "intrinsics"),
        "project points 3": (lambda: tg.project(torch.ones(1, 5, 3), k), "points_h"),
        "reproject flow": (lambda: tg.reproject(d, k, t, k, t, torch.zeros(1, 4, 5, 4)), "flow"),
        "reproject T batch": (lambda: tg.reproject(d, k, t.expand(2, 4, 4), k, t), "T_src"),
        "build Z=0": (lambda: tg.build_mpi(c, d, 0), "num_planes"),
        "build int depth": (lambda: tg.build_mpi(c, torch.ones(1, 4, 5, dtype=torch.int64), 2), "depth"),
        "build unbatched": (lambda: tg.build_mpi(c[0], d[0], 2), "depth"),
        "composite Z=0": (lambda: tg.composite(tg.Mpi(*(a[:, :, :0] if a.dim() == 5 else a[:, :0] for a in mpi))),
                          "mpi"),
        "warp flow": (lambda: tg.forward_warp_mpi(mpi, k, t, k, t, torch.zeros(1, 2, 2, 4, 5)), "object_flow"),
        "warp sharpness": (lambda: tg.forward_warp_mpi(mpi, k, t, k, t, sharpness=float("nan")), "sharpness"),
        "frame color": (lambda: tg.forward_warp_frame(c[..., :2], d, k, t, k, t), "color"),
        "disocclusion": (lambda: tg.disocclusion_mask(mpi._replace(depth=mpi.depth[:, :, :1])), "mpi.depth"),
    }


@pytest.mark.parametrize("name", list(_numpy_calls()))
def test_numpy_input_errors_name_the_argument(name):
    call, field = _numpy_calls()[name]
    with pytest.raises(InputError) as info:
        call()
    assert info.value.field == field


@pytest.mark.parametrize("name", list(_torch_calls()))
def test_torch_input_errors_name_the_argument(name):
    call, field = _torch_calls()[name]
    with pytest.raises(InputError) as info:
        call()
    assert info.value.field == field


# ----------------------------------------------------------------------------------------------------
# Export


def test_torch_export_forward_warp_frame():
    class Warp(torch.nn.Module):
        def forward(self, color, depth, k_src, t_src, k_dst, t_dst):
            return tg.forward_warp_frame(color, depth, k_src, t_src, k_dst, t_dst)

    rng = np.random.default_rng(40)
    color, depth = random_scene(rng, 6, 8)
    k, t_src, t_dst = moving_cameras(rng, 6, 8)
    args = (tb(color), tb(depth), tb(k), tb(t_src), tb(k), tb(t_dst))
    program = torch.export.export(Warp(), args)
    for a, b in zip(program.module()(*args), Warp()(*args)):
        torch.testing.assert_close(a, b)
