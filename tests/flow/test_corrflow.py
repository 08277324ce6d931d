"""The correlation flow network (``models.flow.corrflow``): its lookup against direct dot products, its
reach, the training pairs and loss, and the ONNX export against torch."""
from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from engine.core.config import config_to_dict
from engine.core.errors import InputError
from engine.predict.corrflow import DEPTH_SPAN, depth_code, depth_reference, network_depth, working_size
from models.flow.corrflow import CorrFlow, CorrFlowConfig
from models.flow.corrflow_train import (MAX_TRUTH, PAIR_KEYS, TrainCorrFlowConfig, build_pairs, extra_pairs,
                                        load_start_weights, prepare_pairs, sequence_loss, train, valid_truth)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def tiny_sequence_dir(tmp_path_factory):
    from engine.scenegen import SceneConfig, generate_sequence

    return generate_sequence(SceneConfig(seed=7005, width=96, height=64, num_frames=4, supersample=1, fps=10.0,
                                         object_speed=2.0), tmp_path_factory.mktemp("corr") / "seq", progress=False)
SMALL = CorrFlowConfig(encoder_channels=(8, 8, 16), feature_channels=8, context_channels=8, hidden_channels=8,
                       iterations=2)


def test_lookup_level0_is_the_dot_product_at_the_offset():
    torch.manual_seed(0)
    model = CorrFlow(SMALL)
    fa, fb = torch.randn(1, 8, 6, 10), torch.randn(1, 8, 6, 10)
    pyramid = model.correlation_pyramid(fa, fb)
    ys, xs = torch.meshgrid(torch.arange(6.0), torch.arange(10.0), indexing="ij")
    shift = torch.tensor([2.0, -1.0])  # every cell looks 2 cells right and 1 up in b
    coords = torch.stack([xs + shift[0], ys + shift[1]])[None]
    taps = model.lookup(pyramid, coords)
    r = SMALL.radius
    side = 2 * r + 1
    assert taps.shape == (1, SMALL.levels * side * side, 6, 10)
    for y, x in [(3, 4), (1, 0), (5, 7)]:
        for dy, dx in [(0, 0), (1, -2), (-1, 3)]:
            by, bx = y - 1 + dy, x + 2 + dx
            channel = (dy + r) * side + (dx + r)
            inside = 0 <= by < 6 and 0 <= bx < 10
            expected = float((fa[0, :, y, x] * fb[0, :, by, bx]).sum() / 8 ** 0.5) if inside else 0.0
            assert float(taps[0, channel, y, x]) == pytest.approx(expected, abs=1e-5)


def test_coarsest_level_reaches_radius_times_64_pixels():
    model = CorrFlow(SMALL)
    fa, fb = torch.randn(1, 8, 16, 16), torch.randn(1, 8, 16, 16)
    pyramid = model.correlation_pyramid(fa, fb)
    assert [p.shape[-1] for p in pyramid] == [16, 8, 4, 2]
    assert [p.shape[-1] for p in model.correlation_pyramid(fa[..., :1, :5], fb[..., :1, :5])] == [5, 3, 2, 1]
    # a lookup centred on cell 0 at level 3 spans +-radius cells of 8 level-0 cells = radius * 64 pixels
    assert SMALL.radius * 2 ** (SMALL.levels - 1) * 8 == 192


def test_forward_shapes_and_flow_units():
    model = CorrFlow(SMALL).eval()
    a, b = torch.rand(2, 3, 64, 96), torch.rand(2, 3, 64, 96)
    with torch.no_grad():
        flows = model(a, b)
    assert len(flows) == SMALL.iterations and all(f.shape == (2, 2, 64, 96) for f in flows)
    with torch.no_grad():
        last = model(a, b, every_iteration=False)
    assert len(last) == 1 and torch.equal(last[0], flows[-1])  # what the exported graph computes


