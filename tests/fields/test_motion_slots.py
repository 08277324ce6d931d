"""Motion slots (``--field.motion.slots K``): the torch ``SlotMotion`` (models/fields/dynamic/model.py) against a
direct per-point formula, its numpy oracle (engine/fields/dynamic.py) against torch, the export round trip
(export/dynamic.py, models/fields/assets.py), the GL shader (engine/fields/gldynamic.py) against the numpy
oracle, the config, the ``slot_smooth`` term and the loader's checks.

Fixture: a tiny DeRF with 3 slots trained 6 steps on the moving sphere of tests/fields/test_dynamic_field.py (the
config, the loss term and the checkpoint), then given a motion that matters (keys ~ N(0, 0.3), logits x3:
|flow| up to ~0.6 contracted units, changing with time) and exported (one ONNX export, ~6 s).

Tolerances (measured in brackets): numpy against torch in float64 1e-12 [2.2e-16], in float32 1e-5 [1.8e-7];
GL with exact filtering and no early termination against numpy 1e-4 [1.0e-6], motion vectors 1e-3 px [7.5e-6 px].
"""
from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from engine.core.config import add_options, config_from_args
from engine.core.errors import InputError
from engine.fields.camera_path import scale_intrinsics
from engine.fields.dynamic import (MotionSlots, deform_np, field_motion_vectors, load_dynamic_field,
                                   render_dynamic_field, slot_motion_np)
from engine.fields.gl import COLOR_EPS, TRANSMITTANCE_EPS, available
from export.dynamic import export_dynamic
from models.fields.bake import bake_dynamic, bakes_dynamic, motion_keys
from models.fields.data.timed import split_by_camera
from models.fields.dynamic.model import MotionConfig, MotionField, SlotMotion, slot_motion
from models.fields.train_dynamic import DynamicTrainConfig, load_dynamic_model, train_dynamic
from models.fields.trainer import apply_loss_weights
from tests.fields.test_dynamic_field import TIMES, TINY, sphere_video, tiny_config
from tests.fields.test_dynrender import assert_query_matches_torch

pytestmark = pytest.mark.usefixtures("one_torch_thread")

H, W = 24, 32
SLOTS = dataclasses.replace(TINY, motion=dataclasses.replace(TINY.motion, slots=3, slot_resolution=8),
                            time_resolution=3)
gl_only = pytest.mark.skipif(not available(), reason="no EGL context with OpenGL 4.3 compute shaders and fp64")


@pytest.fixture(scope="module")
def slotted(tmp_path_factory):
    """(run folder, perturbed model, export folder, held-out camera scaled to W x H)."""
    root = tmp_path_factory.mktemp("slots")
    train, test = split_by_camera(sphere_video([0, 30, 15, 60], TIMES), ["cam0", "cam1", "cam3"], ["cam2"])
    run = train_dynamic(train, tiny_config(6, field=SLOTS), root / "run", progress=False)
    model = load_dynamic_model(run)
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        slots = model.field.motion_field.slot_motion
        slots.keys.copy_(torch.randn(slots.keys.shape, generator=g) * 0.3)
        slots.logits.mul_(3.0)
    export_dynamic(model, root / "export")
    cam = test.cameras[0]
    return run, model, root / "export", (scale_intrinsics(cam.intrinsics, 20, 20, W, H), cam.world_to_camera)


def _slow_motion(logits, bias, keys, c, tau) -> np.ndarray:
    """One point, written out: bilinear logits (align_corners, border), softmax, keys at tau, sum_k w_k (A c + T)."""
    z = np.array(bias, np.float64)
    for p, (a, b) in enumerate(((0, 1), (0, 2), (1, 2))):
        r = logits.shape[-1]
        x = min(max((c[a] + 1) / 2 * (r - 1), 0.0), r - 1)
        y = min(max((c[b] + 1) / 2 * (r - 1), 0.0), r - 1)
        x0, y0 = min(int(math.floor(x)), r - 2), min(int(math.floor(y)), r - 2)
        fx, fy = x - x0, y - y0
        for j in range(z.size):
            q = logits[p, j]
            z[j] += ((q[y0, x0] * (1 - fx) + q[y0, x0 + 1] * fx) * (1 - fy)
                     + (q[y0 + 1, x0] * (1 - fx) + q[y0 + 1, x0 + 1] * fx) * fy)
    w = np.exp(z - z.max())
    w /= w.sum()
    s = (min(max(tau, -1.0), 1.0) + 1) / 2 * (keys.shape[0] - 1)
    i = min(int(math.floor(s)), keys.shape[0] - 2)
    key = keys[i] * (1 - (s - i)) + keys[i + 1] * (s - i)
    return sum(w[k + 1] * (key[k, :9].reshape(3, 3) @ c + key[k, 9:]) for k in range(keys.shape[1]))


