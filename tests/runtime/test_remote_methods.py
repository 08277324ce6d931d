"""Issue 41, item 1: a client of `interleave serve` names no file through a method's options.

``check_remote_method`` refuses by allow-list: of each registered method's options (read from its config,
``engine.predict.registry.method_options``), only those whose values cannot name a file pass. Each option
that can (free text: decomp's ``model`` and ``infill_model``, flow2d's ``network``, and any added later) is
sent alone and beside every choice of every closed-choice option (``flow2d[estimator=corr,network=...]``
is the combination that reached onnxruntime): each is refused with BAD_INPUT naming the option, and neither
onnxruntime nor Python opens the planted file. The options that name no file still work.
"""
from __future__ import annotations

import sys
import threading
import typing

import numpy as np
import onnxruntime
import pytest

from engine.core.config import parse_value
from engine.predict.decomp.predictor import DecompConfig
from engine.predict.mvec import MvecConfig
from engine.predict.registry import METHODS, Flow2DOptions, make_predictor, method_options, names_no_file
from engine.runtime.client import Client, ServerError
from engine.runtime.protocol import Status
from engine.runtime.server import Server, ServerLimits, _ProtocolError, check_remote_method
from engine.runtime.session import SessionConfig

W, H = 32, 24
PLANTED = "m.onnx"  # relative: the server's working directory is the test's tmp_path
_OPENED: list[str] = []
_ARMED = threading.Event()


def _audit(event: str, args: tuple) -> None:
    if _ARMED.is_set() and event == "open" and PLANTED in str(args[0]):
        _OPENED.append(str(args[0]))


sys.addaudithook(_audit)


@pytest.fixture
def watched(tmp_path, monkeypatch):
    """A planted file in the working directory; every onnxruntime session made, and every Python open of the
    planted file, is recorded (the list returned)."""
    (tmp_path / PLANTED).write_bytes(b"not a network")
    monkeypatch.chdir(tmp_path)

    def recording_session(path, *args, **kwargs):
        _OPENED.append(str(path))
        raise RuntimeError(f"the test's onnxruntime refuses {path}")

    monkeypatch.setattr(onnxruntime, "InferenceSession", recording_session)
    _OPENED.clear()
    _ARMED.set()
    yield _OPENED
    _ARMED.clear()


@pytest.fixture
def server(tmp_path):
    srv = Server(tmp_path / "s.sock", ServerLimits())
    thread = threading.Thread(target=srv.serve_forever, daemon=True)
    thread.start()
    yield f"unix:{tmp_path / 's.sock'}"
    srv.stop()
    thread.join(timeout=10)


def file_options() -> list[tuple[str, str]]:
    """(method, option) of every option of a registered method whose values can name a file."""
    return [(base, name) for base in METHODS for name, kind in method_options(base).items()
            if not names_no_file(kind)]


def choices(base: str) -> list[str]:
    """``key=choice`` for every choice of every closed-choice (Literal) option of ``base``."""
    return [f"{name}={value}" for name, kind in method_options(base).items()
            if typing.get_origin(kind) is typing.Literal for value in typing.get_args(kind)]


def test_the_registry_has_file_options_and_the_recorder_sees_them_opened(watched):
    """The test is not vacuous: flow2d's network and decomp's model are free text, and in-process (where
    the caller may name files) the registry does hand the planted file to onnxruntime."""
    assert {("flow2d", "network"), ("decomp", "model"), ("decomp", "infill_model")} <= set(file_options())
    with pytest.raises(Exception):
        make_predictor(f"flow2d[estimator=corr,network={PLANTED}]")
    assert watched and watched[-1].endswith(PLANTED)


@pytest.mark.parametrize("base, name", file_options())
def test_every_file_naming_option_is_refused_over_the_wire_and_no_file_is_opened(base, name, watched, server):
    with Client(server) as client:
        for extra in [None] + choices(base):
            method = f"{base}[{'' if extra is None else extra + ','}{name}={PLANTED}]"
            with pytest.raises(ServerError) as info:
                client.hello(SessionConfig(engine="opencv", width=W, height=H, method=method))
            assert info.value.status == Status.BAD_INPUT, method
            assert f"option '{name}' of {base} names a file" in info.value.text, (method, info.value.text)
            assert "\n" not in info.value.text
        client.hello(SessionConfig(engine="opencv", width=W, height=H))  # the connection still serves
    assert watched == []


def _default_text(base: str, name: str) -> str:
    """The default of option ``name`` of ``base`` written as text."""
    if name == "motion":
        return "predicted"
    config = {"mvec": MvecConfig(), "flow2d": Flow2DOptions()}.get(base, DecompConfig())
    value = config
    for part in name.split("."):
        value = getattr(value, part)
    return str(value).lower() if isinstance(value, bool) else str(value)


@pytest.mark.parametrize("base", [b for b in METHODS if method_options(b)])
def test_the_options_that_name_no_file_pass_and_build_the_method(base):
    kinds = method_options(base)
    free = [name for name, kind in kinds.items() if names_no_file(kind)]
    assert free
    method = f"{base}[{','.join(f'{name}={_default_text(base, name)}' for name in free)}]"
    check_remote_method(method, ServerLimits())
    for name in free:  # each value is read as the registry reads it
        parse_value(kinds[name], _default_text(base, name), name)
    assert make_predictor(method).name == base


@pytest.mark.parametrize("method", ["flow2d[preset=fast,estimator=dis]", "mvec[undilate=true,depth_band=2]",
                                    "decomp[fill=infill,gate.tile=16]", "decomp2d[motion=predicted]"])
def test_file_free_options_open_a_session_over_the_wire(method, server):
    color = np.full((H, W, 3), 0.5, np.float32)
    depth = np.full((H, W), 2.0, np.float32)
    k = np.array([[30.0, 0, W / 2], [0, 30.0, H / 2], [0, 0, 1]])
    with Client(server) as client:
        client.hello(SessionConfig(engine="opencv", width=W, height=H, method=method))
        client.submit(color, depth, np.eye(4), k, 0.0)
        out = client.predict(np.eye(4), k, 1 / 60)
        assert np.isfinite(out.color).all()


@pytest.mark.parametrize("method, match", [
    ("flow2d[estimator=raft]", "must be one of dis, gl, corr"),
    ("flow2d[bogus=1]", "'bogus' is not an option of flow2d"),
    ("reproject[network=x]", "reproject; a client may give no options"),
    ("decomp[threads=64]", "exceeds the server's limit"),
    ("decomp[gate.tile=big]", "gate.tile"),
    ("flow2d[estimator=corr][network=x]", "estimator"),  # brackets inside brackets are one bad value
])
def test_other_bad_options_are_refused_before_a_session_is_made(method, match):
    with pytest.raises(_ProtocolError, match=match) as info:
        check_remote_method(method, ServerLimits())
    assert info.value.status == Status.BAD_INPUT


def test_a_name_that_is_no_method_is_left_to_the_registry():
    check_remote_method("nosuch[model=/etc/shadow]", ServerLimits())  # names no file: nothing reads it
    with pytest.raises(Exception, match="unknown method"):
        make_predictor("nosuch[model=/etc/shadow]")
