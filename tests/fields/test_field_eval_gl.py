"""``evaluate_field`` / ``evaluate_dynamic`` with the GL renderer: the scores torch (the oracle) gives.

Tolerances (measured here on llvmpipe in brackets): score PSNR within 0.01 dB of torch's (static sphere
2.5e-5 dB); each view's colour at >= 60 dB PSNR against torch's frame (84-99 dB). What separates the two
is the real-time renderer's early ray termination and colour skip (``engine.fields.gl``, each bounded by
1e-4 .. 6e-4 per pixel) and float32 rounding of the sample positions at occupancy-cell borders.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from engine.core.colorspace import display_encode
from engine.core.errors import InputError
from engine.eval.metrics import psnr
from engine.fields import gl as glfield
from models.fields import trainer
from models.fields.train_dynamic import evaluate_dynamic
from models.fields.train_static import evaluate_field
from tests.fields.test_dynamic_field import derf_run, moving  # noqa: F401  (module fixtures)
from tests.fields.test_field_train import trained  # noqa: F401  (module fixture: a tiny trained sphere)

pytestmark = pytest.mark.usefixtures("one_torch_thread")

needs_gl = pytest.mark.skipif(not glfield.available(), reason="no EGL context with OpenGL 4.3 compute shaders")


def _frames_agree(a: list[dict], b: list[dict]) -> list[float]:
    return [psnr(display_encode(x["color"]), display_encode(y["color"])) for x, y in zip(a, b)]


@needs_gl
def test_static_field_scores_on_gl_as_on_torch(trained):  # noqa: F811
    _, test, run = trained
    oracle = evaluate_field(run, test, with_flip=False, return_images=True, renderer="torch")
    fast = evaluate_field(run, test, with_flip=False, return_images=True, renderer="gl")
    assert oracle["renderer"] == "torch" and fast["renderer"] == "gl"
    assert fast["psnr"] == pytest.approx(oracle["psnr"], abs=0.01)
    assert fast["ssim"] == pytest.approx(oracle["ssim"], abs=1e-3)
    assert fast["depth_mae"] == pytest.approx(oracle["depth_mae"], abs=1e-2)
    assert min(_frames_agree(oracle["images"], fast["images"])) >= 60.0
    for a, b in zip(oracle["images"], fast["images"]):  # the same pixels have a surface
        assert np.mean(np.isfinite(a["depth"]) == np.isfinite(b["depth"])) >= 0.999


@needs_gl
def test_dynamic_field_scores_on_gl_as_on_torch(derf_run, moving):  # noqa: F811
    train, test = moving
    oracle = evaluate_dynamic(derf_run, test, with_flip=False, return_images=True, context_views=train)
    fast = evaluate_dynamic(derf_run, test, with_flip=False, return_images=True, context_views=train,
                            renderer="gl")
    assert fast["renderer"] == "gl" and fast["psnr"] == pytest.approx(oracle["psnr"], abs=0.01)
    assert min(_frames_agree(oracle["images"], fast["images"])) >= 60.0
    assert [p["psnr"] for p in fast["per_time"]] == pytest.approx([p["psnr"] for p in oracle["per_time"]], abs=0.01)
    # the motion diagnostics come from a quarter-resolution torch render: the same statistics, subsampled
    assert set(fast) == set(oracle)
    assert fast["flow_moving_fraction"] == pytest.approx(oracle["flow_moving_fraction"], abs=0.05)
    assert sum(fast["flow_histogram"]["samples"]) < sum(oracle["flow_histogram"]["samples"])


def test_renderer_names_resolve(monkeypatch):
    with pytest.raises(InputError, match="renderer"):
        trainer.resolve_renderer("vulkan")
    assert trainer.resolve_renderer("torch") == "torch"
    monkeypatch.setattr(glfield, "available", lambda: False)
    assert trainer.resolve_renderer("auto") == "torch"
    with pytest.raises(InputError, match="--renderer torch"):
        trainer.resolve_renderer("gl")
    monkeypatch.setattr(glfield, "available", lambda: True)
    assert trainer.resolve_renderer("auto") == "gl"


@needs_gl
def test_eval_command_takes_the_renderer(tmp_path, capsys):
    from engine.cli import main
    from tests.fields.test_field_train import sphere_views, write_blender

    write_blender(tmp_path / "scene", sphere_views([0, 40, 80]), "train")
    write_blender(tmp_path / "scene", sphere_views([20, 60]), "test")
    run = tmp_path / "run"
    assert main(["train", "field", "--dataset", "nerf-synthetic", "--data", str(tmp_path / "scene"), "--out",
                 str(run), "--views", "3", "--steps", "30", "--rays-per-batch", "128", "--field.resolutions", "8,16",
                 "--render.num-samples", "24", "--no-flip"]) == 0
    assert json.loads((run / "scores.json").read_text())["renderer"] == "gl"  # the default, where GL exists
    scores = {}
    for name in ("torch", "gl"):
        assert main(["eval", "field", str(run), "--renderer", name, "--no-flip",
                     "--json", str(tmp_path / f"{name}.json")]) == 0
        scores[name] = json.loads((tmp_path / f"{name}.json").read_text())
        assert scores[name]["renderer"] == name
    assert scores["gl"]["psnr"] == pytest.approx(scores["torch"]["psnr"], abs=0.01)
    capsys.readouterr()
    with pytest.raises(SystemExit) as bad:
        main(["eval", "field", str(run), "--renderer", "vulkan"])
    assert bad.value.code == 2 and "--renderer" in capsys.readouterr().err
