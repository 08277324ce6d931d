"""``tools.bench_backends`` (cpu and gl side by side), ``tools.profile_gl_passes`` (GPU time per pass),
``tools.bench_gl_warp`` (the GL splats side by side), ``tools.profile_gl_flow`` (the GPU's flow alone) and
``tools.bench_torch_networks`` (the networks in torch)."""
import json

import pytest
import torch

from engine.geometry.backends.gl.splat import BINNED_PASSES, SPLAT_PASSES, SPLATS, splat_bytes
from tools import bench_backends, bench_gl_warp, bench_torch_networks, profile_gl_flow, profile_gl_passes


def _run_gl_tool(main, tmp_path, size_flag: str, repeats: str, *extra: str) -> dict:
    """A GL tool's ``main`` on the 96x64 scene (reproject and mvec, 4 frames): its JSON (skips without GL)."""
    from engine.geometry.backends import gl as glb

    if not glb.available():
        pytest.skip("no EGL context with compute shaders")
    out = tmp_path / "out.json"
    main([size_flag, "96x64", "--frames", "4", "--repeats", repeats, "--methods", "reproject,mvec",
          "--out", str(tmp_path / "scenes"), "--json", str(out), *extra])
    return json.loads(out.read_text())


def test_bench_backends_rows_parity_and_stage_split(tmp_path):
    doc = _run_gl_tool(bench_backends.main, tmp_path, "--sizes", "1")
    rows = doc["sizes"][0]["rows"]
    assert doc["sizes"][0]["size"] == [96, 64]
    assert {(r["method"], r["backend"]) for r in rows} == {(m, b) for m in ("reproject", "mvec") for b in ("cpu", "gl")}
    for r in rows:
        assert r["wall_ms"] > 0 and r["parity_within"] == 1.0 and r["parity_max_diff"] < 1e-4
        if r["backend"] == "gl":  # the GPU time split by stage
            assert {"warp", "fill", "readback"} <= set(r["gpu_stage_ms"])
        else:
            assert r["gpu_stage_ms"] == {} and r["gpu_ms"] == 0


def test_bench_backends_srgb8_encodes_on_the_gpu_and_scores_the_decoded_codes(tmp_path):
    linear = _run_gl_tool(bench_backends.main, tmp_path, "--sizes", "1")["sizes"][0]["rows"]
    doc = _run_gl_tool(bench_backends.main, tmp_path, "--sizes", "1", "--encoding", "srgb8")
    assert doc["encoding"] == "srgb8"
    for r, plain in zip(doc["sizes"][0]["rows"], linear):
        assert (r["method"], r["backend"]) == (plain["method"], plain["backend"])
        assert r["parity_max_diff"] <= 1 and r["parity_within"] >= 0.999  # codes of colours within 1e-4
        assert abs(r["psnr"] - plain["psnr"]) < 0.05  # 8-bit quantisation only
        assert ("encode" in r["gpu_stage_ms"]) == (r["backend"] == "gl")


def test_profile_counts_every_pass_of_a_frame(tmp_path):
    from engine.geometry.backends import gl as glb

    doc = _run_gl_tool(profile_gl_passes.main, tmp_path, "--size", "2")
    passes = doc["methods"]["reproject"]["passes"]
    # per predicted frame: the binned splat's five passes and the fill's three, and nothing cleared
    assert set(passes) == set(BINNED_PASSES) | {"fill_rows", "fill_links", "fill_apply"}
    for calls, ms in passes.values():
        assert calls == 1.0 and ms >= 0.0
    assert "motion_extrapolate" in doc["methods"]["mvec"]["passes"]
    # stage timing works again afterwards (pass timing turned the stage queries off only while it ran)
    gl = glb.shared_context()
    stages: dict = {}
    pool: dict = {}

    def staged():
        with gl.timing(stages), gl.gpu_stage("probe"):
            gl.clear_words(gl.buffer(pool, "probe", 64), 64)
    gl.call(staged)
    gl.release_pool(pool)
    assert "probe" in stages


def test_bench_gl_warp_runs_both_splats_at_each_size_with_the_same_bits(tmp_path):
    from engine.geometry.backends import gl as glb

    if not glb.available():
        pytest.skip("no EGL context with compute shaders")
    out = tmp_path / "warp.json"
    bench_gl_warp.main(["--sizes", "96x64,120x90", "--frames", "4", "--repeats", "1", "--out",
                        str(tmp_path / "scenes"), "--json", str(out)])
    doc = json.loads(out.read_text())
    runs = {(tuple(r["size"]), r["case"], r["splat"]): r for r in doc["runs"]}
    assert set(runs) == {(size, case, splat) for size in ((96, 64), (120, 90)) for case in bench_gl_warp.CASES
                         for splat in SPLATS}
    for (size, _, splat), r in runs.items():
        assert r["max_diff_from_atomic"] == 0.0 and r["wall_ms"] > 0 and r["splat_wall_ms"] > 0
        names = BINNED_PASSES if splat == "binned" else SPLAT_PASSES + ("splat_resolve",)
        assert set(names) | {"fill_rows", "fill_links", "fill_apply"} <= set(r["passes"])
        bins = (size[0] + 2) * (size[1] + 2)
        assert r["work_bytes"] == splat_bytes(splat, bins, size[0] * size[1])
        assert ("warp" in r["gpu_stage_ms"]) and ("fill" in r["gpu_stage_ms"])