def test_working_size():
    assert working_size(960, 540, 512) == (512, 288)
    assert working_size(1920, 1080, 512) == (512, 288)
    assert working_size(4000, 3000, 512) == (512, 384)
    assert working_size(1, 1, 512) == (512, 512)
    assert working_size(300, 200, 512) == (512, 344)  # scaled up too; multiples of 8
    assert working_size(8, 1000, 512) == (8, 512)  # the longer side


def test_loss_ignores_invalid_truth():
    target = torch.zeros(1, 2, 4, 4)
    target[0, 0, 0, 0] = float("inf")
    target[0, 1, 1, 1] = 2 * MAX_TRUTH
    assert int(valid_truth(target).sum()) == 14
    flow = torch.ones(1, 2, 4, 4)
    assert float(sequence_loss([flow], target, 0.8)) == pytest.approx(1.0)
    moving = target.clone()
    moving[0, 0, 2:, :] = 4.0  # 8 moving pixels off by (3, 1), 6 valid static ones off by (1, 1)
    assert float(sequence_loss([flow], moving, 0.8)) == pytest.approx(((3 + 1) / 2 + 1) / 2)
    assert float(sequence_loss([flow, 0 * flow], target, 0.5)) == pytest.approx(0.5)


def test_pairs_and_a_training_run(tmp_path, tiny_sequence_dir):
    path = build_pairs(tiny_sequence_dir, tmp_path / "pairs", ks=(1, 2), net_width=64)
    data = np.load(path)
    n = len(data["k"])
    assert data["a"].shape[0] == data["b"].shape[0] == data["flow"].shape[0] == n > 0
    assert data["a"].dtype == np.uint8 and data["flow"].shape[-1] == 2
    assert sorted(set(data["k"].tolist())) == [1, 2]
    w, h = data["a"].shape[2], data["a"].shape[1]
    config = TrainCorrFlowConfig(pairs=str(tmp_path / "pairs"), out_dir=str(tmp_path / "run"), steps=3,
                                 batch_size=1, crop=(min(h, 32), min(w, 48)), threads=1, log_every=1,
                                 model=SMALL)
    checkpoint = train(config)
    state = torch.load(checkpoint, weights_only=False)
    assert state["step"] == 3
    assert (tmp_path / "run" / "metrics.jsonl").read_text().count("\n") == 3


def test_fine_tuning_with_extra_data(tmp_path, tiny_sequence_dir):
    common = dict(pairs=str(tmp_path / "pairs"), steps=2, batch_size=2, crop=(32, 48), threads=1, model=SMALL,
                  scenes=(), ks=(1,), net_width=64)
    build_pairs(tiny_sequence_dir, tmp_path / "pairs", ks=(1,), net_width=64)
    first = train(TrainCorrFlowConfig(out_dir=str(tmp_path / "a"), **common))
    extra = TrainCorrFlowConfig(out_dir=str(tmp_path / "b"), extra_data=str(tiny_sequence_dir.parent), extra_share=0.5,
                                init_from=str(first), lr=0.0, **common)
    prepare_pairs(extra, progress=False)
    # the extra pairs are cached per working width (64 here: pairs_w64; the default 512: pairs)
    assert extra_pairs(extra) == tiny_sequence_dir.parent / "pairs_w64"
    assert (extra_pairs(extra) / f"{tiny_sequence_dir.name}.npz").is_file()
    state = torch.load(train(extra), weights_only=False)
    assert state["step"] == 2 and state["config"]["init_from"] == str(first)
    start = torch.load(first, weights_only=False)["model"]
    assert all(torch.equal(start[k], v) for k, v in state["model"].items())  # lr 0: the weights it started from


