"""ONNX export of the 3D flow network (export/flow.py) and its training loop (models/flow/train.py).

Tolerance of onnxruntime against torch: 1e-4 absolute on the flow (pixels / scene units); measured
~1e-6. The dynamo exporter's symbolic-shape tracing costs ~15 ms per graph node on the 2-core VM, so the
full network's export (even a tiny config, ~1000 nodes) takes about a minute and is marked ``slow``; the
fast test exports the building blocks (partial conv, masked correlation, backward warp, Eq. 6.6) with the
same dynamic shapes. Training tests use a tiny rendered data set shared by the module.
"""
from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from engine.core.errors import InputError
from engine.predict.base import true_object_flow
from engine.predict.decomp.network import FlowNetwork
from export.flow import INPUT_NAMES, FlowGraph, check_parity, example_inputs, export_flow, with_planes
from models.flow.network import (Flow3D, Flow3DConfig, PartialConv3d, backward_warp, flow_from_output,
                                 masked_correlation, set_direct_conv3d)
from models.flow.train import (TrainFlowConfig, config_from_dict, load_model, make_batch, open_sequences, prepare_data,
                               sample_items, supervised_loss, train, true_back_flow)
from models.geometry import Mpi

ROOT = Path(__file__).resolve().parents[2]
TOLERANCE = 1e-4
pytestmark = pytest.mark.usefixtures("one_torch_thread")
TINY_NET = Flow3DConfig(encoder_channels=(4, 4, 4), reduce_channels=4, decoder_channels=(4,), search_range=1)


class Blocks(nn.Module):
    """Partial conv (strided) -> masked correlation -> Eq. 6.6 -> backward warp: every op family of Flow3D."""

    def __init__(self) -> None:
        super().__init__()
        self.conv = PartialConv3d(4, 6, stride=(1, 2, 2))
        self.head = PartialConv3d(6 + 3 * 9 + 0, 5, (1, 1, 1))

    def forward(self, x1, a1, x2, a2, planes):
        h1, m1 = self.conv(x1, a1)
        h2, m2 = self.conv(x2, a2)
        cv, cv_mask = masked_correlation(h1, m1, h2, m2, 1, 1)
        out = self.head(torch.cat([cv, h1], 1), torch.cat([cv_mask, m1.expand(-1, 6, -1, -1, -1)], 1))[0]
        flow = flow_from_output(out[:, :2], out[:, 2:], planes)
        return backward_warp(torch.cat([h2, m2], 1), flow, planes)


