"""Motion vectors of a dynamic field (``engine.fields.dynamic.field_motion_vectors`` and its GL pass).

The *programmed* DeRF of ``tools.programmed_field`` makes the truth known in closed form: its flow is
``(max_flow tanh(GAIN (1 + beta x)(tau + 2) + BIAS), 0, 0)``. With beta = 0 every point of the cube moves by
the same world translation between two times, so the vectors equal ``rigid_motion_vectors`` with that
translation; with beta != 0 the inversion of the motion field is iterative and checked by its residual.
"""
from __future__ import annotations

import numpy as np
import pytest

from engine.core.errors import InputError
from engine.core.frames import Camera
from engine.fields import gl as glfield
from engine.fields.dynamic import COHERENCE, deform_np, earlier_points, field_motion_vectors, normalize_time
from engine.fields.render import camera_rays_np, contract_np, uncontract_np
from engine.geometry.motion import camera_motion_vectors, rigid_motion_vectors
from models.fields.assets import dynamic_assets, load_assets
from tests.fields.test_dynamic_field import _model
from tests.fields.test_field_train import look_at_origin
from tools.programmed_field import flow_x, programmed_arrays, write_export

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def programmed(beta: float = 0.0, *, opaque: bool = False, zigzag: bool = False):
    """The programmed DeRF of ``tools.programmed_field`` (default here: its untrained fog, dense everywhere)."""
    return load_assets(*programmed_arrays(beta, opaque=opaque, zigzag=zigzag), "dynamic")


def camera(azimuth_deg: float, size: int = 24, distance: float = 3.0) -> Camera:
    focal = size / (2 * np.tan(np.radians(25.0)))
    k = np.array([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1.0]])
    a, e = np.radians(azimuth_deg), np.radians(20.0)
    eye = distance * np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)])
    return Camera(k, look_at_origin(eye))


def depth_with_sky(size: int = 24) -> np.ndarray:
    """Planar depth 3 (a plane through the cube's centre region, part of it outside the cube) with a sky band."""
    depth = np.full((size, size), 3.0, np.float32)
    depth[:3] = np.inf
    return depth


def test_a_translating_field_gives_the_rigid_vectors_of_its_translation():
    assets = programmed()
    cam, prev = camera(0.0), camera(4.0)
    depth = depth_with_sky()
    times = assets.time_range
    t, t_prev = times[0] + 0.75 * (times[1] - times[0]), times[0] + 0.25 * (times[1] - times[0])
    got = field_motion_vectors(assets, cam.intrinsics, cam.world_to_camera, depth, t, prev.world_to_camera, t_prev)
    tau, tau_prev = normalize_time(t, times), normalize_time(t_prev, times)
    half = (np.asarray(assets.scene["box_max"]) - np.asarray(assets.scene["box_min"])) / 2
    # c' = c + flow(tau) - flow(tau'): the same shift everywhere
    shift = half[0] * (flow_x(assets.max_flow, 0.0, tau) - flow_x(assets.max_flow, 0.0, tau_prev))
    assert abs(shift) > 0.05  # the case moves points by a visible amount
    origin, dirs = camera_rays_np(cam.intrinsics, cam.world_to_camera, 24, 24)
    finite = np.isfinite(depth).reshape(-1)
    points = (origin + np.where(finite, depth.reshape(-1), 0.0)[:, None] * dirs).astype(np.float32)
    inside = (finite & (np.abs(contract_np(assets.scene, points, 0.0)) <= 1.0).all(-1)).reshape(24, 24)
    assert 0 < inside.sum() < np.isfinite(depth).sum()  # moving and static pixels both
    motion = np.eye(4)
    motion[0, 3] = shift
    want = rigid_motion_vectors(depth, cam, prev, inside.astype(np.int32), {1: motion})
    assert np.array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_allclose(got[~np.isnan(want)], want[~np.isnan(want)], atol=2e-3)