def test_depth_code_is_scale_free_log_depth_with_sky_far():
    depth = np.array([[1.0, 2.0, np.inf], [0.5, 1e-6, 1e6]], np.float32)
    code = depth_code(depth, 1.0)
    assert code[0, 0] == pytest.approx(0.5)
    assert code[0, 1] == pytest.approx(0.5 + np.log(2.0) / (2 * DEPTH_SPAN))
    assert code[1, 0] == pytest.approx(0.5 - np.log(2.0) / (2 * DEPTH_SPAN))
    assert code[0, 2] == 1.0 and code[1, 1] == 0.0 and code[1, 2] == 1.0  # sky far, beyond the span clipped
    np.testing.assert_allclose(depth_code(7.0 * depth, 7.0), code, atol=1e-6)  # scale-free
    assert depth_reference(depth) == pytest.approx(1.0)
    assert depth_reference(np.full((4, 4), np.inf, np.float32)) == 1.0  # all sky
    small = network_depth(np.full((16, 24), 2.0, np.float32), 2.0, (8, 8))
    assert small.shape == (8, 8) and small.dtype == np.uint8 and (small == 128).all()


def test_rgbd_pairs_and_fine_tuning_from_an_rgb_checkpoint(tmp_path, tiny_sequence_dir):
    path = build_pairs(tiny_sequence_dir, tmp_path / "pairs", ks=(1,), net_width=64)
    data = np.load(path)
    assert set(PAIR_KEYS) <= set(data.files)
    assert data["da"].shape == data["a"].shape[:3] and data["da"].dtype == np.uint8
    # frame n's codes are against its own median depth: about half of its pixels code at or under 0.5
    assert 0.3 < float((data["da"] <= 128).mean()) < 0.8
    common = dict(pairs=str(tmp_path / "pairs"), steps=1, batch_size=1, crop=(32, 48), threads=1, scenes=(),
                  ks=(1,), net_width=64)
    rgb = train(TrainCorrFlowConfig(out_dir=str(tmp_path / "rgb"), model=SMALL, **common))
    rgbd_config = CorrFlowConfig(**{**config_to_dict(SMALL), "depth": True})
    rgbd = TrainCorrFlowConfig(out_dir=str(tmp_path / "rgbd"), model=rgbd_config, init_from=str(rgb), lr=0.0,
                               **common)
    rgbd_checkpoint = train(rgbd)
    state = torch.load(rgbd_checkpoint, weights_only=False)
    start = torch.load(rgb, weights_only=False)["model"]
    first = "encoder.trunk.0.weight"
    assert state["model"][first].shape[1] == 4
    assert torch.equal(state["model"][first][:, :3], start[first]) and not state["model"][first][:, 3].any()
    # started from the RGB network with a zero depth channel: the same flow whatever the depth says
    model = CorrFlow(rgbd_config).eval()
    model.load_state_dict(state["model"])
    rgb_model = CorrFlow(SMALL).eval()
    rgb_model.load_state_dict(start)
    a, b = torch.rand(1, 4, 32, 48), torch.rand(1, 4, 32, 48)
    with torch.no_grad():
        torch.testing.assert_close(model(a, b)[-1], rgb_model(a[:, :3], b[:, :3])[-1])
    with pytest.raises(InputError, match="first convolution"):
        load_start_weights(CorrFlow(SMALL), rgbd_checkpoint)


def test_old_pair_files_are_built_again(tmp_path, tiny_sequence_dir):
    out = tmp_path / "pairs"
    out.mkdir()
    stale = out / f"{tiny_sequence_dir.name}.npz"
    np.savez(stale, a=np.zeros((1, 8, 8, 3), np.uint8))  # a cache from before the depth codes
    build_pairs(tiny_sequence_dir, out, ks=(1,), net_width=64)
    assert set(PAIR_KEYS) <= set(np.load(stale).files)


def test_rgbd_network_exports_with_parity(tmp_path):
    pytest.importorskip("onnxruntime")
    from export.corrflow import check_parity, export_corrflow

    torch.manual_seed(3)
    model = CorrFlow(CorrFlowConfig(**{**config_to_dict(SMALL), "depth": True})).eval()
    path = export_corrflow(model, tmp_path / "rgbd.onnx", working_width=64, example_size=(32, 48))
    assert check_parity(path, model, size=(48, 64)) < 1e-3


