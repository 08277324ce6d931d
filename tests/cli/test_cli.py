"""The `interleave` command line: help for every option, clear errors with exit status 2, end to end runs."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

from engine.cli import build_parser, main
from engine.io.rgbd import read_sequence, write_sequence
from tests.synthetic import two_layer_sequence


@pytest.mark.parametrize("command", ["demo", "eval", "render-scene", "import", "play"])
def test_every_option_has_help(command, capsys):
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    sub = build_parser()._subparsers._group_actions[0].choices[command]
    for action in sub._actions:
        if action.option_strings and action.dest != "help":
            assert action.help and len(action.help) > 8, f"{command} {action.option_strings} lacks help"
            assert action.option_strings[0] in text


def test_missing_sequence_is_a_clear_error(tmp_path, capsys):
    assert main(["eval", str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err
    assert "interleave eval: error:" in err and "nope" in err and "Traceback" not in err


def test_unknown_method_is_a_clear_error(tmp_path, capsys):
    frames, objects = two_layer_sequence(5)
    path = write_sequence(tmp_path / "seq", frames, fps=30.0, objects=objects)
    assert main(["eval", str(path), "--methods", "reproject,magic"]) == 2
    assert "magic" in capsys.readouterr().err


def test_eval_writes_json_and_plot(tmp_path, capsys):
    frames, objects = two_layer_sequence(9, width=80, height=60, camera_speed=0.1, object_speed=0.03)
    path = write_sequence(tmp_path / "seq", frames, fps=30.0, objects=objects)
    out_json, out_png = tmp_path / "r.json", tmp_path / "r.png"
    assert main(["eval", str(path), "--k", "2,4", "--json", str(out_json), "--plot", str(out_png)]) == 0
    doc = json.loads(out_json.read_text())
    methods = ("repeat", "reproject", "flow2d", "decomp", "mvec", "oracle")
    assert {(r["method"], r["k"]) for r in doc["records"]} == {(m, k) for m in methods for k in (2, 4)}
    epe = {r["method"]: r["epe_moving"] for r in doc["records"] if r["k"] == 2}
    assert epe["repeat"] is None and epe["flow2d"] > 0 and epe["decomp"] > 0  # only flow methods have an EPE
    assert out_png.stat().st_size > 10_000
    printed = capsys.readouterr().out
    assert "| seq | 2 | reproject |" in printed and "reproject beats repeat (PSNR) on 1 of 1" in printed


def test_eval_on_the_gl_backend_reports_gpu_time(tmp_path, capsys):
    from engine.geometry.backends import gl as glb

    if not glb.available():
        pytest.skip("no EGL context with compute shaders")
    frames, objects = two_layer_sequence(7, width=80, height=60, camera_speed=0.1, object_speed=0.03)
    path = write_sequence(tmp_path / "seq", frames, fps=30.0, objects=objects)
    out_json = tmp_path / "r.json"
    assert main(["eval", str(path), "--methods", "repeat,reproject,decomp", "--backend", "gl", "--no-flip",
                 "--json", str(out_json)]) == 0
    records = {r["method"]: r for r in json.loads(out_json.read_text())["records"]}
    assert [records[m]["backend"] for m in ("repeat", "reproject", "decomp")] == ["cpu", "gl", "gl"]
    assert {"warp", "fill", "readback"} <= set(records["decomp"]["gpu_ms"]) and not records["repeat"]["gpu_ms"]
    printed = capsys.readouterr().out
    assert "| backend |" in printed and "gpu total" in printed


def test_render_scene_and_demo_end_to_end(tmp_path):
    assert main(["render-scene", str(tmp_path / "scene"), "--width", "64", "--height", "48", "--num-frames", "5",
                 "--seed", "3", "--supersample", "1"]) == 0
    seq = read_sequence(tmp_path / "scene")
    assert len(seq) == 5 and seq.has_channel("object_flow")
    assert main(["demo", "--out", str(tmp_path / "demo"), "--frames", "8", "--width", "96", "--height", "64"]) == 0
    for name in ("side_by_side.mp4", "table.md", "results.json", "speed_vs_error.png"):
        assert (tmp_path / "demo" / name).stat().st_size > 0


@pytest.mark.parametrize("args, field", [(["--k", "1"], "k"), (["--frames", "3"], "frames"),
                                         (["--methods", "reproject,bogus"], "methods"),
                                         (["--methods", "decomp[bogus=1]"], "decomp")])
def test_demo_refuses_bad_settings_before_it_renders(tmp_path, capsys, args, field):
    assert main(["demo", "--out", str(tmp_path / "demo"), "--width", "96", "--height", "64", *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"field '{field}'" in err[0]
    assert not (tmp_path / "demo").exists()  # nothing rendered, nothing written


def test_eval_bounds_prints_the_four_rows_and_writes_json(tmp_path, capsys):
    frames, objects = two_layer_sequence(9, width=80, height=60, camera_speed=0.1, object_speed=0.08)
    path = write_sequence(tmp_path / "seq", frames, fps=30.0, objects=objects)
    out_json = tmp_path / "bounds.json"
    assert main(["eval", str(path), "--bounds", "decomp[fill=simple]", "--k", "4", "--no-flip",
                 "--json", str(out_json)]) == 0
    printed = capsys.readouterr().out
    for motion, infill in (("pred", "pred"), ("GT", "pred"), ("pred", "GT"), ("GT", "GT")):
        assert f"| 4 | {motion} | {infill} | decomp[fill=simple" in printed
    assert "Per future step k'" in printed  # k > 2
    doc = json.loads(out_json.read_text())
    assert doc["bounds_variant"] == "decomp[fill=simple]" and len(doc["bounds"]) == 4
    assert {"motion", "infill", "psnr", "ssim", "flip", "psnr_moving", "hole_fraction"} <= set(doc["bounds"][0])


def test_eval_bounds_errors(tmp_path, capsys):
    frames, _ = two_layer_sequence(5)
    path = write_sequence(tmp_path / "no_objects", frames, fps=30.0)
    assert main(["eval", str(path), "--bounds", "decomp[fill=simple]", "--no-flip"]) == 2
    err = capsys.readouterr().err
    assert "motion=truth needs the sequence's moving objects" in err and "no_objects" in err
    assert "Traceback" not in err
    assert main(["eval", str(path), "--bounds", "flow2d"]) == 2
    assert "decomp variant" in capsys.readouterr().err


def test_eval_k5_prints_a_per_step_table(tmp_path, capsys):
    frames, objects = two_layer_sequence(11, width=80, height=60, camera_speed=0.05, object_speed=0.03)
    path = write_sequence(tmp_path / "seq", frames, fps=30.0, objects=objects)
    out_json = tmp_path / "k5.json"
    methods = ("reproject", "flow2d", "decomp[fill=simple]")
    assert main(["eval", str(path), "--k", "5", "--methods", ",".join(methods), "--json", str(out_json)]) == 0
    printed = capsys.readouterr().out
    for method in methods:
        for step in (1, 2, 3, 4):
            assert f"| {method} | 5 | {step} | 1 |" in printed
    doc = json.loads(out_json.read_text())
    assert all(set(r["per_step"]) == {"1", "2", "3", "4"} for r in doc["records"])
    assert all(r["per_step"]["4"]["flip"] > 0 for r in doc["records"])


def test_import_through_the_command_line(tmp_path, capsys):
    from tests.io.test_importers import write_veed

    src = write_veed(tmp_path / "veed", channel="Y")
    assert main(["import", "veed", str(src), str(tmp_path / "out"), "--depth-channel", "Y", "--fps", "60"]) == 0
    seq = read_sequence(tmp_path / "out")
    assert len(seq) == 3 and seq.fps == 60.0
    assert main(["import", "blender", str(src), str(tmp_path / "out2"), "--fps", "60"]) == 2
    assert "does not take --fps" in capsys.readouterr().err
    assert main(["import", "veed", str(src), str(tmp_path / "out3")]) == 2  # depth is in Y, not B
    err = capsys.readouterr().err
    assert "interleave import: error:" in err and "B" in err and "Traceback" not in err


@pytest.mark.parametrize("argv, names", [
    (["eval", "{seq}", "--max-groups", "0"], "--max-groups"),
    (["eval", "{seq}", "--max-groups", "-3"], "--max-groups"),
    (["eval", "{seq}", "--methods", ""], "--methods"),
    (["eval", "{seq}", "--methods", "reproject", "--json", "{tmp}"], "is a folder"),
    (["eval", "{seq}", "--methods", "reproject", "--json", "/proc/no/x.json"], "--json"),
    (["eval", "{seq}", "{tmp}/missing", "--methods", "reproject", "--json", "{tmp}/r.json"], "missing"),
    (["render-scene", "{tmp}/big", "--width", "20000", "--height", "20000", "--num-frames", "1"], "8192"),
    (["render-scene", "{tmp}/afile", "--width", "32", "--height", "24", "--num-frames", "2"], "not a folder"),
    (["import", "sintel", "{tmp}", "{tmp}/out"], "--scene"),
    (["serve", "--listen", "tcp:70000"], "0..65535"),
    (["eval", "{tmp}/deep"], "nests too deeply"),
])
def test_careless_input_is_one_line_and_exit_2(tmp_path, capsys, argv, names):
    """Each of these ended in a traceback or exit 1 (issue 20, D6/D11); a bad output file is caught before the
    work, and a bad second sequence before the first is evaluated."""
    frames, objects = two_layer_sequence(5, width=48, height=32)
    seq = write_sequence(tmp_path / "seq", frames, fps=30.0, objects=objects)
    (tmp_path / "afile").write_text("x")
    (tmp_path / "deep").mkdir()
    (tmp_path / "deep" / "sequence.json").write_text("[" * 200_000 + "]" * 200_000)
    args = [a.format(seq=seq, tmp=tmp_path) for a in argv]
    try:
        code = main(args)
    except SystemExit as exc:  # argparse's own errors (usage, then one error line)
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"interleave {args[0]}: error:") and names in last and "Traceback" not in err
    assert not (tmp_path / "r.json").exists()


def test_no_flip_plots_psnr_alone_and_prints_dashes(tmp_path, capsys):
    """--no-flip --plot crashed in matplotlib (no finite FLIP on a log-scaled axis) and printed nan (issue 20)."""
    frames, objects = two_layer_sequence(7, width=48, height=32)
    seq = write_sequence(tmp_path / "seq", frames, fps=30.0, objects=objects)
    png = tmp_path / "p.png"
    assert main(["eval", str(seq), "--methods", "repeat,reproject", "--no-flip", "--plot", str(png)]) == 0
    assert png.stat().st_size > 5_000
    row = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("| seq | 2 | reproject"))
    assert "nan" not in row and row.split("|")[7].strip() == "-"  # the FLIP column


def test_an_error_during_eval_starts_its_own_line(tmp_path):
    """Issue 20, D8: the one-line error was printed onto the progress bar's line, and the bar redrawn."""
    frames, objects = two_layer_sequence(7, width=48, height=32)
    seq = write_sequence(tmp_path / "seq", frames, fps=30.0, objects=objects)
    broken = read_sequence(seq).files[4]
    broken.write_bytes(broken.read_bytes()[:40])
    result = subprocess.run([sys.executable, "-m", "engine.cli", "eval", str(seq), "--methods", "reproject"],
                            capture_output=True, text=True, cwd=Path(__file__).resolve().parents[2], timeout=120)
    assert result.returncode == 2
    lines = result.stderr.replace("\r", "\n").splitlines()
    errors = [line for line in lines if "error:" in line]
    assert len(errors) == 1 and errors[0].startswith("interleave eval: error:") and "truncated" in errors[0]
    assert lines[-1] == errors[0]  # nothing redrawn after it
