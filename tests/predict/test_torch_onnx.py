"""The torch runner of the exported networks (engine/predict/torch_onnx.py) against onnxruntime, its oracle."""
import json

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper

from engine.core.errors import InputError
from engine.predict.onnx import network_runtime, open_network
from engine.predict.torch_onnx import _HOST_INPUTS, SUPPORTED_OPS, TorchOnnxSession
from engine.weights import CORRFLOW
from tools.bench_net_runner import graph_feeds as _feeds

WEIGHTS = CORRFLOW.parent


@pytest.mark.parametrize("name, rows, cols", [("corrflow.onnx", 4, 6), ("flow2d.onnx", 2, 3), ("flow3d.onnx", 2, 3),
                                              ("infill.onnx", 3, 4)])
def test_every_shipped_network_runs_in_torch_as_in_onnxruntime(name, rows, cols):
    path = WEIGHTS / name
    session = TorchOnnxSession(path)
    oracle = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    assert session.get_modelmeta().custom_metadata_map == oracle.get_modelmeta().custom_metadata_map
    for seed in (0, 1):  # the second run reuses the first one's plan (the values that do not depend on the data)
        feeds = _feeds(path, rows, cols, seed)
        want, got = oracle.run(None, feeds), session.run(None, feeds)
        assert len(got) == len(want)
        for a, b in zip(want, got):
            assert a.shape == b.shape and a.dtype == b.dtype
            np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-4 * max(1.0, float(np.abs(a).max())))
    assert len(session._plans) == 1


def test_the_plan_keeps_what_does_not_depend_on_the_data_and_follows_a_new_size(monkeypatch):
    path = WEIGHTS / "infill.onnx"
    session = TorchOnnxSession(path)
    oracle = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    for rows, cols in ((3, 4), (2, 5)):
        feeds = _feeds(path, rows, cols)
        np.testing.assert_allclose(session.run(None, feeds)[0], oracle.run(None, feeds)[0], atol=1e-5)
    first, _ = session._plans.values()
    static, dynamic = first.static, first.dynamic
    assert 0 < len(dynamic) < len(session._nodes) and not any(node.op == "Shape" for node in dynamic)
    assert len(session._plans) == 2
    monkeypatch.setattr("engine.predict.torch_onnx.MAX_PLANS", 2)
    session.run(None, _feeds(path, 1, 2))  # a third size: the least recently used goes
    assert len(session._plans) == 2 and (first.static is not next(iter(session._plans.values())).static)
    # numbers the data does not change (slice bounds, shapes, pads) are read from host copies: no device sync
    host = [node.inputs[i] for node in dynamic for i in _HOST_INPUTS.get(node.op, ()) if i < len(node.inputs)
            and node.inputs[i] and node.inputs[i] in static]
    assert host and all(name.endswith("@host") and static[name].device.type == "cpu" for name in host)


@pytest.mark.parametrize("capture", ["same", "wrong", "fails"])
def test_a_captured_replay_is_kept_only_where_it_gives_the_eager_outputs(capture, monkeypatch):
    """On a GPU each signature is captured as a CUDA graph; the capture is checked against the eager run before it
    is used. Here the capture is stood in for on the CPU: a replay that agrees is used, one that disagrees or
    fails to capture leaves the session running eagerly, with the same outputs."""
    path = WEIGHTS / "infill.onnx"
    session = TorchOnnxSession(path)
    calls = []

    def fake_capture(plan, tensors):
        if capture == "fails":
            raise RuntimeError("operation not permitted when stream is capturing")

        def replay(feeds):
            calls.append(1)
            out = session._eager(plan, feeds)
            return out if capture == "same" else [o + 1 for o in out]
        return replay
    monkeypatch.setattr(session, "_capture", fake_capture)
    session.graphs = True
    feeds = _feeds(path, 3, 4)
    want = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, feeds)[0]
    for _ in range(3):
        np.testing.assert_allclose(session.run(None, feeds)[0], want, atol=1e-5)
    (plan,) = session._plans.values()
    assert (plan.replay is not None) == (capture == "same")
    # captured at the second run (a size seen once is not), which returns the eager outputs it checked the replay
    # against; the third run replays
    assert len(calls) == {"same": 2, "wrong": 1, "fails": 0}[capture]