@pytest.mark.parametrize("args, problem", [(["--crop", "224by320"], "expected HxW"),
                                           (["--crop", "0x320"], "multiples of 8"),
                                           (["--crop", "220x320"], "multiples of 8"),
                                           (["--net-width", "0"], "net_width must be >= 8"),
                                           (["--threads", "0"], "threads must be >= 1"),
                                           (["--scenes", "fast:5000"], "PRESET:FIRST:COUNT"),
                                           (["--ks", "1,two"], "comma-separated integers"),
                                           (["--batch-size", "0"], "batch_size must be >= 1"),
                                           (["--workers", "0"], "workers must be >= 1"),
                                           (["--channels", "16,32,64"], "six positive widths"),
                                           (["--device", "tpu"], "device must be one of")])
def test_bad_training_options_are_one_line_errors(tmp_path, capsys, args, problem):
    from models.flow.corrflow_train import main

    try:  # argparse's own errors exit, the config's return the status
        status = main(args + ["--pairs", str(tmp_path / "pairs"), "--out", str(tmp_path / "run")])
    except SystemExit as exc:
        status = exc.code
    assert status == 2
    err = capsys.readouterr().err.strip()  # argparse prints its usage before the error line
    assert problem in err.splitlines()[-1] and "Traceback" not in err
    assert not (tmp_path / "run").exists()


def test_a_crop_larger_than_the_pairs_names_the_pairs_folder(tmp_path, tiny_sequence_dir):
    build_pairs(tiny_sequence_dir, tmp_path / "pairs", ks=(1,), net_width=64)
    config = TrainCorrFlowConfig(pairs=str(tmp_path / "pairs"), out_dir=str(tmp_path / "run"), steps=1,
                                 net_width=64, crop=(64, 64), model=SMALL)
    with pytest.raises(InputError, match="smaller than the crop") as err:
        train(config)
    assert err.value.field == "crop"


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine where torch sees no GPU")
def test_training_on_cuda_without_a_gpu_is_a_one_line_error_before_rendering(tmp_path, capsys):
    from models.flow.corrflow_train import main

    status = main(["--device", "cuda", "--data", str(tmp_path / "data"), "--pairs", str(tmp_path / "pairs"),
                   "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err.strip()
    assert status == 2 and "sees no GPU" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "data").exists() and not (tmp_path / "pairs").exists()


def test_pairs_built_by_several_processes_are_those_of_one(tmp_path, tiny_sequence_dir):
    from models.flow.corrflow_train import build_all_pairs

    second = tmp_path / "scenes" / "second"
    shutil.copytree(tiny_sequence_dir, second)
    one = build_all_pairs([tiny_sequence_dir, second], tmp_path / "one", (1,), 64, workers=1)
    two = build_all_pairs([tiny_sequence_dir, second], tmp_path / "two", (1,), 64, workers=2)
    assert [p.name for p in one] == [p.name for p in two] == [f"{tiny_sequence_dir.name}.npz", "second.npz"]
    for a, b in zip(one, two):
        with np.load(a) as x, np.load(b) as y:
            assert all(np.array_equal(x[k], y[k]) for k in PAIR_KEYS)


def test_the_network_widths_option_builds_that_network(tmp_path, tiny_sequence_dir):
    from models.flow.corrflow_train import main

    build_pairs(tiny_sequence_dir, tmp_path / "pairs", ks=(1, 2, 4), net_width=64)
    status = main(["--pairs", str(tmp_path / "pairs"), "--out", str(tmp_path / "run"), "--scenes", "gentle:1:0",
                   "--ks", "1,2,4", "--net-width", "64", "--crop", "32x48", "--steps", "1", "--batch-size", "1",
                   "--threads", "1", "--device", "cpu", "--channels", "8,16,24,16,8,12", "--iterations", "2"])
    assert status == 0
    state = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)
    model = state["config"]["model"]
    assert list(model["encoder_channels"]) == [8, 16, 24] and model["feature_channels"] == 16
    assert model["hidden_channels"] == 12 and model["iterations"] == 2
    assert state["model"]["features.weight"].shape[:2] == (16, 24)