@pytest.mark.parametrize("direct", [False, True], ids=["plane-stacked", "conv3d"])
def test_export_blocks_dynamic_shapes_parity(tmp_path, direct):
    """Both forms of the partial conv (``export_flow`` uses the one-Conv3d form) against torch."""
    import onnxruntime as ort

    torch.manual_seed(0)
    blocks = set_direct_conv3d(Blocks().eval(), direct)

    def inputs(h, w, seed):
        g = torch.Generator().manual_seed(seed)
        return (torch.randn(1, 4, 4, h, w, generator=g), (torch.rand(1, 1, 4, h, w, generator=g) > 0.4).float(),
                torch.randn(1, 4, 4, h, w, generator=g), (torch.rand(1, 1, 4, h, w, generator=g) > 0.4).float(),
                torch.tensor([[2.0, 3.0, 5.0, 9.0]]))

    rows, cols = torch.export.Dim("rows", min=2, max=512), torch.export.Dim("cols", min=2, max=512)
    image = {3: 2 * rows, 4: 2 * cols}
    path = tmp_path / "blocks.onnx"
    with torch.no_grad():
        program = torch.onnx.export(blocks, inputs(16, 24, 0), dynamo=True, opset_version=20, optimize=False,
                                    dynamic_shapes=(image, image, image, image, None))
    program.save(str(path))
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    names = [i.name for i in session.get_inputs()]
    for h, w in [(16, 24), (20, 12)]:
        args = inputs(h, w, h)
        with torch.no_grad():
            want = blocks(*args).numpy()
        got = session.run(None, {n: a.numpy() for n, a in zip(names, args)})[0]
        assert got.shape == want.shape == (1, 7, 4, h // 2, w // 2)
        assert np.max(np.abs(got - want)) < TOLERANCE


@pytest.mark.slow
@pytest.mark.parametrize("depth_flow", [True, False])
def test_export_network_parity_at_two_resolutions(tmp_path, depth_flow):
    import onnxruntime as ort

    torch.manual_seed(0)
    model = Flow3D(TINY_NET).eval()
    path = export_flow(model, tmp_path / "flow3d.onnx", depth_flow=depth_flow)
    assert path.exists() and FlowNetwork(path, threads=1).depth_flow == depth_flow
    assert not any(m.direct for m in model.modules() if isinstance(m, PartialConv3d))  # exported from a copy
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    for size, batch in [((64, 96), 1), ((96, 48), 2)]:
        inputs = example_inputs(model, *size, batch=batch, seed=size[0])
        err = check_parity(path, model, inputs)
        assert err < TOLERANCE, (size, err)
        got = session.run(None, {n: t.numpy() for n, t in zip(INPUT_NAMES, inputs)})[0]
        with torch.no_grad():
            full = FlowGraph(model)(*inputs).numpy()
        if not depth_flow:  # (du, dv) of the full graph, dz exactly 0
            assert np.max(np.abs(got[:, :2] - full[:, :2])) < TOLERANCE and not got[:, 2].any()
            assert np.abs(full[:, 2]).max() > 0


def test_export_rejects_sizes_off_the_stride(tmp_path):
    with pytest.raises(InputError):
        export_flow(Flow3D(TINY_NET), tmp_path / "x.onnx", example_size=(36, 64))  # stride 8
    assert len(INPUT_NAMES) == 7


# ----------------------------------------------------------------------------------------------------
# Training


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    """The tiny data set (2 scenes, 64 x 48, 5 frames), rendered once for the module."""
    out = tmp_path_factory.mktemp("flowdata")
    prepare_data(tiny_config(out, data_dir=str(out / "data")))
    return out / "data"


def tiny_config(out: Path, **kwargs) -> TrainFlowConfig:
    base = dict(out_dir=str(out), data_dir=str(out / "data"), steps=2, batch_size=2, crop=32, downsample=1,
                crop_candidates=2, crops_per_pair=1, scene_width=64, scene_height=48, scene_frames=5,
                scene_seeds=(1, 2), k_values=(1, 2), checkpoint_every=2, log_every=1, threads=1, model=TINY_NET)
    base.update(kwargs)
    return TrainFlowConfig(**base)


def run_dir(tmp_path: Path, data_dir: Path, name: str) -> Path:
    out = tmp_path / name
    out.mkdir()
    (out / "data").symlink_to(data_dir, target_is_directory=True)  # tiny_config's data_dir = out/data
    return out


def test_train_writes_config_checkpoint_metrics(tmp_path, data_dir):
    out = run_dir(tmp_path, data_dir, "run")
    config = tiny_config(out)
    ckpt = train(config, progress=False)
    assert ckpt == out / "checkpoint.pt" and ckpt.exists()
    saved = json.loads((out / "config.json").read_text())
    assert config_from_dict(saved) == config
    lines = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in lines] == [1, 2]
    assert all(np.isfinite(r["loss"]) for r in lines)
    logged = lines[0]["items"]
    assert [{k: v for k, v in item.items() if k != "picked"} for item in logged] == sample_items(config, 0)
    assert all(len(item["picked"]) == config.crops_per_pair and item["picked"][0] in item["crops"] for item in logged)
    model = load_model(ckpt)
    assert isinstance(model, Flow3D) and model.config == TINY_NET


def test_resume_matches_uninterrupted_run(tmp_path, data_dir):
    straight = train(tiny_config(run_dir(tmp_path, data_dir, "straight"), steps=4), progress=False)
    out = run_dir(tmp_path, data_dir, "resumed")
    train(tiny_config(out, steps=2), progress=False)
    resumed = train(tiny_config(out, steps=4), progress=False, resume=True)
    a = torch.load(straight, weights_only=False)
    b = torch.load(resumed, weights_only=False)
    assert a["step"] == b["step"] == 4
    for name, value in a["model"].items():
        torch.testing.assert_close(b["model"][name], value, atol=1e-6, rtol=1e-6)


def test_dataloader_workers_match_in_process_batches(tmp_path, data_dir):
    """Batches built by DataLoader workers (each with its own frame cache) train the same network."""
    inline = train(tiny_config(run_dir(tmp_path, data_dir, "inline"), steps=3), progress=False)
    out = run_dir(tmp_path, data_dir, "workers")
    workers = train(tiny_config(out, steps=3, workers=2), progress=False)
    a = torch.load(inline, weights_only=False)
    b = torch.load(workers, weights_only=False)
    for name, value in a["model"].items():
        torch.testing.assert_close(b["model"][name], value, atol=1e-6, rtol=1e-6)
    logged = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    reference = [json.loads(line) for line in (tmp_path / "inline" / "metrics.jsonl").read_text().splitlines()]
    assert [r["items"] for r in logged] == [r["items"] for r in reference]  # crops picked included


