"""tools.compare_scores: exact score comparison of two eval runs, timings ignored."""
import json
import math

from tools.compare_scores import main, score_differences


def _record(psnr, ms=1.0, step_psnr=20.0, method="reproject"):
    return {"sequence": "s", "method": method, "k": 2, "psnr": psnr, "flip": math.nan, "ms_per_frame": ms,
            "stages_ms": {"warp": ms}, "per_step": {"1": {"psnr": step_psnr}}}


def test_identical_scores_with_other_timings_match(tmp_path, capsys):
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text(json.dumps({"records": [_record(30.0, ms=1.0)]}))
    b.write_text(json.dumps({"records": [_record(30.0, ms=9.0)]}))
    assert main([str(a), str(b)]) == 0
    assert "1 records compared, 0 differences" in capsys.readouterr().out


def test_a_changed_score_a_changed_step_and_a_missing_record_are_reported():
    key = ("s", "reproject", 2)
    assert len(score_differences({key: _record(30.0)}, {key: _record(30.0 + 1e-12)})) == 1
    assert len(score_differences({key: _record(30.0)}, {key: _record(30.0, step_psnr=19.0)})) == 1
    other = ("s", "flow2d", 2)
    lines = score_differences({key: _record(30.0), other: _record(1.0, method="flow2d")}, {key: _record(30.0)})
    assert lines == [f"{other}: only in the first"]
