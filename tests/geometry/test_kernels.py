"""The compiled kernels (engine/geometry/kernels.py) against their numpy references, on ordinary and hard inputs.

Tolerances: the warp, the one-hot MPI and the 8-bit encoding run the same float32 / float64 operations in
the same order as their references and must agree exactly; compositing sums the planes sequentially in
float32 where ``np.einsum`` may pair them, so colour and depth agree to 1e-6 relative; hole-fill sources
are integers and agree exactly. No torch here: the engine's fast path is tested on a torch-free install.
"""
from __future__ import annotations

import numpy as np
import pytest

from engine import geometry as ng
from engine.core.colorspace import encode8_reference, encode8_table
from engine.geometry import holefill, reference, splat
from engine.predict import encode8, luma8
from tests.random_scenes import extreme_scene, moving_cameras, pose, random_scene


def _warp_both(mpi, k_src, t_src, k_dst, t_dst, flow=None, out_size=None, sharpness=ng.DEFAULT_SHARPNESS):
    out = out_size or mpi.alpha.shape[1:]
    args = (mpi, np.asarray(k_src, np.float64), np.asarray(t_src, np.float64), np.asarray(k_dst, np.float64),
            np.asarray(t_dst, np.float64), flow, out, sharpness)
    return splat.forward_warp_mpi_unchecked(*args), reference.forward_warp_mpi_reference(*args)


