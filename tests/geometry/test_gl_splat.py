"""The GL backend's MPI forward splats (engine/geometry/backends/gl/splat.py, both of SPLATS) against their
oracle, engine.geometry.forward_warp_mpi, and the binned splat against the atomic one (the same bits).

Tolerances: alpha identical on >= 99.9 % of the pixels; where both are covered, colour within 1e-3 of
max(1, value) and depth within 1e-4 relative (sky: both +inf) on >= 99.5 % of them; no NaN anywhere.
"""
from __future__ import annotations

import numpy as np
import pytest

from engine import geometry as ng
from engine.core.errors import InputError
from engine.geometry.backends import gl as glb
from engine.geometry.backends.gl.splat import SPLATS
from tests.random_scenes import moving_cameras, pose, random_scene

if not glb.available():
    pytest.skip("no EGL context with compute shaders", allow_module_level=True)


_SPLATTERS: dict = {}


def SPLATTER(splat: str = SPLATS[0]) -> glb.GlSplatter:
    """One splatter of each splat for the module (its buffers grow to the largest test)."""
    if splat not in _SPLATTERS:
        _SPLATTERS[splat] = glb.GlSplatter(splat=splat)
    return _SPLATTERS[splat]


@pytest.fixture(params=SPLATS)
def splat(request) -> str:
    return request.param


def warp_both(mpi, k_src, t_src, k_dst, t_dst, flow=None, splat=SPLATS[0], **kwargs):
    """(the reference's warp, the GL splat ``splat``'s)."""
    ref = ng.forward_warp_mpi(mpi, k_src, t_src, k_dst, t_dst, flow, **kwargs)
    gl = SPLATTER(splat).forward_warp_mpi(mpi, k_src, t_src, k_dst, t_dst, flow, **kwargs)
    return ref, gl


def assert_parity(ref, gl) -> float:
    """Check the stated tolerances; returns the fraction of covered pixels."""
    (r_mpi, r_cov), (g_mpi, g_cov) = ref, gl
    for a, b in zip((*r_mpi, r_cov), (*g_mpi, g_cov)):
        assert a.shape == b.shape and b.dtype == np.float32
    assert not any(np.isnan(x).any() for x in (*g_mpi, g_cov))
    np.testing.assert_array_equal(g_mpi.plane_depths, r_mpi.plane_depths)
    assert np.mean(r_mpi.alpha == g_mpi.alpha) >= 0.999
    both = (r_mpi.alpha > 0) & (g_mpi.alpha > 0)
    if both.any():
        r_col, g_col = r_mpi.color[:, both], g_mpi.color[:, both]
        col_ok = (np.abs(r_col - g_col) < 1e-3 * np.maximum(1.0, np.abs(r_col))).all(axis=0)
        r_d, g_d = r_mpi.depth[both], g_mpi.depth[both]
        sky = np.isinf(r_d)
        with np.errstate(invalid="ignore"):
            depth_ok = np.where(sky, np.isinf(g_d), np.abs(g_d - r_d) <= 1e-4 * np.abs(r_d))
        assert np.mean(col_ok & depth_ok) >= 0.995
    assert np.abs(r_cov - g_cov).max() < 1e-4
    uncovered = g_mpi.alpha == 0
    assert (g_mpi.color[:, uncovered] == 0).all() and (g_mpi.depth[uncovered] == 0).all()
    return float(both.mean())


@pytest.mark.parametrize("num_planes", [1, 2, 4])
@pytest.mark.parametrize("with_flow", [False, True])
def test_random_one_hot_mpi_parity(num_planes, with_flow, splat):
    rng = np.random.default_rng(10 * num_planes + with_flow)
    h, w = 64, 96
    color, depth = random_scene(rng, h, w, sky=0.0, boxes=6)
    mpi = ng.build_mpi(color, depth, num_planes)
    k, t_src, t_dst = moving_cameras(rng, h, w, angle=0.05, shift=0.2)
    flow = rng.normal(0, 1.0, (3, num_planes, h, w)).astype(np.float32) if with_flow else None
    if flow is not None:
        flow[2] *= 0.05
    assert assert_parity(*warp_both(mpi, k, t_src, k, t_dst, flow, splat=splat)) > 0.1


@pytest.mark.parametrize("num_planes", [1, 4])
def test_sky_regions(num_planes, splat):
    rng = np.random.default_rng(7 + num_planes)
    h, w = 64, 96
    color, depth = random_scene(rng, h, w, sky=0.3, boxes=4)
    color[:20] *= 8.0  # HDR sky
    mpi = ng.build_mpi(color, depth, num_planes)
    k, t_src, t_dst = moving_cameras(rng, h, w)
    ref, gl = warp_both(mpi, k, t_src, k, t_dst, splat=splat)
    assert_parity(ref, gl)
    sky_pixels = np.isinf(gl[0].depth) & (gl[0].alpha > 0)
    assert sky_pixels.any() and np.array_equal(sky_pixels, np.isinf(ref[0].depth) & (ref[0].alpha > 0))


