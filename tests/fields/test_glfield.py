"""GL field renderer (engine/fields/gl.py) against its oracle, engine.fields.render.render_field, and the torch renderer.

Tolerances (measured on these fields in brackets): with early termination and the colour skip off, GL and
numpy agree to float32 rounding: colour within 1e-4 [2e-6], opacity within 1e-4, the same pixels without a
surface, median planar depth within 1e-4 [< 1e-5], PSNR above 40 dB [~130 dB]. With the defaults
(transmittance_eps 1e-4, color_eps 1e-5) the colour stays within transmittance_eps + num_samples * color_eps
of it [1.1e-4]. uint8 planes: GL against numpy on the same uint8 planes above 60 dB [exact filtering ~130,
hardware ~70], against the float planes above 40 dB. On a GPU every colour tolerance grows by GPU_SLACK (below).
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from engine.core.colorspace import display_encode
from engine.core.errors import InputError
from engine.eval.metrics import psnr
from engine.fields import gl as glfield
from engine.fields.camera_path import field_camera_path, scale_intrinsics
from engine.fields.render import load_field, render_field
from tests.fields.test_field_export import bounded_run, ndc_run  # noqa: F401  (module fixtures: tiny trained fields)
from tests.fields.test_field_train import sphere_views

if not glfield.available():
    pytest.skip("no EGL context with OpenGL 4.3 compute shaders and fp64", allow_module_level=True)

pytestmark = pytest.mark.usefixtures("one_torch_thread")

H, W = 32, 48
EXACT = {"transmittance_eps": 0.0, "color_eps": 0.0}


def _hardware_renderer() -> bool:
    import moderngl

    from engine.geometry.backends.gl.context import is_software_renderer

    ctx = moderngl.create_standalone_context(backend="egl", require=glfield.REQUIRED_GL)
    try:
        return not is_software_renderer(str(ctx.info.get("GL_RENDERER", "")))
    finally:
        ctx.release()


#: Added to the colour tolerances against numpy on a GPU: GLSL's division and exp are not correctly rounded there
#: (2.5 ulp allowed), so a sample can land in the next occupancy cell, and hardware filtering weighs texels in
#: 8-bit steps. Measured on an H200 (2026-11-27): 5.5e-3 at most on these fields, PSNR above 77 dB.
GPU_SLACK = 1e-2 if _hardware_renderer() else 0.0


def _camera(which: str):
    return sphere_views([20] if which == "bounded_run" else [10]).cameras[0]


def _psnr(a: dict, b: dict) -> float:
    return psnr(display_encode(a["color"]), display_encode(b["color"]))


def _gl(out, cam, **kwargs) -> dict:
    with glfield.GlFieldRenderer(out, W, H, **kwargs) as renderer:
        return renderer.render(cam.intrinsics, cam.world_to_camera)


def assert_same_render(ref: dict, got: dict, color_tol: float) -> None:
    assert got["color"].shape == (H, W, 3) and got["depth"].shape == (H, W) and got["opacity"].shape == (H, W)
    assert all(got[k].dtype == np.float32 for k in ("color", "depth", "opacity"))
    assert not np.isnan(got["color"]).any() and not np.isnan(got["depth"]).any()
    assert np.abs(got["color"] - ref["color"]).max() <= color_tol + GPU_SLACK
    assert np.abs(got["opacity"] - ref["opacity"]).max() <= color_tol + GPU_SLACK
    finite = np.isfinite(ref["depth"])
    assert np.array_equal(np.isfinite(got["depth"]), finite) and finite.any() and not finite.all()
    assert np.median(np.abs(got["depth"][finite] - ref["depth"][finite])) < 1e-4
    assert _psnr(ref, got) > 40.0


@pytest.mark.parametrize("which", ["bounded_run", "ndc_run"])
@pytest.mark.parametrize("filtering", ["exact", "hardware"])
def test_gl_matches_the_numpy_reference(which, filtering, request):
    _, out, manifest = request.getfixturevalue(which)
    assert (manifest["occupancy"] is not None) == (which == "bounded_run")
    cam = _camera(which)
    ref = render_field(load_field(out), cam.intrinsics, cam.world_to_camera, H, W)
    assert_same_render(ref, _gl(out, cam, filtering=filtering, **EXACT), 1e-4)
    # defaults: early ray termination and the colour skip stay within their documented bound
    bound = glfield.TRANSMITTANCE_EPS + manifest["render"]["num_samples"] * glfield.COLOR_EPS
    assert_same_render(ref, _gl(out, cam, filtering=filtering), bound)


@pytest.mark.parametrize("which", ["bounded_run", "ndc_run"])
def test_gl_matches_the_torch_renderer(which, request):
    from models.fields.components.render import render_image
    from models.fields.train_static import load_model

    run, out, _ = request.getfixturevalue(which)
    model = load_model(run)
    cam = _camera(which)
    ref = render_image(model, cam.intrinsics, cam.world_to_camera, H, W, model.scene.near, model.scene.far)
    got = _gl(out, cam)
    # a sample within float rounding of an occupancy-cell boundary may be skipped by one and not the other
    # (see tests/fields/test_field_export.py), so a few pixels may differ slightly
    error = np.abs(got["color"] - ref["color"]).max(-1)
    assert np.mean(error < 1e-3) > 0.97 and _psnr(ref, got) > 40.0


def test_uint8_planes(bounded_run):
    _, out, manifest = bounded_run
    cam = _camera("bounded_run")
    float_ref = render_field(load_field(out), cam.intrinsics, cam.world_to_camera, H, W)
    quant_ref = render_field(load_field(out, quantized=True), cam.intrinsics, cam.world_to_camera, H, W)
    exact = _gl(out, cam, quantized=True, filtering="exact", **EXACT)
    assert_same_render(quant_ref, exact, 1e-4)
    hardware = _gl(out, cam, quantized=True, **EXACT)  # 8-bit texture filtering: llvmpipe rounds the result
    assert _psnr(quant_ref, hardware) > 60.0
    assert _psnr(float_ref, hardware) > 40.0 and manifest["quantization"]["psnr_uint8_vs_float"] > 40.0


def test_early_termination_and_colour_skip_are_bounded(bounded_run):
    _, out, manifest = bounded_run
    cam = _camera("bounded_run")
    full = _gl(out, cam, **EXACT)
    n = manifest["render"]["num_samples"]
    for eps in (0.05, 0.3):  # large thresholds make the effect visible; it never exceeds the bound
        stopped = _gl(out, cam, transmittance_eps=eps, color_eps=0.0)
        diff = np.abs(stopped["color"] - full["color"]).max()
        assert 0.0 < diff <= eps and np.abs(stopped["opacity"] - full["opacity"]).max() <= eps
        skipped = _gl(out, cam, transmittance_eps=0.0, color_eps=eps / n)
        assert np.abs(skipped["color"] - full["color"]).max() <= eps
        np.testing.assert_allclose(skipped["opacity"], full["opacity"], atol=1e-6)  # weights still count


@pytest.mark.parametrize("which", ["bounded_run", "ndc_run"])
def test_counted_evaluations_are_those_of_the_reference(which, request):
    """The profiling count (``count_evaluations``) is the reference's ``evaluated_samples``, and counting
    changes nothing in the frame."""
    _, out, _ = request.getfixturevalue(which)
    cam = _camera(which)
    assets = load_field(out)
    ref = render_field(assets, cam.intrinsics, cam.world_to_camera, H, W)
    counted = _gl(out, cam, count_evaluations=True)
    plain = _gl(out, cam)
    assert "evaluations" not in plain and counted["evaluations"].dtype == np.uint32
    for key in ("color", "depth", "opacity"):
        assert np.array_equal(counted[key], plain[key])
    same = counted["evaluations"].astype(np.int64) == ref["evaluations"]
    # on a GPU a sample within rounding of a cell boundary or of the termination threshold may count differently
    assert np.mean(same) >= (0.98 if GPU_SLACK else 1.0)
    assert 0 < ref["evaluations"].max() <= assets.manifest["render"]["num_samples"]
    assert (ref["evaluations"] == 0).any()  # rays missing the box (or leaving the NDC frustum) evaluate nothing
    exhaustive = _gl(out, cam, count_evaluations=True, transmittance_eps=0.0)["evaluations"]
    assert (exhaustive >= counted["evaluations"]).all()


@pytest.mark.parametrize("which", ["bounded_run", "ndc_run"])
@pytest.mark.parametrize("num_samples", [31, 64, 100, 150])
def test_sample_counts_across_the_marchs_chunks(which, num_samples, request):
    """The march visits samples in chunks of 64 with a two-word mask (samples 0-31 and 32-63 of a chunk): a count
    under one word, exactly one chunk, and counts that end inside a later chunk's first or second word render and
    count evaluations as the reference does (the trained fields use 48: one chunk, both words)."""
    _, out, _ = request.getfixturevalue(which)
    cam = _camera(which)
    assets = load_field(out)
    assets.manifest["render"]["num_samples"] = num_samples
    ref = render_field(assets, cam.intrinsics, cam.world_to_camera, H, W)
    with glfield.GlFieldRenderer(assets, W, H, filtering="exact", **EXACT) as renderer:
        assert_same_render(ref, renderer.render(cam.intrinsics, cam.world_to_camera), 1e-4)
    with glfield.GlFieldRenderer(assets, W, H, count_evaluations=True) as renderer:  # the reference's thresholds
        got = renderer.render(cam.intrinsics, cam.world_to_camera)
    same = got["evaluations"].astype(np.int64) == ref["evaluations"]
    assert np.mean(same) >= (0.98 if GPU_SLACK else 1.0) and ref["evaluations"].max() > min(num_samples, 64) // 2


@pytest.mark.parametrize("which", ["bounded_run", "ndc_run"])
def test_tiles_per_invocation_do_not_change_the_frame(which, request):
    """Several tiles per shader invocation (llvmpipe's default) shade every pixel exactly as one does, also when
    the tile rows do not divide by it (H = 32: 4 tile rows; 3 per invocation leaves 2 tiles past the edge)."""
    _, out, _ = request.getfixturevalue(which)
    cam = _camera(which)
    one = _gl(out, cam, tiles_per_invocation=1, count_evaluations=True)
    for tiles in (3, 8):
        many = _gl(out, cam, tiles_per_invocation=tiles, count_evaluations=True)
        for key in ("color", "depth", "opacity", "evaluations"):
            assert np.array_equal(many[key], one[key]), (tiles, key)
    with glfield.GlFieldRenderer(out, W, H) as renderer:  # the default follows the renderer
        assert renderer.tiles_per_invocation == (1 if GPU_SLACK else glfield.SOFTWARE_TILES)
    for bad in (0, 65, 2.5, True):
        with pytest.raises(InputError, match="tiles_per_invocation"):
            glfield.GlFieldRenderer(out, W, H, tiles_per_invocation=bad)


def test_renders_are_repeatable_and_the_renderer_reusable(bounded_run):
    _, out, _ = bounded_run
    views = sphere_views([20, 50])
    assets = load_field(out)
    with glfield.GlFieldRenderer(assets, W, H) as renderer:
        a = renderer.render(views.cameras[0].intrinsics, views.cameras[0].world_to_camera)
        b = renderer.render(views.cameras[1].intrinsics, views.cameras[1].world_to_camera)
        c = renderer.render(views.cameras[0].intrinsics, views.cameras[0].world_to_camera)
    assert np.array_equal(a["color"], c["color"]) and np.array_equal(a["depth"], c["depth"])
    assert not np.array_equal(a["color"], b["color"]) and a["seconds"] > 0
    renderer.release()  # a second release is harmless


def test_dispatch_seconds_times_frames_that_render_leaves_unchanged(bounded_run):
    """``dispatch_seconds``: one wall time per frame (dispatch to finish, no readback); the frames it draws are the
    renderer's own, so the next render is the same; bad counts and cameras raise InputError."""
    _, out, _ = bounded_run
    cam = _camera("bounded_run")
    with glfield.GlFieldRenderer(load_field(out), W, H) as renderer:
        before = renderer.render(cam.intrinsics, cam.world_to_camera)
        seconds = renderer.dispatch_seconds(cam.intrinsics, cam.world_to_camera, 3)
        after = renderer.render(cam.intrinsics, cam.world_to_camera)
        assert len(seconds) == 3 and all(isinstance(t, float) and t > 0 for t in seconds)
        assert np.array_equal(before["color"], after["color"])
        for bad in (0, 1.5, True):
            with pytest.raises(InputError, match="frames"):
                renderer.dispatch_seconds(cam.intrinsics, cam.world_to_camera, bad)
        with pytest.raises(InputError, match="intrinsics"):
            renderer.dispatch_seconds(np.eye(4), cam.world_to_camera)


def test_bad_inputs_raise_input_error(bounded_run, tmp_path):
    _, out, _ = bounded_run
    cam = _camera("bounded_run")
    assets = load_field(out)
    for size in ((0, 8), (8, -1), (1.5, 8), (True, 8)):
        with pytest.raises(InputError, match="size"):
            glfield.GlFieldRenderer(assets, *size)
    with pytest.raises(InputError, match="filtering"):
        glfield.GlFieldRenderer(assets, 8, 8, filtering="cubic")
    with pytest.raises(InputError, match="transmittance_eps"):
        glfield.GlFieldRenderer(assets, 8, 8, transmittance_eps=1.0)
    with pytest.raises(InputError, match="color_eps"):
        glfield.GlFieldRenderer(assets, 8, 8, color_eps=float("nan"))
    with pytest.raises(InputError, match="does not exist"):
        glfield.GlFieldRenderer(tmp_path, 8, 8)
    with glfield.GlFieldRenderer(assets, 8, 8) as renderer:
        squashed = cam.world_to_camera.copy()
        squashed[:3, :3] *= 1.5
        with pytest.raises(InputError, match="world_to_camera"):
            renderer.render(cam.intrinsics, squashed)
        with pytest.raises(InputError, match="intrinsics"):
            renderer.render(np.full((3, 3), np.nan), cam.world_to_camera)
        with pytest.raises(InputError, match="intrinsics"):
            renderer.render(np.eye(4), cam.world_to_camera)


def test_scale_intrinsics_keeps_the_horizontal_field_of_view_or_the_whole_view():
    k = np.array([[50.0, 0, 50], [0, 50, 50], [0, 0, 1]])
    out = scale_intrinsics(k, 100, 100, 960, 540)
    np.testing.assert_allclose(out, [[480, 0, 480], [0, 480, 270], [0, 0, 1]])
    out = scale_intrinsics(k, 100, 100, 960, 540, fit="contain")  # the whole square view fits
    np.testing.assert_allclose(out, [[270, 0, 480], [0, 270, 270], [0, 0, 1]])


def test_camera_path_orbits_at_the_training_radius(bounded_run):
    _, out, _ = bounded_run
    train = sphere_views([0, 40, 80])  # distance 3, elevation 25 degrees, looking at the origin
    cams, w, h = field_camera_path(load_field(out), (train.cameras, train.width, train.height), 12, 40, 30)
    assert (w, h) == (40, 30) and len(cams) == 12
    pos = np.stack([c.position for c in cams])
    np.testing.assert_allclose(np.linalg.norm(pos, axis=1), 3.0, rtol=1e-6)
    np.testing.assert_allclose(np.degrees(np.arcsin(pos[:, 2] / 3.0)), 25.0, atol=1e-6)
    np.testing.assert_allclose(pos[0], train.cameras[0].position, atol=1e-6)
    centre_ray = np.array([c.world_to_camera[2, :3] for c in cams])  # camera z axis in world
    np.testing.assert_allclose(np.einsum("ij,ij->i", centre_ray, -pos / 3.0), 1.0, atol=1e-6)


@pytest.mark.parametrize("which", ["bounded_run", "ndc_run"])
def test_field_demo_writes_the_scene_demo_outputs(which, request, tmp_path):
    from demos.upsample import run_field_demo

    run, out, _ = request.getfixturevalue(which)
    summary = run_field_demo(out, tmp_path, k=2, frames=6, width=32, height=24, methods=("repeat", "reproject",
                                                                                          "mvec", "oracle"),
                             progress=False)
    assert set(summary) == {"repeat/k=2", "reproject/k=2", "mvec/k=2"}  # oracle dropped: nothing moves
    # the field's motion vectors are the camera's alone: mvec is reprojection, score for score
    assert summary["mvec/k=2"]["psnr"] == summary["reproject/k=2"]["psnr"]
    for name in ("table.md", "results.json", "speed_vs_error.png", "side_by_side.mp4", "field/sequence.json"):
        assert (tmp_path / name).is_file()
    table = (tmp_path / "table.md").read_text()
    assert "Field renderer" in table
    assert summary["reproject/k=2"]["psnr"] > summary["repeat/k=2"]["psnr"]
    # a static field has no moving pixels: '-' in the table, null in the JSON, never nan
    assert "nan" not in table.lower()
    row = next(line for line in table.splitlines() if line.startswith("| **mean** | 2 | reproject |"))
    assert row.split(" | ")[7:10] == ["-", "-", "-"]  # PSNR moving, FLIP moving, EPE moving
    doc = json.loads((tmp_path / "results.json").read_text())
    assert doc["summary"]["reproject/k=2"]["psnr_moving"] is None


def test_field_demo_explains_a_missing_export(tmp_path, capsys):
    from engine.cli import main as cli_main

    assert cli_main(["demo", "--field", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert "interleave export field" in capsys.readouterr().err


def test_field_benchmark_scores_every_renderer_against_torch(bounded_run, tmp_path):
    from tools.bench_fields import bench_table, run_static_bench

    run, out, _ = bounded_run
    records = run_static_bench(out, [(24, 16)], run=run, repeat=1, skip=("onnx",))
    names = [r["renderer"] for r in records]
    assert names[0] == "torch" and "gl float" in names and "numpy" in names and "onnx" not in names
    assert all(r["reference"] == "torch" and r["size"] == "24x16" for r in records)
    assert min(r["psnr"] for r in records if r["renderer"] in ("gl float", "numpy")) > 60.0
    assert "| 24x16 | gl float |" in bench_table(records)
    gl = next(r for r in records if r["renderer"] == "gl float")  # its arithmetic: evaluations and GMAC/s
    assert 0 < gl["evaluations_per_pixel"] <= 64 and gl["macs_per_evaluation"] > 0
    assert gl["gmac_per_s"] == pytest.approx(gl["gmac_per_frame"] / (gl["ms"] / 1e3))
    from tools.bench_fields import DISPATCH_FRAMES  # each GL variant is also timed without its readback

    assert gl["dispatch_frames"] == DISPATCH_FRAMES and 0 < gl["dispatch_ms"] < 1e4
    assert all(np.isnan(r["dispatch_ms"]) and r["dispatch_frames"] == 0 for r in records
               if r["renderer"] in ("torch", "numpy"))
    assert f"| {gl['fps']:.2f} | {gl['dispatch_ms']:.2f} |" in bench_table(records)


def test_a_renderer_on_the_shared_context_hands_frames_to_the_warper_without_a_readback(bounded_run):
    """GlFieldRenderer(context=shared_context()): the same render as on a context of its own, and
    render_to_buffer + GlFrameWarper.from_rgbd warp exactly as the read-back frame uploaded again."""
    from engine.geometry.backends import gl as glb

    _, out, _ = bounded_run
    cam, other = sphere_views([20, 35]).cameras
    gl = glb.shared_context()
    warper = glb.GlFrameWarper(gl)
    with glfield.GlFieldRenderer(out, W, H) as own:
        ref = own.render(cam.intrinsics, cam.world_to_camera)
        with pytest.raises(InputError, match="context"):
            own.render_to_buffer(cam.intrinsics, cam.world_to_camera)
    with glfield.GlFieldRenderer(out, W, H, context=gl) as shared:
        got = shared.render(cam.intrinsics, cam.world_to_camera)
        image = warper.from_rgbd(shared.render_to_buffer(cam.intrinsics, cam.world_to_camera), (H, W))
        shared.render_to_buffer(other.intrinsics, other.world_to_camera)  # the image keeps its own copy
        with pytest.raises(InputError, match="rgbd"):
            warper.from_rgbd(shared.render_to_buffer(cam.intrinsics, cam.world_to_camera), (H + 1, W))
    for key in ("color", "depth", "opacity"):
        np.testing.assert_array_equal(got[key], ref[key])
    args = (cam.intrinsics, cam.world_to_camera, other.intrinsics, other.world_to_camera)
    color, holes = warper.warp_and_fill(image, *args)
    ref_color, ref_holes = warper.warp_and_fill(warper.upload(ref["color"], ref["depth"]), *args)
    np.testing.assert_array_equal(color, ref_color)
    np.testing.assert_array_equal(holes, ref_holes)
    assert not holes.all() and gl.ctx is not None  # the shared context outlives the renderer
    with pytest.raises(InputError, match="context"):
        glfield.GlFieldRenderer(out, W, H, context="not a context")


def test_empty_distance_is_the_chebyshev_distance_to_the_nearest_occupied_cell():
    """The grid the march skips by, against a brute-force minimum over the occupied cells (capped)."""
    rng = np.random.default_rng(5)
    for density in (0.002, 0.02, 0.3):
        occ = rng.random((9, 11, 7)) < density
        occ[rng.integers(9), rng.integers(11), rng.integers(7)] = True
        cells = np.stack(np.meshgrid(*[np.arange(n) for n in occ.shape], indexing="ij"), -1).reshape(-1, 3)
        occupied = cells[occ.reshape(-1)]
        brute = np.abs(cells[:, None, :] - occupied[None, :, :]).max(-1).min(1).reshape(occ.shape)
        assert np.array_equal(glfield.empty_distance(occ), brute.astype(np.uint8))
        assert np.array_equal(glfield.empty_distance(occ, cap=3), np.minimum(brute, 3).astype(np.uint8))
    assert (glfield.empty_distance(np.zeros((4, 4, 4), bool)) == 255).all()  # nothing occupied: skip at will
    with pytest.raises(InputError, match="occupancy"):
        glfield.empty_distance(np.zeros((4, 4), bool))


@pytest.mark.parametrize("sparse", [False, True])
def test_skipping_empty_runs_by_distance_changes_no_bit(bounded_run, ndc_run, sparse, monkeypatch):
    """A bounded field's march jumps over samples in cells at distance >= 3 from the occupancy instead of testing
    each: the frame and the evaluated samples are those of the march that tests every sample (the distances
    clamped to 1), on the trained grid and on a sparse random grid (many rays grazing occupied cells)."""
    import dataclasses

    _, out, _ = bounded_run
    cam = _camera("bounded_run")
    assets = load_field(out)
    assert glfield.skips_by_distance(assets) and not glfield.skips_by_distance(load_field(ndc_run[1]))
    if sparse:
        rng = np.random.default_rng(1)
        assets = dataclasses.replace(assets, occupancy=rng.random(assets.occupancy.shape) < 0.004)
    assert glfield.empty_distance(assets.occupancy).max() >= 3  # the test exercises jumps

    def render():
        with glfield.GlFieldRenderer(assets, W, H, count_evaluations=True) as renderer:
            return renderer.render(cam.intrinsics, cam.world_to_camera)

    skipping = render()
    exact = glfield.empty_distance
    monkeypatch.setattr(glfield, "empty_distance", lambda occ, cap=255: np.minimum(exact(occ, cap), 1).astype(np.uint8))
    stepping = render()
    for key in ("color", "depth", "opacity", "evaluations"):
        assert np.array_equal(skipping[key], stepping[key], equal_nan=True), key
    assert skipping["evaluations"].any()