def test_train_config_errors(tmp_path):
    with pytest.raises(InputError):
        tiny_config(tmp_path, crop=100)  # larger than the 64 x 48 scenes
    with pytest.raises(InputError):
        tiny_config(tmp_path, k_values=(5,))  # needs scene_frames > k
    with pytest.raises(InputError):
        tiny_config(tmp_path, workers=-1)
    with pytest.raises(InputError):
        train("not a config", progress=False)


def test_two_process_gloo_matches_one_process(tmp_path, data_dir):
    single = train(tiny_config(run_dir(tmp_path, data_dir, "single")), progress=False)
    out = run_dir(tmp_path, data_dir, "ddp")
    net = TINY_NET
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           "-m", "models.flow.train", "--out-dir", str(out), "--data-dir", str(data_dir), "--steps", "2",
           "--batch-size", "2", "--crop", "32", "--downsample", "1", "--crop-candidates", "2", "--crops-per-pair", "1",
           "--scene-width", "64", "--scene-height", "48", "--scene-frames", "5", "--scene-seeds", "1,2",
           "--k-values", "1,2", "--checkpoint-every", "2", "--log-every", "1", "--threads", "1",
           "--model.encoder-channels", ",".join(map(str, net.encoder_channels)), "--model.reduce-channels",
           str(net.reduce_channels), "--model.decoder-channels", ",".join(map(str, net.decoder_channels)),
           "--model.search-range", str(net.search_range), "--no-progress"]
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    result = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    a = torch.load(single, weights_only=False)
    b = torch.load(out / "checkpoint.pt", weights_only=False)
    assert b["step"] == 2
    for name, value in a["model"].items():  # DDP averages the same per-item losses as one process
        torch.testing.assert_close(b["model"][name], value, atol=1e-5, rtol=1e-4)


def test_config_file_with_command_line_overrides(tmp_path):
    from models.flow.train import build_parser, config_from_args

    base = tiny_config(tmp_path, steps=5, lr=3e-4)
    path = tmp_path / "config.json"
    path.write_text(json.dumps(dataclasses.asdict(base)))
    parser = build_parser()
    argv = ["--config", str(path), "--steps", "7", "--model.search-range", "2"]
    config = config_from_args(parser.parse_args(argv))
    assert config.steps == 7 and config.model.search_range == 2  # given on the command line
    assert config.lr == 3e-4 and config.crop == base.crop and config.model.encoder_channels == TINY_NET.encoder_channels
    with pytest.raises(InputError, match="config file not found"):
        config_from_args(parser.parse_args(["--config", str(tmp_path / "nope.json")]))
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(InputError, match="TrainFlowConfig JSON"):
        config_from_args(parser.parse_args(["--config", str(tmp_path / "bad.json")]))


def test_with_planes_rebuilds_the_same_weights_for_another_plane_count():
    torch.manual_seed(0)
    model = Flow3D(TINY_NET).eval()
    for z in (2, 8):
        other = with_planes(model, z)
        assert other.config.num_planes == z and model.config.num_planes == TINY_NET.num_planes
        assert all(torch.equal(a, b) for a, b in zip(model.state_dict().values(), other.state_dict().values()))
        with torch.no_grad():
            flow = FlowGraph(other)(*example_inputs(other, 32, 48))
        assert flow.shape == (1, 3, z, 32, 48) and torch.isfinite(flow).all()
    with pytest.raises(InputError, match="only '3d' networks"):
        with_planes(Flow3D(Flow3DConfig(mode="2d", num_planes=1)), 4)
    with pytest.raises(InputError, match=">= 1"):
        with_planes(model, 0)


def test_supervised_target_is_the_true_motion_back_to_frame_n_minus_k(data_dir):
    config = tiny_config(data_dir.parent, supervised_weight=1.0)
    sequences = open_sequences(config)
    seq = sequences[1]
    objects = {o.id: o for o in seq.objects}
    assert any(o.moving for o in seq.objects)
    back = true_back_flow(seq, 3, 2, 2)
    full = true_object_flow(seq[3], objects, 1)[..., :2]
    np.testing.assert_allclose(back, full.reshape(24, 2, 32, 2, 2).mean(axis=(1, 3)) / 2, atol=1e-5)
    *_, target = make_batch(config, [{"scene": 1, "k": 2, "n": 3, "y": 4, "x": 8}], sequences)
    np.testing.assert_allclose(target[0].numpy(), true_back_flow(seq, 3, 2, 1)[4:36, 8:40], atol=1e-6)
    *_, none = make_batch(tiny_config(data_dir.parent), [{"scene": 1, "k": 2, "n": 3}], sequences)
    assert none is None  # unsupervised runs do not compute it


