"""``tools.bench_mvec`` end to end on a tiny render: the table, the measured speeds and the JSON."""
import json

from tools import bench_mvec


def test_bench_prints_speed_against_error_and_writes_json(tmp_path, capsys):
    out = tmp_path / "bench.json"
    bench_mvec.main(["--out", str(tmp_path / "seqs"), "--size", "96x64", "--frames", "8", "--k", "2",
                     "--methods", "reproject,mvec", "--sets", "gentle,camera", "--timing-size", "64x48",
                     "--repeats", "1", "--json", str(out)])
    printed = capsys.readouterr().out
    assert "| gentle | 2 | mvec |" in printed and "| camera | 2 | mvec |" in printed
    doc = json.loads(out.read_text())
    rows = {(r["set"], r["method"]): r for r in doc["rows"]}
    assert rows[("gentle", "reproject")]["time_vs_reproject"] == 1.0
    assert rows[("gentle", "mvec")]["psnr"] >= rows[("gentle", "reproject")]["psnr"]
    # a camera-only scene: mvec is reproject exactly (nothing moves but the camera)
    assert rows[("camera", "mvec")]["psnr"] == rows[("camera", "reproject")]["psnr"]
    assert set(doc["speeds"]) == {"seed1001", "seed1002", "camera1004"}
    timed = {(t["sequence"], t["k"]) for t in doc["timing"]}
    assert timed == {(s, k) for s in ("seed1001", "glide3302", "spin4101") for k in (2, 4)}
    assert all(t["ms"]["mvec"] > 0 and t["ms"]["reproject"] > 0 for t in doc["timing"])


def test_profile_splits_a_prediction_into_its_passes(tmp_path, capsys):
    from tools import profile_mvec

    out = tmp_path / "profile.json"
    profile_mvec.main(["--out", str(tmp_path / "seqs"), "--size", "96x64", "--frames", "8", "--k", "2",
                       "--methods", "mvec[extrapolation=rigid,fallback=true]", "--sequences", "spin4101",
                       "--repeats", "2", "--json", str(out)])
    assert "spin4101 k=2" in capsys.readouterr().out
    (row,) = json.loads(out.read_text())["rows"]
    methods = row["methods"]
    assert list(methods) == ["reproject", "mvec[extrapolation=rigid,fallback=true]"]
    assert set(methods["reproject"]["passes"]) == {"render:warp", "render:fill"}  # nothing to prepare
    rigid = methods["mvec[extrapolation=rigid,fallback=true]"]["passes"]
    assert {"prepare:velocity", "prepare:rigid", "render:warp"} <= set(rigid)  # the motion extrapolated in the warp
    steps = {"prepare:rigid.groups", "prepare:rigid.parts", "prepare:rigid.keep"}  # the steps of pass rigid
    assert steps <= set(rigid) and sum(rigid[s] for s in steps) <= 1.5 * rigid["prepare:rigid"]
    for result in methods.values():
        assert result["wall_ms"] > 0 and result["cpu_ms"] > 0
        # the passes are parts of the prediction (medians of parts may exceed the median whole only slightly)
        assert sum(v for name, v in result["passes"].items() if "." not in name) <= 1.5 * result["wall_ms"]



def test_the_steps_profile_times_each_call_on_the_calling_thread(tmp_path, capsys):
    import engine.predict.base as base
    import engine.predict.mvec as mvec
    from tools import profile_mvec_steps

    before = (mvec.scene_velocity, base.geometry.forward_warp_moved_frame, base.Timer.__call__)
    out = tmp_path / "steps.json"
    profile_mvec_steps.main(["--out", str(tmp_path / "seqs"), "--size", "96x64", "--frames", "8", "--k", "2",
                             "--methods", "mvec[extrapolation=rigid],reproject", "--sequences", "spin4101",
                             "--repeats", "2", "--json", str(out)])
    assert "spin4101 k=2 mvec[extrapolation=rigid]" in capsys.readouterr().out
    assert (mvec.scene_velocity, base.geometry.forward_warp_moved_frame, base.Timer.__call__) == before  # unwrapped
    rigid, plain = json.loads(out.read_text())["rows"]
    assert {"fn:scene_velocity", "fn:find_parts", "fn:previous_positions", "fn:kept_part_motion",
            "fn:forward_warp_moved_frame", "stage:rigid.parts", "stage:warp"} <= set(rigid["ms"])
    assert not any(name.startswith("fn:scene") for name in plain["ms"]) and "stage:warp" in plain["ms"]
    for row, warp in ((rigid, "fn:forward_warp_moved_frame"), (plain, "fn:forward_warp_frame")):
        wall, cpu = row["total_ms"]
        assert row["frames"] > 0 and wall > 0 and cpu > 0
        # a step's calling-thread time is part of its stage's, and the stages are parts of the whole
        assert row["ms"][warp][1] <= row["ms"]["stage:warp"][1] + 1e-3
        assert sum(c for name, (_, c, _) in row["ms"].items() if name.startswith("stage:") and "." not in name) \
            <= cpu + 1e-3

def test_fallback_audit_scores_each_choice_against_the_true_flow(tmp_path, capsys):
    from tools import fallback_audit

    out = tmp_path / "audit.json"
    fallback_audit.main(["--out", str(tmp_path / "seqs"), "--size", "96x64", "--frames", "8", "--k", "2",
                         "--sequences", "fast3203", "--min-pixels", "1", "--json", str(out)])
    assert "fast3203 k=2: flow error" in capsys.readouterr().out
    rows = json.loads(out.read_text())["rows"]
    (totals,) = [r["totals_kpx"] for r in rows if "totals_kpx" in r]
    # the best choice per group is at most either rule; the method's decisions lie between best and worst
    assert totals["best"] <= min(totals["keep"], totals["method"]) + 1e-9
    assert totals["keep"] > 0
    for group in (r for r in rows if "group" in r):
        assert group["better_held"] == (group["camera_only_px"] < group["keep_px"])