def _assert_same_warp(fast, reference):
    (mpi_a, cov_a), (mpi_b, cov_b) = fast, reference
    for a, b in zip(tuple(mpi_a[:3]) + (cov_a,), tuple(mpi_b[:3]) + (cov_b,)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(mpi_a.plane_depths, mpi_b.plane_depths)


@pytest.mark.parametrize("num_planes", [1, 2, 4, 8])
@pytest.mark.parametrize("with_flow", [False, True])
@pytest.mark.parametrize("seed", [0, 1])
def test_warp_kernel_equals_numpy_reference_on_random_scenes(num_planes, with_flow, seed):
    rng = np.random.default_rng(100 + seed)
    h, w = 23, 31
    color, depth = random_scene(rng, h, w, sky=0.2)
    k, t_src, t_dst = moving_cameras(rng, h, w, angle=0.2, shift=0.5)
    mpi = ng.build_mpi(color, depth, num_planes)
    flow = None
    if with_flow:
        flow = (rng.normal(0, 2, (3, num_planes, h, w)) * [[[[1]]], [[[1]]], [[[0.05]]]]).astype(np.float32)
        flow *= mpi.alpha[None]
    _assert_same_warp(*_warp_both(mpi, k, t_src, k, t_dst, flow))


def _assert_close_warp(fast, reference):
    """A split warp against the reference: alpha and where depth is +inf exactly, the rest to 1e-6."""
    (mpi_a, cov_a), (mpi_b, cov_b) = fast, reference
    np.testing.assert_array_equal(mpi_a.alpha, mpi_b.alpha)
    np.testing.assert_array_equal(np.isinf(mpi_a.depth), np.isinf(mpi_b.depth))
    finite = np.isfinite(mpi_b.depth)
    np.testing.assert_allclose(mpi_a.depth[finite], mpi_b.depth[finite], rtol=1e-6)
    np.testing.assert_allclose(mpi_a.color, mpi_b.color, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(cov_a, cov_b, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("threads", [2, 3])
def test_warp_split_over_threads_matches_the_reference(monkeypatch, threads):
    """The warp's passes split over threads (rows, points into one sum volume per part, added in order):
    the partial sums are added in another order than the sequential one, so the float64 sums may differ in
    their last bits; outputs agree to 1e-6 relative, alpha and the sky depth (+inf) exactly."""
    from engine.geometry import kernels
    monkeypatch.setenv(kernels.THREADS_ENV, str(threads))
    monkeypatch.setattr(splat, "MIN_POINTS_PER_THREAD", 64)
    monkeypatch.setattr(splat, "MIN_ROWS_PER_THREAD", 2)
    assert len(kernels.split_ranges(23 * 31, 64)) == threads
    rng = np.random.default_rng(7)
    h, w = 23, 31
    color, depth = random_scene(rng, h, w, sky=0.2)
    k, t_src, t_dst = moving_cameras(rng, h, w, angle=0.2, shift=0.5)
    for num_planes in (1, 4):
        mpi = ng.build_mpi(color, depth, num_planes)
        flow = (rng.normal(0, 3, (3, num_planes, h, w)) * [[[[1]]], [[[1]]], [[[0.05]]]]).astype(np.float32)
        for out_size in (None, (11, 17)):
            _assert_close_warp(*_warp_both(mpi, k, t_src, k, t_dst, flow * mpi.alpha[None], out_size))
    # the hard cases split too: points behind the camera, far off screen, depths from 1e-3 to 1e5, sky
    color, depth, k, poses = extreme_scene(7)
    for t_dst in poses:
        (fast, cov), reference = _warp_both(ng.build_mpi(color, depth, 4), k, np.eye(4), k, t_dst)
        _assert_close_warp((fast, cov), reference)
        assert np.isfinite(fast.color).all() and np.isfinite(cov).all()


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_the_frame_warp_is_the_one_plane_mpi_warp_and_composite_bit_for_bit(monkeypatch, threads):
    """``forward_warp_frame`` reads the frame in place and composites in ``normalize_frame``; the MPI path
    (``build_mpi(., 1)`` + ``forward_warp_mpi`` + ``composite``) is its oracle, equal bit for bit with the same
    thread split: colours with -0 and negative values, sky, flows of 2 and 3 channels, points behind the camera
    and off screen, depths 1e-3..1e5, 1x1 and one-row frames."""
    from engine.geometry import kernels
    monkeypatch.setenv(kernels.THREADS_ENV, str(threads))
    monkeypatch.setattr(splat, "MIN_POINTS_PER_THREAD", 64)
    monkeypatch.setattr(splat, "MIN_ROWS_PER_THREAD", 2)
    rng = np.random.default_rng(31)

    def both(color, depth, k, t_src, t_dst, flow=None):
        fast = ng.forward_warp_frame(color, depth, k, t_src, k, t_dst, flow)
        object_flow = None
        if flow is not None:
            object_flow = np.zeros((3, 1) + depth.shape, np.float32)
            object_flow[:flow.shape[2], 0] = np.moveaxis(flow, -1, 0)
        warped, _ = ng.forward_warp_mpi(ng.build_mpi(color, depth, 1), k, t_src, k, t_dst, object_flow)
        ref_color, ref_depth, _ = ng.composite(warped)
        for a, b in zip(fast, (ref_color, ref_depth, ng.disocclusion_mask(warped))):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)
            assert (np.signbit(a) == np.signbit(b)).all()  # -0 and +0 told apart

    h, w = 23, 31
    color, depth = random_scene(rng, h, w, sky=0.2)
    color[::3] -= 0.5  # negative colours; and -0 where a weighted sum is exactly zero
    color[1, :, :] = -0.0
    k, t_src, t_dst = moving_cameras(rng, h, w, angle=0.2, shift=0.5)
    both(color, depth, k, t_src, t_dst)
    both(color, depth, k, t_src, t_dst, rng.normal(0, 3, (h, w, 2)).astype(np.float32))
    both(color, depth, k, t_src, t_dst, (rng.normal(0, 1, (h, w, 3)) * [1, 1, 0.05]).astype(np.float32))
    color, depth, k, poses = extreme_scene(7)
    for t_dst in poses + [np.eye(4)]:
        both(color, depth, k, np.eye(4), t_dst)
    for hh, ww in ((1, 1), (1, 9)):
        c, d = rng.uniform(-1, 1, (hh, ww, 3)).astype(np.float32), np.full((hh, ww), 2.0, np.float32)
        kk = np.array([[5.0, 0, ww / 2], [0, 5.0, hh / 2], [0, 0, 1]])
        both(c, d, kk, np.eye(4), pose((0.05, 0, 0)))


def test_split_ranges_and_thread_setting(monkeypatch):
    from engine.geometry import kernels
    monkeypatch.setenv(kernels.THREADS_ENV, "4")
    assert kernels.split_ranges(100, 10) == [(0, 25), (25, 50), (50, 75), (75, 100)]
    assert kernels.split_ranges(100, 40) == [(0, 50), (50, 100)]
    assert kernels.split_ranges(5, 10) == [(0, 5)]
    assert kernels.run_ranges(lambda a, b: b - a, kernels.split_ranges(100, 10)) == [25, 25, 25, 25]
    # a split kernel called from a worker thread runs whole there (no pool waits on itself)
    assert kernels.run_ranges(lambda a, b: kernels.split_ranges(100, 10), [(0, 1), (1, 2)])[1] == [(0, 100)]
    monkeypatch.setenv(kernels.THREADS_ENV, "0")
    with pytest.raises(ValueError, match=kernels.THREADS_ENV):
        kernels.thread_count()


def test_run_beside_runs_a_step_on_a_kernel_thread_and_hands_back_its_result_or_error(monkeypatch):
    import threading
    from engine.geometry import kernels
    monkeypatch.setenv(kernels.THREADS_ENV, "2")
    started = threading.Event()

    def side():  # waits until the calling thread has gone on: they run at the same time
        assert started.wait(10)
        return threading.current_thread().name, kernels.split_ranges(100, 10)

    result = kernels.run_beside(side)
    started.set()
    name, ranges = result()
    assert name.startswith("interleave-kernel") and ranges == [(0, 100)]  # its split kernels run whole there
    # started in order: a zeroing queued behind a slower step, both beside the calling thread
    out = np.ones(1000, np.float32)
    first, zeroed = kernels.run_beside(lambda: out.sum()), kernels.run_beside(lambda: kernels.fill_zeros(out))
    zeroed()
    assert first() == 1000 and not out.any()
    failed = kernels.run_beside(lambda: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        failed()
    monkeypatch.setenv(kernels.THREADS_ENV, "1")  # one thread: at once, on the calling thread
    assert kernels.run_beside(lambda: threading.current_thread().name)() == threading.current_thread().name


def test_warp_kernel_hard_cases_equal_the_reference():
    """Points behind the camera, far off screen, huge and tiny depths, sky only, a box-sized output with
    other intrinsics, sharpness 0 (plain average), empty planes and an all-empty MPI."""
    color, depth, k, poses = extreme_scene(7)
    h, w = depth.shape
    for t_dst in poses + [np.eye(4)]:
        for num_planes in (1, 4):
            mpi = ng.build_mpi(color, depth, num_planes)
            for sharpness in (0.0, 50.0):
                _assert_same_warp(*_warp_both(mpi, k, np.eye(4), k, t_dst, sharpness=sharpness))
    sky = ng.build_mpi(color, np.full((h, w), np.inf, np.float32), 3)
    fast, _ = _warp_both(sky, k, np.eye(4), k, pose((0.1, 0.05, 0)))
    assert np.isinf(fast[0].depth[fast[0].alpha > 0]).all()
    _assert_same_warp(fast, _warp_both(sky, k, np.eye(4), k, pose((0.1, 0.05, 0)))[1])
    mpi = ng.build_mpi(color, np.where(depth > 10, np.float32(20.0), np.float32(1.0)), 5)  # 3 empty planes
    assert (mpi.alpha.reshape(5, -1).sum(axis=1) == 0).sum() == 3
    k_box = k.copy()
    k_box[:2, 2] -= (4, 3)
    _assert_same_warp(*_warp_both(mpi, k, np.eye(4), k_box * [[1.3], [1.3], [1]], pose((0, 0.02, 0), (0.1, 0, 0)),
                                  out_size=(9, 11)))
    empty = ng.Mpi(mpi.color * 0, mpi.depth * 0, mpi.alpha * 0, mpi.plane_depths)
    fast, ref = _warp_both(empty, k, np.eye(4), k, pose(translation=(0.1, 0, 0)))
    _assert_same_warp(fast, ref)
    assert not fast[0].alpha.any()


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("num_planes", [1, 3, 6])
def test_one_hot_mpi_kernel_equals_reference(monkeypatch, num_planes, threads):
    from engine.geometry import kernels

    monkeypatch.setenv("INTERLEAVE_KERNEL_THREADS", str(threads))
    monkeypatch.setattr(kernels, "MIN_PIXELS_PER_THREAD", 32)  # rows split over the threads
    rng = np.random.default_rng(3)
    color, depth = random_scene(rng, 19, 27, sky=0.3)
    for planes in (None, ng.plane_depths(depth[::2, ::2], num_planes)):
        fast = ng.build_mpi(color, depth, num_planes, planes)
        ref = reference.build_mpi_reference(color, depth, num_planes, fast.plane_depths)
        for a, b in zip(fast, ref):
            np.testing.assert_array_equal(a, b)
    all_sky = np.full(depth.shape, np.inf, np.float32)
    for a, b in zip(ng.build_mpi(color, all_sky, num_planes), reference.build_mpi_reference(color, all_sky, num_planes)):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("num_planes", [1, 2, 5])
def test_composite_kernel_equals_reference_with_soft_alpha_sky_and_holes(monkeypatch, num_planes, threads):
    from engine.geometry import kernels

    monkeypatch.setenv("INTERLEAVE_KERNEL_THREADS", str(threads))
    monkeypatch.setattr(kernels, "MIN_PIXELS_PER_THREAD", 32)  # rows split over the threads
    rng = np.random.default_rng(4)
    color, depth = random_scene(rng, 17, 21, sky=0.3)
    mpi = ng.build_mpi(color, depth, num_planes)
    soft = rng.uniform(0, 1, mpi.alpha.shape).astype(np.float32) * (rng.uniform(size=mpi.alpha.shape) < 0.7)
    soft_mpi = ng.Mpi(mpi.color * (soft > 0), np.where(soft > 0, np.where(mpi.depth > 0, mpi.depth, np.float32(3.0)),
                                                         np.float32(0.0)), soft, mpi.plane_depths)
    for m in (mpi, soft_mpi):
        fast, ref = ng.composite(m), reference.composite_reference(m)
        np.testing.assert_allclose(fast[0], ref[0], rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(fast[2], ref[2], rtol=1e-6, atol=1e-7)
        assert (np.isinf(fast[1]) == np.isinf(ref[1])).all()
        finite = np.isfinite(ref[1])
        np.testing.assert_allclose(fast[1][finite], ref[1][finite], rtol=1e-6)


def test_row_sources_kernel_equals_reference_on_random_holes():
    rng = np.random.default_rng(5)
    for trial in range(40):
        h, w = (int(v) for v in rng.integers(1, 40, 2))
        depth = rng.uniform(1, 10, (h, w)).astype(np.float32)
        depth[rng.uniform(size=(h, w)) < 0.1] = np.inf
        if trial % 3 == 0:
            depth = np.round(depth / 3).astype(np.float32)  # ties: the left side wins in both
        holes = rng.uniform(size=(h, w)) < rng.uniform(0, 1)
        if trial % 7 == 0:
            holes[:] = True  # rows with no known pixel
        np.testing.assert_array_equal(holefill.row_sources(depth, holes),
                                      reference.row_sources_reference(depth, holes))


def test_encode8_table_and_kernel_equal_the_reference_at_every_step():
    level, step = encode8_table()
    steps = step[np.isfinite(step)]
    assert steps.size == 255  # one per 8-bit code above 0
    rng = np.random.default_rng(6)
    values = np.concatenate([steps, np.nextafter(steps, np.float32(0)), np.nextafter(steps, np.float32(2)),
                             rng.uniform(-0.5, 1.5, 30000).astype(np.float32), rng.uniform(0, 1e-3, 3000),
                             np.array([0.0, -0.0, 1.0, 1e-45, -np.inf, np.inf, 1e30, 0.0031308])]).astype(np.float32)
    values = values[:values.size // 3 * 3].reshape(1, -1, 3)
    np.testing.assert_array_equal(encode8(values), encode8_reference(values))
    assert encode8(np.full((1, 1, 3), np.nan, np.float32)).tolist() == [[[0, 0, 0]]]


def test_luma8_is_the_grey_of_the_encoded_frame():
    import cv2

    rng = np.random.default_rng(8)
    color = rng.uniform(0, 2, (33, 47, 3)).astype(np.float32)
    np.testing.assert_array_equal(luma8(color), cv2.cvtColor(encode8_reference(color), cv2.COLOR_RGB2GRAY))


@pytest.mark.parametrize("factor", [1, 2, 4])
def test_flow_upsampling_kernel_matches_the_reference(factor):
    from engine.predict.decomp.reference import upsample_flow_reference
    from engine.predict.decomp.upsample import upsample_flow

    rng = np.random.default_rng(9)
    num_z, h, w = 4, 13, 17
    planes = rng.integers(0, num_z, (h, w))
    alpha = (planes[None] == np.arange(num_z)[:, None, None]).astype(np.float32)
    alpha[1] = 0.0  # an empty plane at the network's resolution
    flow = (rng.normal(0, 5, (3, num_z, h, w)) * alpha[None]).astype(np.float32)
    big_h, big_w = h * factor + factor - 1, w * factor + 1  # rows / columns past the last whole block
    full_planes = rng.integers(0, num_z, (big_h, big_w))
    full_alpha = (full_planes[None] == np.arange(num_z)[:, None, None]).astype(np.float32)
    full_alpha[3] = 0.0  # a plane with no full-resolution point
    fast = upsample_flow(flow, alpha, factor, full_alpha)
    ref = upsample_flow_reference(flow, alpha, factor, full_alpha)
    assert fast.shape == ref.shape == (3, num_z, big_h, big_w)
    np.testing.assert_allclose(fast, ref, rtol=1e-5, atol=1e-4)
    assert (fast[:, full_alpha == 0] == 0).all() and np.abs(fast).max() > 1.0


def test_thread_benchmark_runs_every_setting_and_restores_the_environment(tmp_path, monkeypatch, capsys):
    import json
    import os

    from engine.geometry import kernels
    from engine.io.rgbd import write_sequence
    from tests.synthetic import two_layer_sequence
    from tools import bench_threads

    monkeypatch.delenv(kernels.THREADS_ENV, raising=False)
    monkeypatch.delenv("INTERLEAVE_ORT_SPIN", raising=False)
    frames, objects = two_layer_sequence(11, width=96, height=64, camera_speed=0.05, object_speed=0.05)
    path = write_sequence(tmp_path / "seq", frames, fps=30.0, objects=objects)
    bench_threads.main([str(path), "--pairs", "2", "--repeats", "1", "--json", str(tmp_path / "b.json")])
    result = json.loads((tmp_path / "b.json").read_text())
    assert result["pairs"] == 2 and len(result["median_ms"]) == 5
    assert all(ms > 0 for ms in result["median_ms"].values())
    assert "decomp, onnxruntime spinning" in capsys.readouterr().out
    assert kernels.THREADS_ENV not in os.environ and "INTERLEAVE_ORT_SPIN" not in os.environ


def test_seen_before_kernel_equals_reference_on_random_and_extreme_scenes():
    rng = np.random.default_rng(11)
    for trial in range(30):
        h, w = (int(v) for v in rng.integers(3, 40, 2))
        depth = random_scene(rng, h, w)[1]
        k, t_n, t_prev = moving_cameras(rng, h, w, angle=0.3, shift=1.0)
        size_prev = (h, w) if trial % 2 else tuple(int(v) for v in rng.integers(1, 40, 2))
        args = (depth, k, t_n, k, t_prev, size_prev)
        np.testing.assert_array_equal(ng.seen_before(*args), reference.seen_before_reference(*args))
    for seed in range(4):
        _, depth, k, poses = extreme_scene(seed)  # sky, 1e-3..1e5, behind the camera, far off screen
        for t_prev in poses:
            args = (depth, k, np.eye(4), k, t_prev, depth.shape)
            np.testing.assert_array_equal(ng.seen_before(*args), reference.seen_before_reference(*args))
    k_n = np.array([[4.0, 0.0, 3.0], [0.0, 4.0, 2.0], [0.0, 0.0, 1.0]])
    k_prev = k_n + [[0.0, 0.0, 0.5], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]  # pixel centre x + 0.5 lands on x + 1
    seen = ng.seen_before(np.full((4, 6), 2.0, np.float32), k_n, np.eye(4), k_prev, np.eye(4), (4, 6))
    assert seen[:, :5].all() and not seen[:, 5].any()  # the last column lands on u = 6 = w: outside, [0, w)
    one = np.array([[np.inf]], np.float32)  # a 1x1 all-sky frame
    assert ng.seen_before(one, np.eye(3), np.eye(4), np.eye(3), np.eye(4), (1, 1)).shape == (1, 1)


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_image_kernels_split_over_rows_equal_their_references(monkeypatch, threads):
    """``seen_before`` and ``encode8`` cut an image's rows over the kernel threads (``kernels.split_rows``); each
    row's pixels are computed alone, so any split gives the reference's result exactly."""
    from engine.geometry import kernels

    monkeypatch.setenv("INTERLEAVE_KERNEL_THREADS", str(threads))
    monkeypatch.setattr(kernels, "MIN_PIXELS_PER_THREAD", 64)
    rng = np.random.default_rng(threads)
    h, w = 37, 53
    color, depth = random_scene(rng, h, w, sky=0.2)
    k, t_prev, t_n = moving_cameras(rng, h, w, angle=0.2, shift=0.5)
    assert len(kernels.split_rows(h, w)) == min(threads, h * w // 64)
    np.testing.assert_array_equal(ng.seen_before(depth, k, t_n, k, t_prev, (h - 5, w + 3)),
                                  reference.seen_before_reference(depth, k, t_n, k, t_prev, (h - 5, w + 3)))
    values = rng.uniform(-0.1, 1.2, (h, w, 3)).astype(np.float32)
    np.testing.assert_array_equal(encode8(values), encode8_reference(values))