def test_all_sky_frame(splat):
    h, w = 32, 48
    rng = np.random.default_rng(3)
    color = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    mpi = ng.build_mpi(color, np.full((h, w), np.inf, np.float32), 2)
    k, t_src, t_dst = moving_cameras(rng, h, w)
    assert_parity(*warp_both(mpi, k, t_src, k, t_dst, splat=splat))


def test_points_behind_camera_and_leaving_the_frame(splat):
    rng = np.random.default_rng(5)
    h, w = 64, 96
    color, depth = random_scene(rng, h, w, sky=0.1, near=0.2, far=5.0)
    mpi = ng.build_mpi(color, depth, 2)
    k = np.array([[60.0, 0.0, w / 2], [0.0, 60.0, h / 2], [0.0, 0.0, 1.0]])
    t_src = np.eye(4)
    t_dst = np.eye(4)
    t_dst[:3, 3] = (0.8, 0.3, -1.5)  # camera moves forward past the nearest points, and sideways
    flow = np.zeros((3, 2, h, w), np.float32)
    flow[0] = 40.0  # large object motion pushes points out of the frame
    flow[2] = -0.1
    ref, gl = warp_both(mpi, k, t_src, k, t_dst, flow, splat=splat)
    assert_parity(ref, gl)
    valid = ng.reproject(depth, k, t_src, k, t_dst)[2]
    assert not valid.all()  # some points really are behind the destination camera


@pytest.mark.parametrize("out_size", [(48, 80), (90, 120)])
def test_out_size_differs_from_source(out_size, splat):
    rng = np.random.default_rng(11)
    h, w = 64, 96
    color, depth = random_scene(rng, h, w)
    mpi = ng.build_mpi(color, depth, 2)
    k, t_src, t_dst = moving_cameras(rng, h, w)
    ho, wo = out_size
    k_dst = np.diag([wo / w, ho / h, 1.0]) @ k
    ref, gl = warp_both(mpi, k, t_src, k_dst, t_dst, out_size=out_size, splat=splat)
    assert gl[1].shape == (2, ho, wo)
    assert_parity(ref, gl)


def test_empty_mpi_gives_zeros(splat):
    h, w = 32, 48
    z = 3
    mpi = ng.Mpi(np.ones((3, z, h, w), np.float32), np.ones((z, h, w), np.float32),
                 np.zeros((z, h, w), np.float32), np.array([1.0, 2.0, 4.0], np.float32))
    k, t_src, t_dst = moving_cameras(np.random.default_rng(0), h, w)
    ref, gl = warp_both(mpi, k, t_src, k, t_dst, splat=splat)
    assert_parity(ref, gl)
    assert all((x == 0).all() for x in (gl[0].color, gl[0].depth, gl[0].alpha, gl[1]))


@pytest.mark.parametrize("sharpness", [0.0, 200.0])
def test_sharpness_extremes(sharpness, splat):
    rng = np.random.default_rng(21)
    h, w = 64, 96
    color, depth = random_scene(rng, h, w, near=0.5, far=200.0)
    mpi = ng.build_mpi(color, depth, 1)
    k, t_src, t_dst = moving_cameras(rng, h, w)
    assert_parity(*warp_both(mpi, k, t_src, k, t_dst, sharpness=sharpness, splat=splat))


def test_large_frame_with_flow(splat):
    rng = np.random.default_rng(99)
    h, w = 270, 480
    color, depth = random_scene(rng, h, w, boxes=12)
    mpi = ng.build_mpi(color, depth, 4)
    k, t_src, t_dst = moving_cameras(rng, h, w, angle=0.03, shift=0.1)
    flow = rng.normal(0, 0.7, (3, 4, h, w)).astype(np.float32)
    flow[2] *= 0.02
    assert assert_parity(*warp_both(mpi, k, t_src, k, t_dst, flow, splat=splat)) > 0.1


def _bits(result) -> list:
    (mpi, cov) = result
    return [x.view(np.uint32) for x in (*mpi[:3], cov)]


@pytest.mark.parametrize("case", ["frame_sky_flow", "planes_flow", "zoomed_out", "plain_average"])
def test_binned_splat_gives_the_atomic_splats_bits(case):
    """The binned splat gathers per pixel the very fixed-point terms the atomic splat adds up in memory: exact
    integer sums, so the same bits whatever the order (here with sky, flow, several planes, ~100 points a bin
    and sharpness 0)."""
    rng = np.random.default_rng(["frame_sky_flow", "planes_flow", "zoomed_out", "plain_average"].index(case))
    h, w = 64, 96
    num_planes = 4 if case == "planes_flow" else 1
    color, depth = random_scene(rng, h, w, sky=0.3 if case == "frame_sky_flow" else 0.1, boxes=6)
    mpi = ng.build_mpi(color, depth, num_planes)
    k, t_src, t_dst = moving_cameras(rng, h, w, angle=0.05, shift=0.2)
    flow = None
    if case in ("frame_sky_flow", "planes_flow"):
        flow = rng.normal(0, 1.5, (3, num_planes, h, w)).astype(np.float32)
        flow[2] *= 0.05
    kwargs = {"sharpness": 0.0} if case == "plain_average" else {}
    k_dst = k
    if case == "zoomed_out":
        kwargs["out_size"] = (6, 9)
        k_dst = np.diag([9 / w, 6 / h, 1.0]) @ k
    ref, binned = warp_both(mpi, k, t_src, k_dst, t_dst, flow, splat="binned", **kwargs)
    atomic = SPLATTER("atomic").forward_warp_mpi(mpi, k, t_src, k_dst, t_dst, flow, **kwargs)
    assert_parity(ref, binned)
    for a, b in zip(_bits(atomic), _bits(binned)):
        np.testing.assert_array_equal(a, b)
    assert (binned[0].alpha > 0).any(axis=0).mean() > 0.5


