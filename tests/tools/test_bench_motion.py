"""``tools.bench_motion`` end to end on tiny renders: the speed rule of its held-out sets, the table, the JSON."""
import json

from tools import bench_motion, heldout


def test_bench_prints_speed_against_error_and_writes_json(tmp_path, capsys, monkeypatch):
    # a fast set whose speed rule keeps seeds of median 0.5-1000 px a frame (at 640 px width)
    monkeypatch.setitem(bench_motion.SETS, "fast", ("fast", 7001, (0.5, 1000.0)))
    out = tmp_path / "bench.json"
    bench_motion.main(["--out", str(tmp_path / "seqs"), "--size", "96x64", "--frames", "6", "--k", "2",
                       "--methods", "reproject,flow2d", "--sets", "gentle,fast", "--count", "1",
                       "--json", str(out)])
    printed = capsys.readouterr().out
    assert "| gentle | 2 | flow2d |" in printed and "| fast | 2 | oracle |" in printed
    doc = json.loads(out.read_text())
    rows = {(r["set"], r["method"]): r for r in doc["rows"]}
    assert rows[("fast", "reproject")]["time_vs_reproject"] == 1.0
    assert rows[("fast", "oracle")]["gap_moving"] == 1.0
    (name,) = doc["sets"]["fast"]
    seeds = json.loads((tmp_path / "seqs" / "fast_96x64x6_seeds.json").read_text())
    assert name == f"fast{min(int(s) for s, v in seeds.items() if v['median'] >= 0.5)}"
    assert doc["speeds"][name][0] * 640 / 96 >= 0.5


def test_speed_set_says_when_no_seed_is_fast_enough(tmp_path):
    try:
        heldout.speed_set(tmp_path, "none", "gentle", 1, 1, (1e6, 2e6), 32, 24, 2, max_tries=1)
    except RuntimeError as error:
        assert "only 0 of 1 seeds" in str(error)
    else:
        raise AssertionError("expected a RuntimeError")
    assert not (tmp_path / "none1_32x24x2").exists()  # seeds outside the rule are not kept