def test_the_vectors_for_mvec_keep_steady_motion_and_drop_motion_that_turned():
    """``coherence`` (what the renderers give ``mvec``): the programmed translation, steady over the interval
    before, keeps the field's vectors; the zig-zag translation, which reversed during that interval, gets the
    camera's vectors alone; with no interval before inside the trained range nothing is dropped."""
    cam, prev = camera(0.0), camera(4.0)
    depth = depth_with_sky()
    camera_only = camera_motion_vectors(depth, cam, prev)

    def vectors(assets, tau: float, tau_earlier: float, coherence):
        t0, t1 = assets.time_range
        at = [t0 + (x + 1.0) / 2.0 * (t1 - t0) for x in (tau, tau_earlier)]
        return field_motion_vectors(assets, cam.intrinsics, cam.world_to_camera, depth, at[0], prev.world_to_camera,
                                    at[1], coherence=coherence)

    steady, zigzag = programmed(), programmed(zigzag=True)
    for assets, tau, tau_earlier in ((steady, 0.5, 0.0), (zigzag, -0.5, -0.9)):  # the latter: tau_before -1.3
        plain = vectors(assets, tau, tau_earlier, None)
        assert np.nanmax(np.abs(plain - camera_only)) > 0.5  # the field's points moved
        np.testing.assert_array_equal(vectors(assets, tau, tau_earlier, COHERENCE), plain)
    # zig-zag rows at tau -1, -1/3, 1/3, 1: -0.5 -> -0.2 moved one way, -0.2 -> 0.1 the other
    plain, turned = vectors(zigzag, 0.1, -0.2, None), vectors(zigzag, 0.1, -0.2, COHERENCE)
    assert np.nanmax(np.abs(plain - camera_only)) > 0.5
    assert np.array_equal(np.isnan(turned), np.isnan(camera_only))
    np.testing.assert_allclose(turned[np.isfinite(camera_only)], camera_only[np.isfinite(camera_only)], atol=2e-3)


def test_mvec_on_the_demos_vectors_does_not_extrapolate_a_motion_that_turned():
    """The zig-zag translation reverses at the time rows -1/3 and 1/3: frames at tau -1/3 and 1/3 (the box moved
    one way over that interval, the other way over the one before) predict tau 2/3, where it moves back.
    ``mvec`` on the field's motion as it is carries the box on the wrong way, below ``reproject``; on the
    vectors the demo gives it (the motion turned: the camera's alone) it is ``reproject``."""
    from demos.upsample import field_vector_source
    from engine.core.frames import Frame
    from engine.eval.metrics import psnr
    from engine.fields.dynamic import render_dynamic_field
    from engine.predict import Target, make_predictor

    assets = programmed(opaque=True, zigzag=True)
    t0, t1 = assets.time_range
    times = [t0 + (tau + 1.0) / 2.0 * (t1 - t0) for tau in (-1.0 / 3.0, 1.0 / 3.0, 2.0 / 3.0)]
    cameras = [camera(azimuth, size=48) for azimuth in (0.0, 2.0, 3.0)]
    frames = []
    for i, (cam, t) in enumerate(zip(cameras, times)):
        out = render_dynamic_field(assets, cam.intrinsics, cam.world_to_camera, 48, 48, t)
        frames.append(Frame(index=i, time=(0.0, 2.0, 3.0)[i], color=out["color"], depth=out["depth"], camera=cam))
    older, newest, truth = frames
    target = Target(truth.camera, truth.time, truth.index)
    reproject = psnr(truth.color, make_predictor("reproject", backend="cpu").predict([older, newest], target).color)
    scores = {}
    for name, vectors in (("as is", field_motion_vectors(assets, newest.camera.intrinsics,
                                                         newest.camera.world_to_camera, newest.depth, times[1],
                                                         older.camera.world_to_camera, times[0])),
                          ("demo", field_vector_source(assets, cameras, times)(0, 1, newest))):
        newest.motion_vectors = vectors
        scores[name] = psnr(truth.color, make_predictor("mvec", backend="cpu").predict([older, newest], target).color)
    assert scores["as is"] < reproject - 1.0
    assert scores["demo"] >= reproject - 0.01


def residual(assets, earlier, coords, tau, tau_earlier):
    n = coords.shape[0]
    canonical, _ = deform_np(assets, coords, np.full(n, tau, np.float32))
    back, _ = deform_np(assets, np.clip(earlier, -1, 1), np.full(n, tau_earlier, np.float32))
    return np.abs(back - canonical).max(axis=1)


