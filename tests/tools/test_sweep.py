"""The decomp speed/error sweep (tools/sweep.py): Pareto front, variant grid, plane-count networks."""
import json
import math
import shutil

import pytest

from engine.core.errors import InputError
from engine.eval.protocol import MethodResult
from engine.io.rgbd import write_sequence
from engine.predict.decomp.network import DEFAULT_MODEL
from tests.synthetic import two_layer_sequence
from tools.sweep import Variant, decomp_variants
from tools.sweep import main as sweep_main
from tools.sweep import pareto_front, plane_models, sweep_points, sweep_table


def test_pareto_front_keeps_the_fastest_for_each_error():
    times = [1.0, 2.0, 3.0, 4.0, 2.0]
    errors = [5.0, 6.0, 4.0, 4.0, 3.0]
    # 1: fastest; 2: slower and worse than 1; 3 and 4: beaten by point 5 (faster, better); 5: best error
    assert pareto_front(times, errors) == [True, False, False, False, True]
    assert pareto_front([1.0, 1.0], [2.0, 2.0]) == [True, True]  # identical points do not dominate each other
    assert pareto_front([1.0, 2.0], [2.0, 2.0]) == [True, False]  # same error, slower: dominated
    assert pareto_front([1.0, 2.0, 3.0], [math.nan, 5.0, 4.0]) == [False, True, True]  # NaN neither on nor beats
    assert pareto_front([], []) == []
    with pytest.raises(InputError, match="2 times but 1 errors"):
        pareto_front([1.0, 2.0], [1.0])


def test_variant_grid_sweeps_infill_passes_only_with_the_network():
    variants = decomp_variants([480, 240], ["simple", "infill"], [1, 2, 3], [4, 8], {4: "", 8: "z8.onnx"}, "gate=0")
    assert len(variants) == 2 * 2 * (1 + 3)
    assert variants[0] == Variant("decomp[gate=0,flow_width=480,fill=simple]", 480, "simple", None, 4, "medium")
    assert variants[1].method == "decomp[gate=0,flow_width=480,fill=infill,infill_iterations=1]"
    assert variants[-1].method == "decomp[gate=0,flow_width=240,fill=infill,infill_iterations=3,model=z8.onnx]"
    assert variants[-1].label == "decomp w240 Z8 infill g3" and Variant("reproject").label == "reproject"
    with pytest.raises(InputError, match="swept by the sweep itself"):
        decomp_variants([480], ["simple"], [1], [4], {4: ""}, "fill=infill")
    with pytest.raises(InputError, match="unknown fill"):
        decomp_variants([480], ["magic"], [1], [4], {4: ""})
    with pytest.raises(InputError, match="no flow network for Z"):
        decomp_variants([480], ["simple"], [1], [2], {4: ""})
    fast = decomp_variants([480], ["simple"], [1], [4], {4: ""}, dis_presets=["medium", "fast"])
    assert [v.method for v in fast] == ["decomp[flow_width=480,fill=simple]",
                                        "decomp[flow_width=480,fill=simple,dis_preset=fast]"]
    assert fast[1].label == "decomp w480 Z4 simple DIS-fast" and fast[0].label == "decomp w480 Z4 simple"
    with pytest.raises(InputError, match="unknown DIS preset"):
        decomp_variants([480], ["simple"], [1], [4], {4: ""}, dis_presets=["slow"])


def _result(method: str, ms: float, psnr: float, flip: float) -> MethodResult:
    return MethodResult(sequence="s", method=method, k=2, frames=3, psnr=psnr, ssim=0.9, flip=flip,
                        psnr_moving=psnr - 5, ssim_moving=0.8, flip_moving=flip * 2, ms_per_frame=ms)


def test_points_are_grouped_by_frame_size_with_their_own_fronts():
    variants = [Variant("reproject"), Variant("decomp[flow_width=480,fill=simple]", 480, "simple", None, 4)]
    results = [("960x540", _result("reproject", 100.0, 30.0, 0.04)),
               ("960x540", _result(variants[1].method, 500.0, 31.0, 0.05)),
               ("1920x1080", _result("reproject", 400.0, 29.0, 0.05)),
               ("1920x1080", _result(variants[1].method, 300.0, 29.5, 0.04))]
    points = sweep_points(results, variants)
    front = {(p.resolution, p.label): (p.pareto_psnr, p.pareto_flip) for p in points}
    assert front == {("960x540", "reproject"): (True, True), ("960x540", "decomp w480 Z4 simple"): (True, False),
                     ("1920x1080", "reproject"): (False, False), ("1920x1080", "decomp w480 Z4 simple"): (True, True)}
    table = sweep_table(points)
    assert "| 960x540 | decomp | 480 | simple | - | 4 | - | 3 | 500.0 | 31.00 | 0.0500 | 26.00 | PSNR |" in table
    fast = sweep_points([("960x540", _result("flow2d[preset=fast]", 90.0, 30.5, 0.04))], [Variant("flow2d[preset=fast]")])
    assert "| 960x540 | flow2d[preset=fast] | - |" in sweep_table(fast)


def test_plane_models_use_the_committed_network_for_its_own_planes(tmp_path):
    assert plane_models([2], tmp_path) == {2: ""}
    shutil.copy(DEFAULT_MODEL, tmp_path / "flow3d_z4_xy.onnx")  # a 2-plane network under a 4-plane name (no dz)
    with pytest.raises(InputError, match="holds a network for 2 planes, expected 4"):
        plane_models([4], tmp_path)


def test_sweep_runs_on_a_tiny_sequence(tmp_path, capsys):
    frames, objects = two_layer_sequence(9, width=80, height=60, camera_speed=0.05, object_speed=0.08)
    path = write_sequence(tmp_path / "seq", frames, fps=30.0, objects=objects)
    out = tmp_path / "sweep"
    assert sweep_main([str(path), "--fill", "simple", "--flow-width", "80,40", "--max-groups", "2",
                 "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "| 80x60 | reproject |" in printed and "Stage breakdown at 80x60" in printed
    doc = json.loads((out / "sweep.json").read_text())
    assert [p["label"] for p in doc["points"]] == ["reproject", "flow2d", "decomp w80 Z4 simple",
                                                   "decomp w40 Z4 simple"]
    assert any(p["pareto_psnr"] for p in doc["points"]) and any(p["pareto_flip"] for p in doc["points"])
    fastest = min(doc["points"], key=lambda p: p["ms_per_frame"])
    assert fastest["pareto_psnr"] and fastest["pareto_flip"]  # nothing is faster than the fastest
    assert len(doc["records"]) == len(doc["resolutions"]) == 4
    assert (out / "sweep.md").stat().st_size > 0 and (out / "sweep.png").stat().st_size > 10_000
    assert sweep_main([str(path), "--fill", "simple", "--decomp-options", "flow_width=10",
                 "--out", str(out)]) == 2
    assert "swept by the sweep itself" in capsys.readouterr().err
