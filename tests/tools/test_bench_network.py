"""The flow-graph benchmark (tools/bench_network.py): records the engine's real network inputs and times
graphs on them; graphs that take other inputs are refused."""
from __future__ import annotations

import json

import pytest

from engine.core.errors import InputError
from engine.io.rgbd import write_sequence
from engine.predict.decomp.network import DEFAULT_MODEL
from tests.synthetic import two_layer_sequence
from tools import bench_network


@pytest.fixture(scope="module")
def moving(tmp_path_factory):
    frames, objects = two_layer_sequence(9, width=192, height=128, camera_speed=0.02, object_speed=0.15)
    return write_sequence(tmp_path_factory.mktemp("seq") / "moving", frames, fps=30.0, objects=objects)


def test_benchmark_times_each_graph_on_the_recorded_boxes(moving, tmp_path, capsys):
    copy = tmp_path / "copy.onnx"
    copy.write_bytes(DEFAULT_MODEL.read_bytes())
    out = tmp_path / "b.json"
    bench_network.main([str(moving), "--models", f"{DEFAULT_MODEL},{copy}", "--groups", "2", "--repeats", "1",
                        "--threads", "1", "--json", str(out)])
    result = json.loads(out.read_text())
    assert result["boxes"] >= 1 and len(result["graphs"]) == 2
    assert all(g["median_ms_per_box"] > 0 and g["median_ms_per_frame"] >= g["median_ms_per_box"]
               for g in result["graphs"])
    assert [g["max_flow_difference_px"] for g in result["graphs"]] == [0.0, 0.0]  # the same graph
    assert "ms / box" in capsys.readouterr().out


def test_benchmark_refuses_graphs_with_other_inputs(moving):
    other = DEFAULT_MODEL.with_name("flow2d.onnx")  # the 2D ablation: one plane
    with pytest.raises(InputError, match="planes"):
        bench_network.run([moving], [DEFAULT_MODEL, other], groups=1, repeats=1, threads=1)


def test_benchmark_says_when_the_network_never_ran(tmp_path):
    frames, objects = two_layer_sequence(7, width=128, height=96, camera_speed=0.02, object_speed=0.0)
    still = write_sequence(tmp_path / "still", frames, fps=30.0, objects=objects)
    with pytest.raises(InputError, match="never ran"):
        bench_network.run([still], [DEFAULT_MODEL], groups=2, repeats=1, threads=1)