def test_the_iterative_inversion_lands_on_the_same_canonical_point():
    rng = np.random.default_rng(0)
    coords = rng.uniform(-0.5, 0.5, (500, 3)).astype(np.float32)
    contracting = programmed(beta=0.3)  # |d flow / dx| <= 0.3 * 0.6 * 1.6 < 1 at tau' = -0.4
    earlier, found = earlier_points(contracting, coords, 0.6, -0.4)
    assert found.all() and residual(contracting, earlier, coords, 0.6, -0.4).max() < 1e-5
    assert np.abs(earlier - coords).max() > 0.05  # the points did move
    one_step, _ = earlier_points(contracting, coords, 0.6, -0.4, iterations=1)
    assert np.abs(one_step - earlier).max() > 1e-4  # a spatially varying flow needs the iteration
    # points whose earlier position leaves the cube, or where the iteration does not settle, are not found
    wide = rng.uniform(-0.95, 0.95, (500, 3)).astype(np.float32)
    earlier, found = earlier_points(programmed(beta=0.8), wide, 0.6, -0.4)
    assert 0 < found.sum() < found.size
    assert residual(programmed(beta=0.8), earlier[found], wide[found], 0.6, -0.4).max() <= 1e-3


def fixed_point(assets, coords, tau, tau_earlier, steps=8):
    """The plain iteration ``c' <- C - flow(c', tau')`` from c and which points it settles (the test's foil)."""
    n = coords.shape[0]
    canonical, _ = deform_np(assets, coords, np.full(n, tau, np.float32))
    taus = np.full(n, tau_earlier, np.float32)
    earlier = coords.copy()
    for _ in range(steps):
        earlier = canonical - deform_np(assets, np.clip(earlier, -1, 1), taus)[1]
    return (np.abs(earlier) <= 1).all(axis=1) & (residual(assets, earlier, coords, tau, tau_earlier) <= 1e-3)


def test_newton_finds_the_earlier_point_where_the_flow_varies_faster_than_the_points_move():
    """A moving object's border in a trained field: the flow to the canonical time changes faster in space than 1
    (here d flow_x / dx reaches 3 * 0.6 * 1.5 = 2.7 at tau' = 1), so the fixed-point iteration diverges. The map
    c -> c + flow stays one-to-one (d flow_x / dx > 0), and Newton's steps find every point, to 1e-5."""
    rng = np.random.default_rng(1)
    coords = rng.uniform(-0.5, 0.5, (500, 3)).astype(np.float32)
    steep = programmed(beta=1.5)
    for tau, tau_earlier in ((-1.0, 1.0), (-0.6, 0.9), (0.6, -0.4)):
        earlier, found = earlier_points(steep, coords, tau, tau_earlier)
        assert found.all() and residual(steep, earlier, coords, tau, tau_earlier).max() < 1e-5
        assert fixed_point(steep, coords, tau, tau_earlier).mean() < 0.5  # most diverge
    # its x is the closed form's root: x' + flow_x(x') = x + flow_x(x); y and z do not move
    earlier, _ = earlier_points(steep, coords, -1.0, 1.0)
    x, xe = coords[:, 0], earlier[:, 0]
    np.testing.assert_allclose(xe + flow_x(steep.max_flow, xe, 1.0, 1.5), x + flow_x(steep.max_flow, x, -1.0, 1.5),
                               atol=2e-5)
    np.testing.assert_array_equal(earlier[:, 1:], coords[:, 1:])


def test_the_same_time_gives_the_camera_motion_alone_and_kplanes_never_move():
    cam, prev = camera(10.0), camera(13.0)
    depth = depth_with_sky()
    for assets in (load_assets(*dynamic_assets(_model("derf")), "dynamic"),
                   load_assets(*dynamic_assets(_model("kplanes")), "dynamic")):
        t = sum(assets.time_range) / 2
        got = field_motion_vectors(assets, cam.intrinsics, cam.world_to_camera, depth, t, prev.world_to_camera,
                                   t if assets.has_motion else assets.time_range[0])
        want = camera_motion_vectors(depth, cam, prev)
        np.testing.assert_allclose(got, want, atol=2e-3)