def test_slot_motion_starts_at_zero_and_matches_the_written_out_formula():
    torch.manual_seed(0)
    field = MotionField(MotionConfig(slots=4, slot_resolution=6), 5)
    assert field.encoding is None and field.flow_mlp is None  # the hex-planes and flow MLP are not built
    assert [tuple(p.shape) for p in field.spatial_planes()] == [(3, 5, 6, 6)] and field.temporal_planes() == []
    coords = torch.rand(200, 3) * 2.4 - 1.2
    taus = torch.rand(200) * 2 - 1
    flow = field(coords, taus)
    assert flow.shape == (200, 3) and torch.equal(flow, torch.zeros_like(flow))
    flow.square().sum().backward()
    keys = torch.randn(5, 4, 12, requires_grad=True)
    loss = field.config.max_flow * torch.tanh(slot_motion(field.slot_motion.logits, field.slot_motion.still_bias,
                                                          keys, coords, taus)).sum()
    loss.backward()
    assert keys.grad.abs().sum() > 0  # the keys learn from zero
    sm = SlotMotion(4, 5, 6, still_bias=1.5).double()
    with torch.no_grad():
        sm.keys.normal_(0.0, 0.5)
    c64, t64 = coords.double()[:40], torch.cat([torch.tensor([-1.0, 1.0, 0.0]), taus[3:40]]).double()
    got = sm(c64, t64).detach().numpy()
    args = (sm.logits.detach().numpy(), sm.still_bias.numpy(), sm.keys.detach().numpy())
    want = np.stack([_slow_motion(*args, c.numpy(), float(t)) for c, t in zip(c64, t64)])
    np.testing.assert_allclose(got, want, atol=1e-12)
    assert sm(c64.reshape(4, 10, 3), t64.reshape(4, 10)).shape == (4, 10, 3)  # any lead shape
    assert sm(c64[:0], t64[:0]).shape == (0, 3)  # an empty batch


def test_the_numpy_oracle_matches_torch_in_float64_and_float32():
    torch.manual_seed(1)
    sm = SlotMotion(5, 4, 7).double()
    with torch.no_grad():
        sm.keys.normal_(0.0, 0.5)
    g = torch.Generator().manual_seed(2)
    coords = torch.rand(3000, 3, generator=g, dtype=torch.float64) * 2.2 - 1.1
    taus = torch.rand(3000, generator=g, dtype=torch.float64) * 2 - 1
    slots = MotionSlots(sm.logits.detach().numpy(), sm.still_bias.numpy(), sm.keys.detach().numpy())
    got = slot_motion_np(slots, coords.numpy(), taus.numpy())
    assert got.dtype == np.float64
    np.testing.assert_allclose(got, sm(coords, taus).detach().numpy(), atol=1e-12)
    sm = sm.float()
    slots32 = MotionSlots(*(a.astype(np.float32) for a in slots))
    got32 = slot_motion_np(slots32, coords.float().numpy(), taus.float().numpy())
    assert got32.dtype == np.float32
    np.testing.assert_allclose(got32, sm(coords.float(), taus.float()).detach().numpy(), atol=1e-5)
    with pytest.raises(InputError, match="coords"):
        slot_motion_np(slots32, np.zeros((4, 2), np.float32), np.zeros(4, np.float32))


def test_training_writes_the_config_and_the_term_and_the_export_round_trips(slotted):
    run, model, out, _ = slotted
    config = json.loads((run / "config.json").read_text())
    assert config["field"]["motion"]["slots"] == 3 and config["field"]["motion"]["slot_resolution"] == 8
    logged = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert any("slot_smooth" in json.dumps(entry) for entry in logged)  # on by default with slots
    assets = load_dynamic_field(out)
    spec = assets.manifest["field"]["motion"]
    assert spec["model"] == "slots" and spec["slots"] == 3 and spec["resolution"] == 8
    assert "flow" not in assets.mlps and "motion_spatial" not in assets.planes
    slots = model.field.motion_field.slot_motion
    assert assets.slots.logits.shape == (3, 4, 8, 8) and assets.slots.keys.shape == (model.time_resolution, 3, 12)
    np.testing.assert_array_equal(assets.slots.keys, slots.keys.detach().numpy())
    np.testing.assert_array_equal(assets.slots.still_bias, [2.0, 0.0, 0.0, 0.0])
    parity = assets.manifest["parity"]["random_points"]
    assert parity["density"] < 1e-4 and parity["color"] < 1e-4  # the ONNX graph (slots inside) against torch
    coords, taus, want, _, _ = assert_query_matches_torch(model, assets)
    canonical, flow = deform_np(assets, coords.numpy(), taus.numpy())
    np.testing.assert_allclose(canonical, want.canonical.numpy(), atol=1e-5)
    assert np.linalg.norm(flow, axis=-1).max() > 0.2  # the motion is exercised
    with torch.no_grad():  # the bake samples the same motion field
        keys = motion_keys(model, 3)
        axis = torch.linspace(-1.0, 1.0, 3)
        grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
        first = model.field.motion_field(grid, torch.full((27,), -1.0)).reshape(3, 3, 3, 3).numpy()
    np.testing.assert_allclose(keys[0].astype(np.float32), first, atol=2e-3)  # float16 keys