def test_binned_splat_leaves_its_counts_zeroed_across_sizes():
    """The binned splat clears its bin counts once, when their buffer is made; every scan zeroes what it read.
    A splatter that warps a large, a small and the large MPI again gives what fresh splatters give, and its
    counts are all zero after each warp."""
    rng = np.random.default_rng(4)
    splatter = glb.GlSplatter(splat="binned")
    scenes = []
    for h, w, z in ((90, 120, 2), (40, 56, 1), (90, 120, 2)):
        color, depth = random_scene(rng, h, w, sky=0.1, boxes=5)
        k, t_src, t_dst = moving_cameras(rng, h, w)
        scenes.append((ng.build_mpi(color, depth, z), k, t_src, k, t_dst))
    for scene in scenes:
        got = splatter.forward_warp_mpi(*scene)
        fresh = glb.GlSplatter(splat="binned")
        for a, b in zip(_bits(got), _bits(fresh.forward_warp_mpi(*scene))):
            np.testing.assert_array_equal(a, b)
        fresh.release()
        counts = splatter.gl.call(lambda: np.frombuffer(splatter._pool["counts"].read(), np.uint32))
        assert counts.size >= scene[0].alpha.size and not counts.any()
    splatter.release()


def test_dispatches_spread_over_y_give_the_same_bits(monkeypatch, splat):
    """Past GL's 65535 workgroups along x a dispatch spreads its groups over y, the last row with spare groups
    (a 4K MPI's scan blocks, a frame's points): with 3 groups a row, every pass of both splats ends as with
    one row, and the binned scan's spare groups write nothing."""
    from engine.geometry.backends.gl import context

    rng = np.random.default_rng(12)
    h, w = 90, 120  # 11 224 bins a plane: 11 scan blocks, 43 groups of points
    color, depth = random_scene(rng, h, w, sky=0.1, boxes=5)
    mpi = ng.build_mpi(color, depth, 2)
    k, t_src, t_dst = moving_cameras(rng, h, w)
    one_row = SPLATTER(splat).forward_warp_mpi(mpi, k, t_src, k, t_dst)
    monkeypatch.setattr(context, "MAX_GROUPS_X", 3)
    spread = glb.GlSplatter(splat=splat)
    for a, b in zip(_bits(one_row), _bits(spread.forward_warp_mpi(mpi, k, t_src, k, t_dst))):
        np.testing.assert_array_equal(a, b)
    spread.release()


def test_an_unknown_splat_is_refused():
    with pytest.raises(InputError, match="splat"):
        glb.GlSplatter(splat="sorted")
    with pytest.raises(InputError, match="splat"):
        glb.GlFrameWarper(splat="")


def test_validation_matches_reference():
    h, w = 8, 12
    mpi = ng.build_mpi(np.zeros((h, w, 3), np.float32), np.ones((h, w), np.float32), 2)
    k, t_src, t_dst = moving_cameras(np.random.default_rng(1), h, w)
    splatter = SPLATTER()
    for kwargs in ({"out_size": (0, 3)}, {"sharpness": -1.0}):
        with pytest.raises(InputError):
            splatter.forward_warp_mpi(mpi, k, t_src, k, t_dst, **kwargs)
    with pytest.raises(InputError):
        splatter.forward_warp_mpi(mpi, k, t_src, k, t_dst, np.zeros((3, 1, h, w), np.float32))


def test_clear_words_sets_exactly_the_words_asked():
    """GlContext.clear_words (the splat's clear of its keys and sums) writes the value into the first words and
    leaves the rest; a byte count below one word writes nothing."""
    gl = glb.shared_context()
    data = np.arange(1000, dtype=np.uint32) + 7

    def run(nbytes, value):
        buf = gl.ctx.buffer(data.tobytes())
        gl.clear_words(buf, nbytes, value)
        out = np.frombuffer(buf.read(), np.uint32).copy()
        buf.release()
        return out

    out = gl.call(run, 4 * 777, 0xFFFFFFFF)
    assert (out[:777] == 0xFFFFFFFF).all() and (out[777:] == data[777:]).all()
    assert (gl.call(run, 4 * 1000, 0) == 0).all()
    assert (gl.call(run, 3, 5) == data).all()