def test_contraction_round_trips_in_both_scene_kinds():
    rng = np.random.default_rng(1)
    box = {"kind": "bounded-360", "near": 1.0, "far": 5.0, "box_min": [-1.0, -2.0, 0.0], "box_max": [1.0, 2.0, 3.0]}
    ref = camera(30.0, size=32)
    ndc = {"kind": "forward-facing", "near": 0.5, "far": float("inf"), "ndc_intrinsics": ref.intrinsics.tolist(),
           "ndc_world_to_camera": ref.world_to_camera.tolist(), "ndc_size": [32.0, 32.0]}
    for scene in (box, ndc):
        coords = rng.uniform(-0.95, 0.95, (300, 3)).astype(np.float32)
        np.testing.assert_allclose(contract_np(scene, uncontract_np(scene, coords, 0.1), 0.1), coords, atol=2e-4)
    assert np.isnan(uncontract_np(ndc, np.array([[0.0, 0.0, 1.0]], np.float32), 0.1)).all()  # infinity


def test_bad_input_is_one_line_naming_the_field():
    assets = programmed()
    cam = camera(0.0)
    t = assets.time_range[0]
    bad_depth = depth_with_sky()
    bad_depth[5, 5] = np.nan
    with pytest.raises(InputError, match="depth"):
        field_motion_vectors(assets, cam.intrinsics, cam.world_to_camera, bad_depth, t, cam.world_to_camera, t)
    with pytest.raises(InputError, match="earlier_world_to_camera"):
        field_motion_vectors(assets, cam.intrinsics, cam.world_to_camera, depth_with_sky(), t, np.eye(3), t)
    with pytest.raises(InputError, match="outside the trained range"):
        field_motion_vectors(assets, cam.intrinsics, cam.world_to_camera, depth_with_sky(), t,
                             cam.world_to_camera, assets.time_range[1] + 5.0)


@pytest.mark.skipif(not glfield.available(), reason="no EGL context with OpenGL 4.3 compute shaders")
@pytest.mark.parametrize("kind", ["programmed", "derf", "kplanes"])
def test_the_gl_pass_computes_what_the_numpy_oracle_computes(kind):
    """On llvmpipe the two agree to float32 rounding (measured: 2.4e-6 px on the programmed field)."""
    from engine.fields.gldynamic import GlDynamicRenderer

    assets = programmed(beta=0.3) if kind == "programmed" else load_assets(*dynamic_assets(_model(kind)), "dynamic")
    cam, prev = camera(0.0), camera(4.0)
    t0, t1 = assets.time_range
    t, t_prev = t0 + 0.75 * (t1 - t0), t0 + 0.25 * (t1 - t0)
    with GlDynamicRenderer(assets, 24, 24, filtering="exact") as renderer:
        out = renderer.render(cam.intrinsics, cam.world_to_camera, t, earlier_world_to_camera=prev.world_to_camera,
                              earlier_time=t_prev)
        plain = renderer.render(cam.intrinsics, cam.world_to_camera, t)
        with pytest.raises(InputError, match="earlier_time"):
            renderer.render(cam.intrinsics, cam.world_to_camera, t, earlier_world_to_camera=prev.world_to_camera)
    assert "motion_vectors" not in plain and np.array_equal(plain["depth"], out["depth"])
    want = field_motion_vectors(assets, cam.intrinsics, cam.world_to_camera, out["depth"], t, prev.world_to_camera,
                                t_prev)
    got = out["motion_vectors"]
    assert got.shape == (24, 24, 2) and got.dtype == np.float32
    assert np.array_equal(np.isnan(got), np.isnan(want)) and np.isfinite(want).mean() > 0.5
    np.testing.assert_allclose(got[np.isfinite(want)], want[np.isfinite(want)], atol=1e-3)
    if kind == "programmed":  # the field's points moved: not the camera's vectors alone
        camera_only = camera_motion_vectors(out["depth"], cam, prev)
        assert np.nanmax(np.abs(want - camera_only)) > 0.5