def _tiny_graph(path, op: str = "Relu", domain: str = ""):
    node = helper.make_node(op, ["x"], ["y"], domain=domain)
    graph = helper.make_graph([node], "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [2])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [2])])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 20)])
    helper.set_model_props(model, {"interleave.test": json.dumps({"ok": 1})})
    onnx.save(model, str(path))


def test_an_operator_it_does_not_implement_is_refused_when_the_graph_is_opened(tmp_path):
    assert "Relu" in SUPPORTED_OPS and "Erf" not in SUPPORTED_OPS
    _tiny_graph(tmp_path / "ok.onnx")
    out = TorchOnnxSession(tmp_path / "ok.onnx").run(None, {"x": np.array([-1, 2], np.float32)})[0]
    np.testing.assert_array_equal(out, [0, 2])
    _tiny_graph(tmp_path / "erf.onnx", "Erf")
    with pytest.raises(InputError) as err:
        TorchOnnxSession(tmp_path / "erf.onnx")
    assert "Erf" in str(err.value) and err.value.file is not None
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    with pytest.raises(InputError) as err:
        TorchOnnxSession(tmp_path / "junk.onnx")
    assert "junk.onnx" in str(err.value)


def test_networks_run_in_torch_where_onnxruntime_has_no_cuda_but_torch_has():
    cpu, cuda = ["CPUExecutionProvider"], ["CUDAExecutionProvider", "CPUExecutionProvider"]
    assert network_runtime(cpu, "auto", torch_gpu=True) == ("torch", "cuda")
    assert network_runtime(cpu, "auto", torch_gpu=False) == ("onnxruntime", cpu)
    assert network_runtime(cuda, "auto", torch_gpu=True) == ("onnxruntime", cuda)  # onnxruntime's CUDA first
    assert network_runtime(cpu, "cuda", torch_gpu=True) == ("torch", "cuda")
    assert network_runtime(cuda, "cpu", torch_gpu=True) == ("onnxruntime", cpu)
    assert network_runtime(cpu, "torch", torch_gpu=False) == ("torch", "cpu")
    for device, providers in (("cuda", cpu), ("tpu", cuda)):
        with pytest.raises(InputError) as err:
            network_runtime(providers, device, torch_gpu=False)
        assert err.value.field == "INTERLEAVE_ORT_DEVICE"


def test_open_network_gives_the_torch_runner_when_asked(tmp_path, monkeypatch):
    _tiny_graph(tmp_path / "net.onnx")
    monkeypatch.setenv("INTERLEAVE_ORT_DEVICE", "torch")
    session, meta = open_network(tmp_path / "net.onnx", 1, "interleave.test", "model", "missing")
    assert isinstance(session, TorchOnnxSession) and meta == {"ok": 1}
    monkeypatch.setenv("INTERLEAVE_ORT_DEVICE", "cpu")
    session, _ = open_network(tmp_path / "net.onnx", 1, "interleave.test", "model", "missing")
    assert isinstance(session, ort.InferenceSession)


def test_decomp_predicts_the_same_frame_with_its_networks_in_torch(monkeypatch):
    """The end-to-end check of the GPU path on the CPU: ``decomp`` runs three networks (correlation flow, 3D flow,
    infilling); with every one of them in torch the predicted frame is onnxruntime's, to float rounding."""
    from engine.predict import Target, make_predictor
    from tests.synthetic import two_layer_sequence

    frames, _ = two_layer_sequence(6, width=160, height=96, camera_speed=0.02, object_speed=0.3)
    target = Target(frames[5].camera, frames[5].time, frames[5].index)
    monkeypatch.setenv("INTERLEAVE_ORT_DEVICE", "cpu")
    want = make_predictor("decomp").predict([frames[2], frames[4]], target)
    monkeypatch.setenv("INTERLEAVE_ORT_DEVICE", "torch")
    predictor = make_predictor("decomp")
    got = predictor.predict([frames[2], frames[4]], target)
    assert isinstance(predictor.network.session, TorchOnnxSession) and predictor.network.session._plans  # it ran
    np.testing.assert_array_equal(got.holes, want.holes)
    assert float(np.abs(got.color - want.color).max()) < 1e-3