def test_supervised_loss_is_zero_for_the_true_flow_and_l1_otherwise():
    mpi = Mpi(torch.rand(2, 3, 2, 8, 8), torch.ones(2, 1, 2, 8, 8), torch.zeros(2, 1, 2, 8, 8), torch.ones(2, 2))
    mpi.alpha[:, :, 0] = 1.0  # every pixel on plane 0
    mpi.alpha[1, :, 0, :, 4:] = 0.0  # item 1 covers half its pixels
    target = torch.randn(2, 8, 8, 2)
    flow = torch.zeros(2, 3, 2, 8, 8)
    flow[:, :2, 0] = target.permute(0, 3, 1, 2)
    torch.testing.assert_close(supervised_loss(flow, mpi, target), torch.zeros(2))
    shifted = flow.clone()
    shifted[:, 0, 0] += 0.5
    torch.testing.assert_close(supervised_loss(shifted, mpi, target), torch.full((2,), 0.5))


def test_supervised_run_trains_and_starts_from_a_checkpoint(tmp_path, data_dir):
    first = train(tiny_config(run_dir(tmp_path, data_dir, "sup"), supervised_weight=1.0, unsupervised_weight=0.0),
                  progress=False)
    lines = [json.loads(line) for line in (tmp_path / "sup" / "metrics.jsonl").read_text().splitlines()]
    assert all(np.isfinite(r["supervised"]) and r["loss"] == pytest.approx(r["supervised"]) for r in lines)
    out = run_dir(tmp_path, data_dir, "tuned")
    tuned = train(tiny_config(out, steps=1, init_from=str(first), lr=1e-12), progress=False)
    a, b = (torch.load(p, weights_only=False)["model"] for p in (first, tuned))
    for name, value in a.items():  # a step at lr 1e-12 leaves the weights it started from
        torch.testing.assert_close(b[name], value, atol=1e-6, rtol=1e-5)
    other = dataclasses.replace(TINY_NET, search_range=TINY_NET.search_range + 1)
    with pytest.raises(InputError, match="init_from"):
        train(tiny_config(run_dir(tmp_path, data_dir, "bad"), init_from=str(first), model=other), progress=False)
    with pytest.raises(InputError):
        tiny_config(tmp_path, supervised_weight=0.0, unsupervised_weight=0.0)
    with pytest.raises(InputError):
        tiny_config(tmp_path, scene_preset="fastest")


def test_a_corr_start_is_the_engines_decomp_start_block_meaned(data_dir):
    """``initial_estimator="corr"``: the flow the network refines in training is the one ``decomp`` hands it by
    default (``whole_frame_initial_flow`` with the correlation network, full resolution, trust rules), block-meaned
    to the working grid and cropped as the MPIs are; ``dis`` keeps DIS on the composite."""
    from engine.geometry import downsample_flow
    from engine.predict.corrflow import CorrFlowNetwork
    from engine.predict.decomp.predictor import whole_frame_initial_flow

    net = dataclasses.replace(TINY_NET, initial_flow=True)
    config = tiny_config(data_dir.parent, model=net, downsample=2, crop=16, initial_estimator="corr")
    sequences = open_sequences(config)
    seq = sequences[1]
    item = {"scene": 1, "k": 2, "n": 3, "y": 4, "x": 6}
    cache: dict = {}
    init = make_batch(config, [dict(item)], sequences, cache)[3]
    full = whole_frame_initial_flow(seq[1], seq[3], "medium", None, CorrFlowNetwork(threads=1)).flow
    want = downsample_flow(np.ascontiguousarray(full), 2)[4:20, 6:22]
    np.testing.assert_allclose(init[0].permute(1, 2, 0).numpy(), want, atol=1e-6)
    again = make_batch(config, [dict(item)], sequences, cache)[3]  # the second time from the cache
    torch.testing.assert_close(again, init)
    dis = make_batch(dataclasses.replace(config, initial_estimator="dis"), [dict(item)], sequences)[3]
    assert dis.shape == init.shape
    with pytest.raises(InputError, match="initial_estimator"):
        tiny_config(data_dir.parent, initial_estimator="raft")