def test_numpy_and_onnx_renders_agree(slotted):
    _, _, out, camera = slotted
    assets = load_dynamic_field(out)
    t0, t1 = assets.time_range
    a = render_dynamic_field(assets, *camera, H, W, t0 + 0.3 * (t1 - t0))
    b = render_dynamic_field(assets, *camera, H, W, t0 + 0.3 * (t1 - t0), query="onnx")
    assert np.abs(a["color"] - b["color"]).max() < 1e-4 and np.abs(a["opacity"] - b["opacity"]).max() < 1e-4
    assert np.abs(a["color"] - render_dynamic_field(assets, *camera, H, W, t1)["color"]).max() > 1e-4


@gl_only
def test_gl_renders_and_moves_what_the_numpy_oracle_does(slotted):
    from engine.fields.gldynamic import GlDynamicRenderer
    from tests.fields.test_glfield import GPU_SLACK

    _, _, out, camera = slotted
    assets = load_dynamic_field(out)
    t0, t1 = assets.time_range
    t, t_prev = t0 + 0.7 * (t1 - t0), t0 + 0.3 * (t1 - t0)
    bound = TRANSMITTANCE_EPS + assets.manifest["render"]["num_samples"] * COLOR_EPS
    ref = render_dynamic_field(assets, *camera, H, W, t)
    with GlDynamicRenderer(assets, W, H, filtering="exact", transmittance_eps=0.0, color_eps=0.0) as exact, \
            GlDynamicRenderer(assets, W, H) as fast:
        got = exact.render(*camera, t, earlier_world_to_camera=camera[1], earlier_time=t_prev)
        default = fast.render(*camera, t)
    for render, tol in ((got, 1e-4), (default, bound)):  # + GPU_SLACK on a GPU (tests/fields/test_glfield.py)
        assert np.abs(render["color"] - ref["color"]).max() <= tol + GPU_SLACK
        assert np.abs(render["opacity"] - ref["opacity"]).max() <= tol + GPU_SLACK
        assert np.array_equal(np.isfinite(render["depth"]), np.isfinite(ref["depth"]))
    want = field_motion_vectors(assets, *camera, got["depth"], t, camera[1], t_prev)
    vectors = got["motion_vectors"]
    finite = np.isfinite(want)
    assert np.array_equal(np.isnan(vectors), np.isnan(want)) and finite.mean() > 0.3
    np.testing.assert_allclose(vectors[finite], want[finite], atol=1e-3)
    assert np.abs(want[finite]).max() > 0.5  # the points moved (a still camera: the field's motion alone)


def test_a_slot_field_of_tri_planes_trains_and_bakes(tmp_path):
    """No time planes at all (tri-plane canonical field, slots): the ``temporal`` terms see an empty group; the
    deferred field bakes, its flow sampled from the slots."""
    config = dataclasses.replace(SLOTS, canonical_time=False,
                                 canonical=dataclasses.replace(SLOTS.canonical, shading="deferred"))
    train, _ = split_by_camera(sphere_video([0, 30, 15], TIMES, size=12), ["cam0", "cam1", "cam2"], [])
    model = load_dynamic_model(train_dynamic(train, tiny_config(3, field=config), tmp_path / "run", progress=False))
    assert model.field.plane_groups()["temporal"] == [] and bakes_dynamic(model)
    arrays, manifest = bake_dynamic(model, 16, 5)
    assert arrays["motion"].shape == (3, 5, 5, 5, 3) and manifest["time"]["keys"] == 3


