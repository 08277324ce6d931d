"""The evaluation protocol and its outputs (JSON keys, table, plot) on an analytic sequence on disk."""
import json

import numpy as np
import pytest

from engine.errors import InputError
from engine.evaluate import evaluate_sequence, evaluation_pairs, markdown_table, plot, stage_table, write_json
from engine.io import read_sequence, write_sequence
from tests.synthetic import two_layer_sequence


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    frames, objects = two_layer_sequence(9, width=96, height=64, camera_speed=0.1, object_speed=0.03)
    path = write_sequence(tmp_path_factory.mktemp("seq") / "two_layer", frames, fps=30.0, objects=objects)
    return read_sequence(path)


def test_evaluation_pairs_follow_the_protocol():
    assert evaluation_pairs(9, 2) == [(0, 2, [3]), (2, 4, [5]), (4, 6, [7])]
    assert evaluation_pairs(9, 4) == [(0, 4, [5, 6, 7])]
    assert evaluation_pairs(3, 2) == []
    with pytest.raises(InputError, match="k must be >= 2"):
        evaluation_pairs(9, 1)


def test_evaluate_writes_records_with_required_keys(sequence, tmp_path):
    results = evaluate_sequence(sequence, ["repeat", "reproject", "flow2d", "oracle"], 2)
    by = {r.method: r for r in results}
    assert by["reproject"].psnr > by["repeat"].psnr
    assert by["oracle"].psnr_moving > by["reproject"].psnr_moving
    assert all(r.frames == 3 and r.ms_per_frame > 0 for r in results)
    assert all(np.isfinite([r.psnr, r.ssim, r.flip, r.psnr_moving, r.flip_moving]).all() for r in results)
    write_json(results, tmp_path / "out.json")
    doc = json.loads((tmp_path / "out.json").read_text())
    for rec in doc["records"]:
        assert {"sequence", "method", "k", "frames", "psnr", "ssim", "flip", "psnr_moving", "ms_per_frame"} <= set(rec)
    assert doc["summary"]["reproject/k=2"]["time_vs_reproject"] == pytest.approx(1.0)
    table = markdown_table(results)
    assert table.count("\n") == 1 + len(results) + len(doc["summary"])
    stages = stage_table(results)
    assert "prepare:flow" in stages and "warp" in stages and stages.count("\n") == 1 + len(results)
    plot(results, tmp_path / "plot.png")
    assert (tmp_path / "plot.png").stat().st_size > 10_000


def test_k4_reports_per_step_scores(sequence):
    (result,) = evaluate_sequence(sequence, ["reproject"], 4, with_flip=False)
    assert result.frames == 3 and set(result.per_step) == {"1", "2", "3"}
    assert result.per_step["1"]["psnr"] > result.per_step["3"]["psnr"]  # error grows with the step


def test_too_short_sequence_is_an_error(sequence):
    with pytest.raises(InputError, match="too few"):
        evaluate_sequence(sequence, ["repeat"], 8)