@pytest.mark.skipif(not glfield.available(), reason="no EGL context with OpenGL 4.3 compute shaders")
def test_the_gl_pass_drops_the_motion_that_turned_as_the_numpy_oracle_does():
    """``coherence`` on the GPU: the steady translation keeps its vectors, the zig-zag one that reversed gets the
    camera's (normalised times as in the numpy test: the interval before inside the trained range)."""
    from engine.fields.gldynamic import GlDynamicRenderer

    cam, prev = camera(0.0), camera(4.0)
    for assets, tau, tau_earlier in ((programmed(), 0.5, 0.0), (programmed(zigzag=True), 0.1, -0.2)):
        t0, t1 = assets.time_range
        t, t_prev = (t0 + (x + 1.0) / 2.0 * (t1 - t0) for x in (tau, tau_earlier))
        with GlDynamicRenderer(assets, 24, 24, filtering="exact") as renderer:
            out = renderer.render(cam.intrinsics, cam.world_to_camera, t, earlier_world_to_camera=prev.world_to_camera,
                                  earlier_time=t_prev, coherence=COHERENCE)
            with pytest.raises(InputError, match="coherence"):
                renderer.render(cam.intrinsics, cam.world_to_camera, t, earlier_world_to_camera=prev.world_to_camera,
                                earlier_time=t_prev, coherence=-1.0)
        want = field_motion_vectors(assets, cam.intrinsics, cam.world_to_camera, out["depth"], t, prev.world_to_camera,
                                    t_prev, coherence=COHERENCE)
        plain = field_motion_vectors(assets, cam.intrinsics, cam.world_to_camera, out["depth"], t,
                                     prev.world_to_camera, t_prev)
        got = out["motion_vectors"]
        assert np.array_equal(np.isnan(got), np.isnan(want)) and np.isfinite(want).mean() > 0.5
        np.testing.assert_allclose(got[np.isfinite(want)], want[np.isfinite(want)], atol=1e-3)
        camera_only = camera_motion_vectors(out["depth"], cam, prev)
        assert np.nanmax(np.abs(plain - camera_only)) > 0.5  # the field's points moved
        moved = np.nanmax(np.abs(want - camera_only)) > 0.5
        assert moved == (tau == 0.5)  # steady: kept; zig-zag: the camera's alone


@pytest.mark.skipif(not glfield.available(), reason="no EGL context with OpenGL 4.3 compute shaders")
def test_the_gl_pass_runs_the_newton_steps_of_the_numpy_oracle():
    """Where only Newton's steps find the earlier points (the steep field above), the GPU finds the same ones."""
    from engine.fields.gldynamic import GlDynamicRenderer

    assets = programmed(beta=1.5)
    cam, prev = camera(0.0), camera(4.0)
    t0, t1 = assets.time_range
    with GlDynamicRenderer(assets, 24, 24, filtering="exact") as renderer:
        out = renderer.render(cam.intrinsics, cam.world_to_camera, t0, earlier_world_to_camera=prev.world_to_camera,
                              earlier_time=t1)
    want = field_motion_vectors(assets, cam.intrinsics, cam.world_to_camera, out["depth"], t0, prev.world_to_camera,
                                t1)
    got = out["motion_vectors"]
    assert np.array_equal(np.isnan(got), np.isnan(want)) and np.isfinite(want).mean() > 0.5
    np.testing.assert_allclose(got[np.isfinite(want)], want[np.isfinite(want)], atol=1e-3)
    camera_only = camera_motion_vectors(out["depth"], cam, prev)
    assert np.nanmax(np.abs(want - camera_only)) > 0.5  # the field's points moved


@pytest.mark.skipif(not glfield.available(), reason="no EGL context with OpenGL 4.3 compute shaders")
def test_the_field_demo_feeds_a_dynamic_fields_own_vectors_to_mvec(tmp_path):
    """``interleave demo --field`` on a dynamic export: the textured box of ``tools.programmed_field`` moves ~2 px
    a frame; the field's vectors (to the previous rendered frame, from the field directly) put ``mvec`` well
    above ``reproject`` (measured at 160x120, 24 frames: +4.4 dB at k = 2, +3.1 dB at k = 4)."""
    from demos.upsample import run_field_demo
    from engine.io.rgbd import read_sequence

    export = write_export(tmp_path / "export")
    summary = run_field_demo(export, tmp_path / "demo", k=2, frames=10, width=64, height=48,
                             methods=("reproject", "mvec", "oracle"), progress=False, backend="cpu")
    assert set(summary) == {"reproject/k=2", "mvec/k=2", "oracle/k=2"}  # the field's own oracle
    assert summary["mvec/k=2"]["psnr_moving"] > summary["reproject/k=2"]["psnr_moving"] + 1.0
    assert summary["mvec/k=2"]["psnr"] > summary["reproject/k=2"]["psnr"] + 1.0
    # the oracle moves frame n by the field's own motion to the target's time: the bound mvec approaches
    assert summary["oracle/k=2"]["psnr"] > summary["reproject/k=2"]["psnr"] + 1.0
    assert summary["oracle/k=2"]["psnr"] - 2.0 < summary["mvec/k=2"]["psnr"] <= summary["oracle/k=2"]["psnr"] + 0.1
    assert "Dynamic field renderer" in (tmp_path / "demo" / "table.md").read_text()
    frame = read_sequence(tmp_path / "demo" / "field")[5]
    assert frame.motion_vectors is not None and frame.moving.mean() > 0.05