def test_the_config_the_command_line_and_the_smoothness_term():
    for change, name in (({"slots": -1}, "field.motion.slots"), ({"slots": 1.5}, "field.motion.slots"),
                         ({"slot_resolution": 1}, "field.motion.slot_resolution"),
                         ({"slot_still_bias": float("nan")}, "field.motion.slot_still_bias")):
        with pytest.raises(InputError, match=name):
            MotionConfig(**change).validate()
    import argparse

    parser = argparse.ArgumentParser()
    add_options(parser, DynamicTrainConfig, skip=("priors_choice",))
    args = parser.parse_args(["--field.motion.slots", "8", "--field.motion.slot-resolution", "16"])
    config = config_from_args(DynamicTrainConfig, args, DynamicTrainConfig())
    assert config.field.motion.slots == 8 and config.field.motion.slot_resolution == 16
    terms = {t.name: t for t in config.loss_terms()}
    assert terms["slot_smooth"].weight == 1e-3 and terms["slot_smooth"].enabled
    assert "slot_smooth" not in {t.name for t in DynamicTrainConfig().loss_terms()}  # default: no slots, no term
    off = {t.name: t for t in apply_loss_weights(config, ["slot_smooth=0"]).loss_terms()}
    assert off["slot_smooth"].weight == 0 and not off["slot_smooth"].enabled
    kplanes = dataclasses.replace(config, field=dataclasses.replace(config.field, kind="kplanes"))
    assert "slot_smooth" not in {t.name for t in kplanes.loss_terms()}


def test_bad_slot_assets_are_refused_naming_the_file(slotted, tmp_path):
    _, _, out, _ = slotted
    manifest = json.loads((out / "dynamic.json").read_text())
    with np.load(out / "dynamic.npz") as data:
        arrays = {k: data[k] for k in data.files}
    arrays["motion_slot_keys"] = arrays["motion_slot_keys"][:, :2]
    np.savez(tmp_path / "dynamic.npz", **arrays)
    (tmp_path / "dynamic.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="dynamic.npz: motion slots disagree"):
        load_dynamic_field(tmp_path)
    manifest["field"]["motion"]["model"] = "splines"
    (tmp_path / "dynamic.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="field.motion.model"):
        load_dynamic_field(tmp_path)


def test_the_motion_truth_tool_reads_a_slot_export_without_a_flow_mlp(slotted):
    """``tools.field_motion_truth.flow_units`` counts flow-MLP units: a slot export has none, (0, 0)."""
    from tools.field_motion_truth import flow_units

    assert flow_units(load_dynamic_field(slotted[2])) == (0, 0)


@pytest.mark.parametrize("dtype, atol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_mixing_by_distinct_time_matches_the_hat_mixing(monkeypatch, dtype, atol):
    """A batch with few distinct times (training: one per frame) mixes the keys per time; the general hat mixing
    is its oracle, for the motion and for the gradients of the logits and the keys (both forms hit)."""
    import models.fields.dynamic.model as dm
    g = torch.Generator().manual_seed(5)
    logits = (torch.randn(3, 6, 8, 8, generator=g, dtype=dtype) * 2).requires_grad_()
    keys = (torch.randn(7, 5, 12, generator=g, dtype=dtype) * 0.4).requires_grad_()
    bias = torch.tensor([1.5, 0, 0, 0, 0, 0], dtype=dtype)
    coords = torch.rand(40, 25, 3, generator=g, dtype=dtype) * 2.4 - 1.2
    frames = torch.tensor([-1.3, -1.0, -0.2, 0.0, 1 / 3, 0.9, 1.0, 1.4], dtype=dtype)  # clamped ends, key times
    times = frames[torch.randint(0, 8, (40, 1), generator=g)].expand(40, 25)

    def motion_and_grads(limit):
        monkeypatch.setattr(dm, "SLOT_SEGMENT_TIMES", limit)
        logits.grad = keys.grad = None
        out = slot_motion(logits, bias, keys, coords, times)
        (out * torch.linspace(-1, 1, out.numel(), dtype=dtype).reshape(out.shape)).sum().backward()
        return out.detach(), logits.grad.clone(), keys.grad.clone()

    calls = []
    for name in ("_slot_mix_by_time", "_slot_mix_hat"):
        real = getattr(dm, name)
        monkeypatch.setattr(dm, name, lambda *a, _real=real, _name=name: calls.append(_name) or _real(*a))
    by_time = motion_and_grads(64)
    hat = motion_and_grads(5)  # 6 distinct times once clamped, > 5: falls back to the hat weights
    assert calls == ["_slot_mix_by_time", "_slot_mix_by_time", "_slot_mix_hat"]
    assert by_time[0].shape == (40, 25, 3) and by_time[0].abs().max() > 0.3
    for a, b in zip(by_time, hat):
        torch.testing.assert_close(a, b, atol=atol, rtol=atol)
    torch.testing.assert_close(slot_motion(logits, bias, keys, coords[:1, :1], times[:1, :1]),
                               slot_motion(logits, bias, keys, coords, times)[:1, :1], atol=atol, rtol=0)  # one point