def test_resampled_frame_keeps_its_pixels_and_scales_its_camera():
    """tools.bench_gl_warp's other sizes: nearest-pixel resampling, intrinsics and flow scaled with the size."""
    from types import SimpleNamespace

    import numpy as np

    rng = np.random.default_rng(0)
    h, w = 6, 8
    frame = SimpleNamespace(color=rng.random((h, w, 3), np.float32), depth=rng.random((h, w), np.float32) + 1,
                            object_flow=rng.random((h, w, 2), np.float32),
                            camera=SimpleNamespace(intrinsics=np.array([[10.0, 0, 4], [0, 10.0, 3], [0, 0, 1]])))
    color, depth, flow, k = bench_gl_warp.resampled(frame, (w, h))
    assert np.array_equal(color, frame.color) and np.array_equal(depth, frame.depth)
    assert np.array_equal(flow, frame.object_flow) and np.array_equal(k, frame.camera.intrinsics)
    color, depth, flow, k = bench_gl_warp.resampled(frame, (2 * w, 3 * h))
    assert color.shape == (3 * h, 2 * w, 3) and np.array_equal(depth[::3, ::2], frame.depth)
    assert np.array_equal(color[1::3, 1::2], frame.color)
    assert np.allclose(flow[::3, ::2], frame.object_flow * [2, 3])
    assert np.allclose(k, [[20.0, 0, 8], [0, 30.0, 9], [0, 0, 1]])


def test_profile_gl_flow_times_configurations_and_counts_their_dispatches(tmp_path):
    from engine.geometry.backends import gl as glb
    from engine.geometry.backends.gl.flow import GlFlowConfig, dispatch_counts

    if not glb.available():
        pytest.skip("no EGL context with compute shaders")
    out = tmp_path / "flow.json"
    profile_gl_flow.main(["--sizes", "96x64", "--frames", "4", "--repeats", "1", "--out", str(tmp_path / "scenes"),
                          "--configs", "search=thread,sor=passes,coarse_pixels=0;search=group;"
                          "search=thread,sor=tile,coarse_pixels=8192", "--passes", "--json", str(out)])
    doc = json.loads(out.read_text())
    rows = doc["rows"]
    assert [(r["search"], r["sor"], r["coarse_pixels"]) for r in rows] == [
        ("thread", "passes", 0), ("group", "passes" if not doc["hardware"] else "tile", 0 if not doc["hardware"]
                                  else 8192), ("thread", "tile", 8192)]
    assert all(r["pairs"] == 1 and r["wall_ms"] > 0 for r in rows)
    assert rows[0]["diff_px"]["max"] == 0.0  # the first configuration against itself
    assert rows[1]["diff_px"]["median"] < 1e-2  # the same search, sums in another order
    assert rows[2]["diff_px"]["median"] < 1e-2  # the same arithmetic in fewer dispatches
    for row in rows:  # the dispatches counted are those run
        config = GlFlowConfig(search=row["search"], sor=row["sor"], coarse_pixels=row["coarse_pixels"])
        assert row["dispatches"] == dispatch_counts((64, 96), config)
        assert {name: calls for name, (calls, ms) in row["passes"].items()} == row["dispatches"]
        assert all(ms >= 0 for _, ms in row["passes"].values())
    assert sum(rows[2]["dispatches"].values()) < sum(rows[0]["dispatches"].values()) / 10
    if doc["hardware"]:
        assert {"luma", "pyramid", "search", "readback"} <= set(rows[1]["gpu_ms"])
    else:
        assert rows[1]["gpu_ms"] is None
    for bad in (["--configs", "search=auto,warp=1"], ["--configs", "sor=red"], ["--k", "0"], ["--idle", "-1"]):
        with pytest.raises(SystemExit, match="error"):
            profile_gl_flow.main(bad)


@pytest.mark.parametrize("text", ["", "640", "640x", "0x360", "axb", "640x360x2"])
def test_bad_sizes_are_one_line_errors(text):
    with pytest.raises(SystemExit, match="error: "):
        bench_backends.parse_sizes(text)
    assert bench_backends.parse_sizes(" 640x360, 1920X1080 ") == [(640, 360), (1920, 1080)]


def test_bench_torch_networks_on_the_cpu(tmp_path):
    out = tmp_path / "nets.json"
    bench_torch_networks.main(["--devices", "cpu", "--repeats", "1", "--json", str(out)])
    rows = json.loads(out.read_text())["rows"]
    assert [r["network"] for r in rows] == ["corrflow", "flow3d", "infill"]
    assert all(r["device"] == "cpu" and r["ms"] > 0 and r["max_diff_from_cpu"] == 0 for r in rows)
    module, inputs, (h, w) = bench_torch_networks.networks()["corrflow"]
    assert (h, w) == (216, 384) and inputs[0].shape[-2:] == (h, w)
    ms, result = bench_torch_networks.time_calls(module, inputs, "cpu", 1)
    with torch.no_grad():
        torch.testing.assert_close(result, module(*inputs))
    assert result.shape == (1, 2, h, w)


def test_bench_torch_networks_refuses_cuda_without_a_gpu():
    if torch.cuda.is_available():
        pytest.skip("a CUDA device is here")
    with pytest.raises(SystemExit, match="no CUDA device"):
        bench_torch_networks.main(["--devices", "cuda"])
