"""The evaluation protocol and its outputs (JSON keys, table, plot) on an analytic sequence on disk."""
import json

import numpy as np
import pytest

from engine.core.errors import InputError
from engine.eval.protocol import (TRUE_HOLES, bound_methods, bounds_summary, bounds_table, evaluate_sequence,
                                  evaluation_pairs, markdown_table, per_step_table, plot, split_scoring, stage_table,
                                  with_true_holes, write_json)
from engine.io.rgbd import read_sequence, write_sequence
from tests.synthetic import two_layer_sequence


def _written_sequence(tmp_path_factory, name: str, object_speed: float):
    """A 9-frame two-layer sequence (96 x 64, camera speed 0.1) written to disk and read back."""
    frames, objects = two_layer_sequence(9, width=96, height=64, camera_speed=0.1, object_speed=object_speed)
    path = write_sequence(tmp_path_factory.mktemp("seq") / name, frames, fps=30.0, objects=objects)
    return read_sequence(path)


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    return _written_sequence(tmp_path_factory, "two_layer", 0.03)


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


@pytest.fixture(scope="module")
def moving_sequence(tmp_path_factory):
    """Camera and object both move enough that k = 4 leaves disocclusions to fill."""
    return _written_sequence(tmp_path_factory, "moving", 0.08)


def test_true_holes_copy_the_truth_into_the_holes_only():
    color = np.zeros((4, 5, 3), np.float32)
    truth = np.ones((4, 5, 3), np.float32)
    holes = np.zeros((4, 5), bool)
    holes[1, 2] = True
    out = with_true_holes(color, holes, truth)
    assert out[1, 2].tolist() == [1, 1, 1] and out.sum() == 3 and color.sum() == 0  # the input is not changed
    assert split_scoring("decomp[fill=simple]" + TRUE_HOLES) == ("decomp[fill=simple]", True)
    assert split_scoring("reproject") == ("reproject", False)
    with pytest.raises(InputError, match="holes"):
        with_true_holes(color, holes[:, :4], truth)


def test_truth_in_holes_is_never_worse_on_the_hole_pixels(moving_sequence):
    methods = ["reproject", "reproject" + TRUE_HOLES, "decomp[fill=simple]", "decomp[fill=simple]" + TRUE_HOLES]
    by = {r.method: r for r in evaluate_sequence(moving_sequence, methods, 4, with_flip=False)}
    for method in ("reproject", "decomp[fill=simple]"):
        pred, exact = by[method], by[method + TRUE_HOLES]
        assert pred.hole_fraction > 0 and exact.hole_fraction == pred.hole_fraction  # the same predictions
        assert np.isfinite(pred.psnr_holes) and exact.psnr_holes == float("inf")  # hole pixels now exact
        assert exact.psnr >= pred.psnr and exact.ssim >= pred.ssim - 1e-6
        assert exact.ms_per_frame == pred.ms_per_frame  # shared predictor, shared times
        for step in ("1", "2", "3"):
            assert exact.per_step[step]["psnr"] >= pred.per_step[step]["psnr"]


def test_bound_rows_name_the_four_cases():
    rows = bound_methods("decomp[fill=simple]")
    assert [(r.motion, r.infill) for r in rows] == [("pred", "pred"), ("GT", "pred"), ("pred", "GT"), ("GT", "GT")]
    assert [r.method for r in rows] == ["decomp[fill=simple]", "decomp[fill=simple,motion=truth]",
                                        "decomp[fill=simple]+true_holes", "decomp[fill=simple,motion=truth]+true_holes"]
    assert bound_methods()[1].method == "decomp[motion=truth]"
    for bad in ("reproject", "decomp[motion=truth]", "decomp[fill=simple", "decomp+true_holes"):
        with pytest.raises(InputError):
            bound_methods(bad)


def test_bounds_true_motion_and_pixels_beat_the_prediction(moving_sequence):
    rows = bound_methods("decomp[fill=simple]")
    results = evaluate_sequence(moving_sequence, [r.method for r in rows], 4, with_flip=False)
    by = {(row.motion, row.infill): next(r for r in results if r.method == row.method) for row in rows}
    assert by["GT", "GT"].psnr >= by["pred", "pred"].psnr
    assert by["GT", "GT"].psnr_moving >= by["pred", "pred"].psnr_moving
    for motion in ("pred", "GT"):  # exact hole pixels never lower the PSNR of the same predictions
        assert by[motion, "GT"].psnr >= by[motion, "pred"].psnr
    summary = bounds_summary(results, rows)
    assert [(e["motion"], e["infill"]) for e in summary] == [(r.motion, r.infill) for r in rows]
    table = bounds_table(results, rows)
    assert "| 4 | GT | GT | decomp[fill=simple,motion=truth]+true_holes |" in table and "exact" in table


def test_true_motion_without_objects_is_a_clear_error(tmp_path):
    frames, _ = two_layer_sequence(9, width=48, height=32)
    sequence = read_sequence(write_sequence(tmp_path / "no_objects", frames, fps=30.0))
    with pytest.raises(InputError, match="motion=truth needs the sequence's moving objects") as exc:
        evaluate_sequence(sequence, [bound_methods("decomp[fill=simple]")[1].method], 2)
    assert "no_objects" in str(exc.value)


def test_per_step_table_lists_every_future_step(sequence):
    results = evaluate_sequence(sequence, ["reproject"], 4, with_flip=False)
    table = per_step_table(results)
    assert [line.split("|")[3].strip() for line in table.splitlines()[2:]] == ["1", "2", "3"]
    assert results[0].per_step["2"]["frames"] == 1
    assert [line.split(" | ")[6] for line in table.splitlines()[2:]] == ["-"] * 3  # FLIP skipped: '-', not nan
    assert "nan" not in table.lower()