@pytest.mark.skipif(not glfield.available(), reason="no EGL context with OpenGL 4.3 compute shaders")
def test_play_on_a_dynamic_field_gives_mvec_the_fields_vectors(tmp_path):
    from demos.play import FieldSource, PlayConfig, iter_frames

    export = write_export(tmp_path / "export")
    config = PlayConfig(field=str(export), width=48, height=32, k=2, method="mvec", loop=8, backend="cpu")
    source = FieldSource(config)
    try:
        assert source.dynamic and source.times[0] == 0.0 and max(source.times) == 1.0 and len(source.times) == 14
        frame = source.frame(4, 2)
        assets = source.renderer.assets
        want = field_motion_vectors(assets, frame.camera.intrinsics, frame.camera.world_to_camera, frame.depth,
                                    source.times[4], source.cameras[2].world_to_camera, source.times[2],
                                    coherence=COHERENCE)
        assert np.array_equal(np.isnan(frame.motion_vectors), np.isnan(want))
        np.testing.assert_allclose(frame.motion_vectors[np.isfinite(want)], want[np.isfinite(want)], atol=1e-3)
        assert np.nanmax(np.abs(want - camera_motion_vectors(frame.depth, frame.camera, source.cameras[2]))) > 0.5
    finally:
        source.release()
    shown = list(iter_frames(config, 5))
    assert len(shown) == 5 and all(image.shape[:2] == (32, 48) for image in shown)


def test_the_object_flow_is_the_fields_translation_seen_by_the_same_camera():
    from engine.fields.dynamic import field_object_flow

    assets = programmed()
    cam = camera(10.0)
    depth = depth_with_sky()
    t0, t1 = assets.time_range
    t, target = t0 + 0.25 * (t1 - t0), t0 + 0.75 * (t1 - t0)
    flow = field_object_flow(assets, cam.intrinsics, cam.world_to_camera, depth, t, target)
    tau, tau_target = normalize_time(t, assets.time_range), normalize_time(target, assets.time_range)
    shift = flow_x(assets.max_flow, 0.0, tau) - flow_x(assets.max_flow, 0.0, tau_target)  # box half-size 1
    origin, dirs = camera_rays_np(cam.intrinsics, cam.world_to_camera, 24, 24)
    finite = np.isfinite(depth).reshape(-1)
    points = origin + np.where(finite, depth.reshape(-1), 0.0)[:, None] * dirs
    inside = finite & (np.abs(contract_np(assets.scene, points.astype(np.float32), 0.0)) <= 1.0).all(-1)
    moved = points + np.where(inside, shift, 0.0)[:, None] * np.array([1.0, 0.0, 0.0])
    q = moved @ cam.world_to_camera[:3, :3].T + cam.world_to_camera[:3, 3]
    uv = q[:, :2] / q[:, 2:] * cam.intrinsics[0, 0] + cam.intrinsics[:2, 2]
    pixels = np.stack(np.meshgrid(np.arange(24) + 0.5, np.arange(24) + 0.5), -1).reshape(-1, 2)
    want = np.concatenate([uv - pixels, (q[:, 2] - np.where(finite, depth.reshape(-1), 0.0))[:, None]], axis=1)
    want[~finite] = 0.0
    assert abs(shift) > 0.05 and inside.any() and (~inside & finite).any()
    np.testing.assert_allclose(flow.reshape(-1, 3), want, atol=2e-3)
