"""`interleave play` on the gl path (demos/play.py: ``GlDisplay``, the live renderer, textures): frames drawn from
GPU textures, nothing read back per shown frame, the same pictures as the host path. On llvmpipe here."""
from __future__ import annotations

import json

import moderngl
import numpy as np
import pytest

from demos.play import GlDisplay, LiveSceneSource, PlayConfig, Player, SceneSource, compose, make_source
from engine.cli import main
from engine.core.errors import InputError
from engine.geometry.backends import gl as glb
from engine.geometry.encoding import decode8, encode8

if not glb.available():
    pytest.skip("no EGL context with compute shaders", allow_module_level=True)

SMALL = dict(width=96, height=64, loop=24, backend="gl")


@pytest.fixture
def readbacks(monkeypatch):
    """Every GPU -> host read of moderngl (buffers, textures, framebuffers), counted: a list of their names."""
    calls: list[str] = []
    for cls, name in ((moderngl.Buffer, "read"), (moderngl.Buffer, "read_into"), (moderngl.Texture, "read"),
                      (moderngl.Texture, "read_into"), (moderngl.Framebuffer, "read"),
                      (moderngl.Framebuffer, "read_into")):
        def spy(self, *args, _fn=getattr(cls, name), _label=f"{cls.__name__}.{name}", **kwargs):
            calls.append(_label)
            return _fn(self, *args, **kwargs)
        monkeypatch.setattr(cls, name, spy)
    return calls


@pytest.mark.parametrize("k", [2, 3])
def test_the_gl_path_reads_back_no_shown_frame(readbacks, k):
    """Headless on gl with the live renderer: a generated tick reads nothing back; a rendered tick reads back only
    the depth and the motion vectors mvec's preparation needs on the CPU (two buffers), never its colour, and the
    display is never read."""
    with Player(PlayConfig(**SMALL, k=k, method="mvec")) as player:
        assert isinstance(player.source, LiveSceneSource) and player.display is not None
        per_tick = []
        for _ in range(3 * k + 1):
            before = len(readbacks)
            player.step()
            per_tick.append((player.last_rendered, readbacks[before:]))
        assert player.loop.prepared.predictor.name == "mvec" and player.generated >= 2 * (k - 1)
    for rendered, reads in per_tick:
        assert reads == (["Buffer.read_into"] * 2 if rendered else []), (rendered, reads)


def test_the_gl_path_shows_what_the_host_path_composes():
    """The display's image (read back here, as a recording does) is the host composition of the texture it was
    drawn from, and a rendered tick's texture holds the ground-truth renderer's frame as display codes."""
    size = {**SMALL, "height": 128}  # room below the overlay's four lines
    truth = SceneSource(PlayConfig(**{**size, "backend": "cpu"}))
    try:
        with Player(PlayConfig(**size, k=2, method="mvec")) as player:
            for _ in range(4):
                image = player.tick()
                codes = player.last_texture.read()
                body = slice(70, None)  # below the overlay
                np.testing.assert_array_equal(image[body], compose(decode8(codes))[body])
                want = encode8(truth.renderer.render_frame(player.tick_index - 1).color)
                if player.last_rendered:  # live == ground truth (tests/scenegen/test_live.py)
                    assert np.abs(codes.astype(int) - want.astype(int)).max() <= 1
                else:  # the generated frame is the frame of that tick, not another
                    assert 10 * np.log10(255.0 ** 2 / np.mean((codes.astype(float) - want) ** 2)) > 20
    finally:
        truth.release()


def test_the_overlay_blended_on_the_gpu_is_the_hosts():
    """``overlay_canvas`` blended by ``GlDisplay`` gives what ``compose`` draws, within 2 codes (the host darkens
    the box by truncation, the GPU rounds)."""
    from engine.geometry.backends.gl.texture import TextureRing

    color = np.random.default_rng(5).random((64, 96, 3)).astype(np.float32)
    lines = ["mvec on gl, k=2: tick 3 generated", "rendered 30.0 fps (33.3 ms)"]
    ring, display = TextureRing(), GlDisplay()
    try:
        display.show(ring.upload(color, "srgb8"), lines)
        got = display.read()
    finally:
        ring.release_all()
        display.release()
    want = compose(color, lines)
    assert np.abs(got.astype(int) - want.astype(int)).max() <= 2
    assert not np.array_equal(want, compose(color))  # the overlay is there


def test_keys_split_view_and_other_methods_on_the_gl_path():
    """M to methods that need the colour on the host (flow2d: DIS on the CPU) reads the kept frames' colour back
    once; S gives the split view (compared on the host)."""
    with Player(PlayConfig(**SMALL, k=2)) as player:
        for _ in range(3):
            player.step()
        player.press("m")  # mvec -> decomp
        player.press("m")  # -> reproject
        player.press("m")  # -> flow2d
        assert player.method == "flow2d" and all(f.color is not None for f in player._rendered)
        for _ in range(3):
            assert player.tick().shape == (64, 96, 3)
        player.press("s")
        assert player.tick().shape == (64, 3 * 96, 3) and player.last_truth is not None


def test_headless_command_writes_the_summary_as_json(tmp_path, capsys):
    path = tmp_path / "play.json"
    assert main(["play", "--headless", "--frames", "6", "--width", "96", "--height", "64", "--loop", "24",
                 "--backend", "gl", "--method", "mvec", "--json", str(path)]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and out[0].startswith("played 6 frames (96x64): 3 rendered at ")
    assert out[0].endswith("renderer live; frames drawn from GPU textures")
    summary = json.loads(path.read_text())
    assert summary["renderer"] == "live" and summary["gpu_display"] and summary["rendered"] == 3
    assert summary["rendered_fps"] > 0 and summary["generated_fps"] > 0
    assert {"render", "readout", "warp", "fill"} <= set(summary["gpu_ms"])
    for bad, word in ((["--headless", "--record", str(tmp_path / "x.mp4")], "headless plays without a recording"),
                      (["--renderer", "live", "--field", str(tmp_path)], "live renderer draws the built-in scene")):
        assert main(["play", "--frames", "2", *bad]) == 2
        err = capsys.readouterr().err
        assert err.startswith("interleave play: error:") and word in err and len(err.strip().splitlines()) == 1


def test_renderer_choice():
    assert isinstance(make_source(PlayConfig(**{**SMALL, "backend": "cpu"})), SceneSource)  # auto on cpu: truth
    with pytest.raises(InputError, match="supersample must be 1"):
        make_source(PlayConfig(**SMALL, renderer="live", supersample=2))
    source = make_source(PlayConfig(**SMALL, supersample=2))  # auto: the live renderer draws one sample a pixel
    assert not source.live
    source.release()
    display = GlDisplay()
    with pytest.raises(Exception, match="no frame yet"):
        display.read()
    display.release()
