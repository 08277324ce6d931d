"""Disocclusion infilling: the U-Net, the vector copy (torch vs numpy), the engine loop, hard holes, training,
export parity and the decomp predictor with infilling."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from engine import geometry
from engine.core.errors import InputError
from engine.geometry.holefill import fill_holes
from engine.predict.decomp.infill import (DEFAULT_INFILL_MODEL, RECEPTIVE_MARGIN, InfillNetwork, apply_vectors,
                                          candidate_vectors, composite_holes, copy_along_vectors, downsample_holes,
                                          hole_boxes, hole_mpi, prior_vectors)
from export.infill import check_parity, example_inputs, export_infill
from models.infill.network import NUM_CANDIDATES, InfillConfig, InfillNet, PlaneConv3d
from models.infill.network import apply_vectors as torch_apply_vectors
from models.infill.network import choice_loss, infill
from models.infill.train import TrainInfillConfig, candidate_errors, evaluate_samples, make_samples, train
from tests.geometry.test_geometry import mpi_to_torch

TINY = InfillConfig(num_planes=4, channels=(4, 8))


def frame_with_holes(h=40, w=56, seed=0):
    """A near square over a far, partly sky background, with a disocclusion band right of the square."""
    rng = np.random.default_rng(seed)
    color = rng.random((h, w, 3)).astype(np.float32)
    depth = np.full((h, w), 10.0, np.float32)
    depth[: h // 5] = np.inf
    depth[h // 4: 3 * h // 4, w // 4: w // 2] = 2.0
    holes = np.zeros((h, w), bool)
    holes[h // 4: 3 * h // 4, w // 2: w // 2 + 6] = True
    return color, np.where(holes, np.float32(np.inf), depth), holes


@pytest.fixture(scope="module", params=["residual", "choice"])
def exported(tmp_path_factory, request):
    """A tiny network of each head with a random (non-zero) last layer, exported to ONNX (working width 32)."""
    torch.manual_seed(0)
    net = InfillNet(dataclasses.replace(TINY, head=request.param)).eval()
    torch.nn.init.normal_(net.head.weight, std=0.2)
    path = export_infill(net, tmp_path_factory.mktemp("infill") / "infill.onnx", working_width=32)
    return net, path


def test_plane_conv_is_conv3d():
    conv = PlaneConv3d(5, 7, 2)
    x = torch.randn(2, 5, 3, 19, 22)
    torch.testing.assert_close(conv(x), F.conv3d(x, conv.weight, conv.bias, (1, 2, 2), 1), atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("head", ["residual", "choice"])
def test_untrained_network_is_the_simple_fill(tmp_path, head):
    """The last layer starts at zero: vectors = prior (residual 0; equal logits pick the first candidate, the
    prior), and the engine loop reproduces engine.geometry.holefill."""
    net = InfillNet(dataclasses.replace(TINY, head=head)).eval()
    path = export_infill(net, tmp_path / "zero.onnx", working_width=1000)  # factor 1 on these frames
    color, depth, holes = frame_with_holes()
    planes = geometry.plane_depths(np.where(holes, 10.0, depth).astype(np.float32), 4)
    got, _ = InfillNetwork(path).fill(color, depth, holes, planes, iterations=3)
    want, _ = fill_holes(color, depth, holes)
    np.testing.assert_array_equal(got, want)


def test_numpy_copy_matches_torch_nearest():
    rng = np.random.default_rng(3)
    color, depth, holes = frame_with_holes(24, 30, seed=3)
    planes = geometry.plane_depths(np.where(holes, 10.0, depth).astype(np.float32), 4)
    mpi = hole_mpi(color, depth, holes, planes)
    # vectors with fractional parts away from .5 (rounding ties are a convention, not a property)
    vectors = (rng.integers(-12, 13, (2, 4, 24, 30)) + rng.uniform(-0.4, 0.4, (2, 4, 24, 30))).astype(np.float32)
    got, left = apply_vectors(mpi, holes, vectors)
    tm = mpi_to_torch(mpi)
    want, want_left = torch_apply_vectors(tm, torch.from_numpy(holes)[None], torch.from_numpy(vectors)[None], "nearest")
    np.testing.assert_array_equal(got.alpha, want.alpha[0, 0].numpy())
    np.testing.assert_allclose(got.color, want.color[0].numpy(), atol=1e-6)
    np.testing.assert_allclose(got.depth, want.depth[0, 0].numpy(), rtol=1e-6)
    np.testing.assert_array_equal(left, want_left[0].numpy())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sparse_copy_matches_the_mpi_reference(seed):
    """copy_along_vectors (the engine's fast path) = hole_mpi -> apply_vectors -> composite_holes, sky,
    vectors leaving the frame and vectors landing on holes or other planes included."""
    rng = np.random.default_rng(seed)
    h, w = 30, 44
    color, depth, holes = frame_with_holes(h, w, seed=seed)
    holes |= rng.random((h, w)) < 0.1
    depth = np.where(holes, np.float32(np.inf), depth)
    planes = geometry.plane_depths(np.where(holes, 10.0, depth).astype(np.float32), 4)
    vectors = (rng.integers(-20, 21, (2, 4, h, w)) + rng.uniform(-0.4, 0.4, (2, 4, h, w))).astype(np.float32)
    mpi, _ = apply_vectors(hole_mpi(color, depth, holes, planes), holes, vectors)
    want_color, want_depth, want_holes = composite_holes(mpi)
    rows, cols = np.nonzero(holes)
    got_color, got_depth, got_holes = copy_along_vectors(color, depth, holes, planes, rows, cols,
                                                         vectors[:, :, rows, cols])
    np.testing.assert_array_equal(got_holes, want_holes)
    filled = ~got_holes
    np.testing.assert_array_equal(got_color[filled], want_color[filled])
    np.testing.assert_array_equal(got_depth[filled], want_depth[filled])
    assert 0 < got_holes.sum() < holes.sum()  # the case exercises both outcomes


def test_hole_gate_keeps_the_whole_frame_vectors():
    """With the receptive margin as context the gated network gives the whole-frame result exactly; a
    smaller margin still fills every hole with copies. The committed network, a 960 x 540 frame."""
    rng = np.random.default_rng(7)
    h, w = 540, 960
    yy, xx = np.mgrid[:h, :w]
    color = np.stack([np.sin(xx / 37.0), np.cos(yy / 23.0), (xx + yy) / (h + w)], -1).astype(np.float32) ** 2
    depth = (5.0 + 20.0 * (xx / w)).astype(np.float32)
    depth[200:330, 300:420] = 1.5  # a near box with disocclusions on two sides
    holes = np.zeros((h, w), bool)
    holes[210:320, 420:436] = True
    holes[250:254, 436:500] = True
    holes &= rng.random((h, w)) < 0.95
    depth = np.where(holes, np.float32(np.inf), depth)
    planes = geometry.plane_depths(np.where(holes, 10.0, depth).astype(np.float32), 4)
    net = InfillNetwork(DEFAULT_INFILL_MODEL, threads=1)
    boxes = hole_boxes(downsample_holes(color, depth, holes, 4)[2], RECEPTIVE_MARGIN, net.stride)
    assert boxes and sum((b[1] - b[0]) * (b[3] - b[2]) for b in boxes) < 0.5 * 135 * 240  # a real gate
    whole = net.fill(color, depth, holes, planes, color, 3, margin=None)
    gated = net.fill(color, depth, holes, planes, color, 3, margin=RECEPTIVE_MARGIN)
    np.testing.assert_array_equal(gated[0], whole[0])
    np.testing.assert_array_equal(gated[1], whole[1])
    holes[:, :6] = True  # camera motion at the border: another box
    depth = np.where(holes, np.float32(np.inf), depth)
    small, _ = net.fill(color, depth, holes, planes, color, 3, margin=0)
    assert np.isfinite(small).all()
    np.testing.assert_array_equal(small[~holes], color[~holes])
    known = {tuple(c) for c in color[~holes].round(6).tolist()}
    assert all(tuple(c) in known for c in small[holes].round(6).tolist())
    with pytest.raises(InputError, match="margin"):
        net.fill(color, depth, holes, planes, color, 3, margin=-1)


def test_bilinear_copy_has_vector_gradients_and_never_darkens():
    color, depth, holes = frame_with_holes(16, 20)
    planes = geometry.plane_depths(np.where(holes, 10.0, depth).astype(np.float32), 4)
    mpi = hole_mpi(color, depth, holes, planes)
    tm = mpi_to_torch(mpi)
    vectors = torch.full((1, 2, 4, 16, 20), 0.3, requires_grad=True)
    out, _ = torch_apply_vectors(tm, torch.from_numpy(holes)[None], vectors)
    out.alpha.sum().backward()
    assert torch.isfinite(vectors.grad).all() and vectors.grad.abs().sum() > 0
    assert torch.isfinite(out.color).all() and float(out.color.detach().max()) <= float(color.max()) + 1e-6


def test_straight_through_copies_the_nearest_point_with_bilinear_gradients():
    color, depth, holes = frame_with_holes(16, 20)
    planes = geometry.plane_depths(np.where(holes, 10.0, depth).astype(np.float32), 4)
    mpi = hole_mpi(color, depth, holes, planes)
    tm = mpi_to_torch(mpi)
    vectors = torch.full((1, 2, 4, 16, 20), -3.2, requires_grad=True)
    out, _ = torch_apply_vectors(tm, torch.from_numpy(holes)[None], vectors, "straight_through")
    near, _ = torch_apply_vectors(tm, torch.from_numpy(holes)[None], vectors.detach(), "nearest")
    torch.testing.assert_close(out.color, near.color)
    out.color.sum().backward()
    assert vectors.grad.abs().sum() > 0


@pytest.mark.parametrize("case", ["border", "wide", "no_source_in_plane", "thin", "all_hole", "none"])
def test_hard_holes_fill_with_known_pixels_only(exported, case):
    net, path = exported
    h, w = 48, 64
    color, depth, holes = frame_with_holes(h, w, seed=5)
    holes[:] = False
    if case == "border":  # camera motion: a strip along the left edge and the top rows
        holes[:, :7] = True
        holes[:3] = True
    elif case == "wide":  # far wider than the U-Net's receptive field at this size
        holes[5:40, 4:60] = True
    elif case == "no_source_in_plane":  # every known pixel is on the near plane: far planes have nothing
        depth[:] = 2.0
        holes[10:30, 20:40] = True
    elif case == "thin":  # a one-pixel pole in front of a hole band
        depth[:, 30] = 1.0
        holes[10:30, 26:30] = True
        holes[10:30, 31:35] = True
    elif case == "all_hole":
        holes[:] = True
    depth = np.where(holes, np.float32(np.inf), depth)
    fallback = np.full((h, w, 3), 0.25, np.float32)
    planes = geometry.plane_depths(np.where(holes, 10.0, depth).astype(np.float32), 4) if not holes.all() else \
        np.array([1.0, 2.0, 4.0, 8.0], np.float32)
    got, got_depth = InfillNetwork(path).fill(color, depth, holes, planes, fallback, iterations=3)
    assert np.isfinite(got).all() and not np.isnan(got_depth).any()
    np.testing.assert_array_equal(got[~holes], color[~holes])  # known pixels untouched
    if case == "all_hole":
        np.testing.assert_array_equal(got, fallback)
        return
    known = {tuple(c) for c in color[~holes].round(6).tolist()}
    assert all(tuple(c) in known for c in got[holes].round(6).tolist())  # copies, nothing invented


def test_infill_network_input_errors(exported, tmp_path):
    net, path = exported
    color, depth, holes = frame_with_holes()
    with pytest.raises(InputError, match="plane depths"):
        InfillNetwork(path).fill(color, depth, holes, np.array([1.0, 2.0], np.float32))
    with pytest.raises(InputError, match="not found"):
        InfillNetwork(tmp_path / "missing.onnx")
    other = "vectors" if net.config.head == "choice" else "choices"  # the call of the other head
    mpi = hole_mpi(color, depth, holes, geometry.plane_depths(np.where(holes, 10.0, depth).astype(np.float32), 4))
    with pytest.raises(InputError, match="choice"):
        getattr(InfillNetwork(path), other)(mpi, holes, np.zeros((2, *holes.shape), np.float32))
    if net.config.head == "choice":
        with pytest.raises(InputError, match="residual"):
            infill(net, mpi_to_torch(mpi), torch.from_numpy(holes)[None], torch.zeros(1, 2, *holes.shape))


def test_onnx_matches_torch(exported):
    net, path = exported
    for h, w, seed in ((32, 48, 1), (48, 80, 2)):
        assert check_parity(path, net, example_inputs(net, h, w, batch=1, seed=seed)) < 1e-4


def test_downsample_holes_marks_any_hole_block():
    color, depth, holes = frame_with_holes(8, 8)
    holes[:] = False
    holes[0, 0] = True
    low_c, low_d, low_h = downsample_holes(color, np.where(holes, np.inf, depth), holes, 2)
    assert low_h[0, 0] and low_h.sum() == 1 and np.isinf(low_d[0, 0])
    np.testing.assert_allclose(low_c[1, 1], color[2:4, 2:4].reshape(-1, 3).mean(axis=0), rtol=1e-6)


def test_prior_points_at_known_pixels():
    color, depth, holes = frame_with_holes()
    prior = prior_vectors(depth, holes)
    r, c = np.nonzero(holes)
    sr, sc = r + prior[1, r, c].astype(int), c + prior[0, r, c].astype(int)
    assert not holes[sr, sc].any()
    assert (prior[:, ~holes] == 0).all()


def tiny_train_config(out: Path, **kwargs) -> TrainInfillConfig:
    base = dict(out_dir=str(out), data_dir=str(out.parent / "data"), steps=3, batch_size=2, crop=16, downsample=2,
                scene_seeds=(1,), val_seeds=(2,), scene_width=64, scene_height=48, scene_frames=5,
                samples_per_scene=3, max_step=2, crop_candidates=4, crops_per_sample=2, log_every=1, val_every=3,
                checkpoint_every=3, model=TINY)
    base.update(kwargs)
    return TrainInfillConfig(**base)


def test_train_and_resume(tmp_path):
    cfg = tiny_train_config(tmp_path / "run")
    ckpt = train(cfg, progress=False)
    lines = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in lines] == [1, 2, 3] and all(np.isfinite(r["loss"]) for r in lines)
    assert "val_loss" in lines[-1] and np.isfinite(lines[-1]["val_loss_prior_only"])
    state = torch.load(ckpt, weights_only=False)
    assert state["step"] == 3
    best = torch.load(tmp_path / "run" / "best.pt", weights_only=False)  # lowest held-out loss, step 0 included
    assert best["step"] in (0, 3)
    resumed = train(tiny_train_config(tmp_path / "run", steps=4), progress=False, resume=True)
    assert torch.load(resumed, weights_only=False)["step"] == 4
    samples = make_samples(cfg, (1,))
    assert samples and all(s["holes"].any() and not s["holes"].all() for s in samples)
    assert np.isfinite(evaluate_samples(None, samples))


def test_train_choice_head(tmp_path):
    """The choice head trains on the expected error of its candidates; its held-out metric is the error of
    the arg-max candidate, the prior's is candidate 0's."""
    cfg = tiny_train_config(tmp_path / "run", model=dataclasses.replace(TINY, head="choice"), steps=6, val_every=6)
    train(cfg, progress=False)
    lines = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert all(np.isfinite(r["loss"]) and r["loss"] >= 0 for r in lines) and "val_loss" in lines[-1]
    samples = make_samples(cfg, (2,))
    assert all(s["candidates"].shape == (2 * NUM_CANDIDATES,) + s["holes"].shape for s in samples)
    errors = np.stack([s["errors"] for s in samples])
    holes = np.stack([s["holes"] for s in samples])
    per_sample = [float(e[0][h].mean()) for e, h in zip(errors, holes)]
    assert evaluate_samples(None, samples) == pytest.approx(float(np.mean(per_sample)), rel=1e-5)


def test_candidates_point_at_the_nearest_known_pixels():
    h = np.zeros((5, 6), bool)
    h[1:3, 2:4] = True
    h[4] = True  # a row with no known pixel: left / right fall back to the prior
    depth = (np.arange(30, dtype=np.float32).reshape(5, 6) + 1.0)  # farther to the right and down
    cand = candidate_vectors(depth, h).reshape(NUM_CANDIDATES, 2, 5, 6)
    np.testing.assert_array_equal(cand[:, :, 1, 2], [[2, 0], [-1, 0], [2, 0], [0, -1], [0, 2]])
    np.testing.assert_array_equal(cand[:, :, 4, 0], [[0, -1], [0, -1], [0, -1], [0, -1], [0, -1]])
    np.testing.assert_array_equal(cand[0], prior_vectors(depth, h))
    assert not cand[:, :, ~h].any()
    rows, cols = np.nonzero(h)
    for k in range(NUM_CANDIDATES):  # every candidate lands on a known pixel
        assert not h[rows + cand[k, 1, rows, cols].astype(int), cols + cand[k, 0, rows, cols].astype(int)].any()


def test_choice_loss_is_the_expected_error_of_the_choice():
    errors = torch.tensor([[[[0.5]], [[0.1]], [[0.9]], [[0.3]], [[0.7]]]])  # (1, K, 1, 1)
    holes = torch.ones(1, 1, 1)
    sure = torch.full((1, NUM_CANDIDATES, 1, 1), -30.0)
    sure[0, 1] = 30.0
    assert float(choice_loss(sure, errors, holes)) == pytest.approx(0.1, abs=1e-6)
    logits = torch.zeros(1, NUM_CANDIDATES, 1, 1, requires_grad=True)
    assert float(choice_loss(logits, errors, holes).detach()) == pytest.approx(0.5, abs=1e-6)  # uniform: the mean
    choice_loss(logits, errors, holes).sum().backward()
    assert int(torch.argmin(logits.grad[0, :, 0, 0])) == 1  # descent raises the best candidate's score
    assert float(choice_loss(logits, errors, torch.zeros(1, 1, 1)).detach()) == 0.0  # no hole: nothing to pay
    ce = torch.zeros(1, NUM_CANDIDATES, 1, 1, requires_grad=True)
    choice_loss(ce, errors, holes, "weighted_ce").sum().backward()
    assert int(torch.argmin(ce.grad[0, :, 0, 0])) == 1  # cross-entropy towards the best candidate
    same = torch.full_like(errors, 0.4)  # every candidate as good: the choice does not matter, no loss
    assert float(choice_loss(ce, same, holes, "weighted_ce").detach()) == 0.0
    with pytest.raises(InputError, match="kind"):
        choice_loss(ce, errors, holes, "hinge")
    color = np.array([[[1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [0.2, 0.2, 0.2]]], np.float32)
    hole = np.array([[False, True, False]])
    cand = candidate_vectors(np.ones((1, 3), np.float32), hole)
    err = candidate_errors(color, hole, cand, np.full((1, 3, 3), 0.2, np.float32))
    assert err[2, 0, 1] == 0.0 and err[1, 0, 1] > 0.0 and not err[:, 0, [0, 2]].any()  # right copies the truth


def test_train_config_errors(tmp_path):
    with pytest.raises(InputError):
        tiny_train_config(tmp_path, crop=10)  # not a multiple of the U-Net stride (4)
    with pytest.raises(InputError):
        tiny_train_config(tmp_path, max_step=5)  # needs scene_frames > max_step
    with pytest.raises(InputError):
        train("not a config", progress=False)


def test_decomp_with_infilling_and_true_motion(exported):
    """decomp with the infilling network: finite, known pixels copied; motion=truth (the bound) beats the
    predicted motion on moving pixels; the simple fill stays available as an ablation."""
    from engine.eval.metrics import score_frame
    from engine.predict import DEFAULT_MODEL, DecompConfig, DecompPredictor, DecompTrueMotion, FlowNetwork, Target
    from tests.synthetic import two_layer_sequence

    _, path = exported
    frames, objects = two_layer_sequence(7, width=192, height=128, camera_speed=0.06, object_speed=0.12)
    flow_net, infill_net = FlowNetwork(DEFAULT_MODEL, threads=1), InfillNetwork(path, threads=1)
    truth = frames[5]
    target = Target(truth.camera, truth.time, truth.index)
    scores = {}
    for name, (kind, cfg) in {"infill": (DecompPredictor, DecompConfig()),
                              "simple": (DecompPredictor, DecompConfig(fill="simple")),
                              "truth": (DecompTrueMotion, DecompConfig())}.items():
        pred = kind(cfg, flow_net, objects, infill=infill_net if cfg.fill == "infill" else None)
        out = pred.predict([frames[2], frames[4]], target)
        assert np.isfinite(out.color).all() and out.holes.any()
        if cfg.fill == "infill":
            assert "infill_network" in out.stages_ms
        scores[name] = score_frame(truth.color, out.color, truth.moving)
    assert scores["truth"].psnr_moving > scores["infill"].psnr_moving
    # an infilling network on other planes than the flow network's (e.g. a Z = 2 flow variant of the sweep)
    two = export_infill(InfillNet(InfillConfig(num_planes=2, channels=(4, 8))).eval(), path.with_name("z2.onnx"),
                        working_width=32)
    pred = DecompPredictor(DecompConfig(fill="infill"), flow_net, objects, infill=InfillNetwork(two, threads=1))
    out = pred.predict([frames[2], frames[4]], target)
    assert np.isfinite(out.color).all() and "infill_network" in out.stages_ms
    with pytest.raises(InputError, match="motion=truth"):
        DecompTrueMotion(DecompConfig(), flow_net, (), infill=infill_net)
