"""Tests of `interleave serve` (engine/runtime/server.py), its wire format (engine/runtime/protocol.py, the C header) and
the reference client (engine/runtime/client.py).

The server always runs in its own process (``python -m engine.cli serve``); the tests are its clients:
this process through ``engine.runtime.client.Client`` or raw bytes, a ``python -m engine.runtime.client`` process, and
the C example client compiled from ``engine/runtime/include``. Checked: the header's constants and struct layout
against Python, predictions identical to an in-process Session, request ordering under pipelining,
RESET and size changes, every malformed-message class (error reply, server keeps serving), a client
vanishing mid-message, 10 000 frames without memory growth, and shutdown removing every segment; protocol
version 2's motion-vector plane (vectors arrive converted, at lower resolution too; bad vectors are errors)
and version-1 clients answered as before.
"""
from __future__ import annotations

import math
import os
import re
import shutil
import signal
import socket
import stat
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from engine.core.errors import InputError
from engine.runtime import protocol as wire
from engine.runtime.client import Client, ServerError, _attach
from engine.runtime.protocol import Layout, MessageType, MotionPlane, Status
from engine.runtime.session import Session, SessionConfig

ROOT = Path(__file__).resolve().parents[2]
INCLUDE = ROOT / "engine" / "runtime" / "include"
SHM = Path("/dev/shm")
CC = shutil.which("cc") or shutil.which("gcc")

pytestmark = pytest.mark.skipif(not SHM.is_dir() or not hasattr(socket, "AF_UNIX"),
                                reason="needs POSIX shared memory in /dev/shm and Unix sockets")

W, H = 64, 48
K = np.array([[50.0, 0.0, W / 2], [0.0, 50.0, H / 2], [0.0, 0.0, 1.0]])


def start_server(listen: str, log: Path, *options: str) -> tuple[subprocess.Popen, str]:
    """Start `interleave serve` in its own process; returns it and the address it announced."""
    proc = subprocess.Popen([sys.executable, "-m", "engine.cli", "serve", "--listen", listen, *options], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=log.open("w"), text=True)
    line = proc.stdout.readline()
    if "listening on" not in line:
        proc.kill()
        raise RuntimeError(f"server did not start: {line!r} {log.read_text()}")
    return proc, line.split("listening on ", 1)[1].strip()


def stop_server(proc: subprocess.Popen) -> int:
    proc.send_signal(signal.SIGTERM)
    return proc.wait(timeout=15)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("serve")
    proc, address = start_server(f"unix:{tmp / 'interleave.sock'}", tmp / "server.log")
    yield proc, address
    stop_server(proc)


def assert_serves(proc: subprocess.Popen, address: str) -> None:
    """The server process is alive and a new client gets predictions."""
    assert proc.poll() is None
    with Client(address) as client:
        client.hello(config())
        client.submit(*frame_arrays(), pose(), K, 0.0)
        assert client.predict(pose(0.01), K, 0.05).method == "reproject"


def segment_exists(name: str) -> bool:
    assert name.startswith("/"), name  # a named segment's layout
    return (SHM / name.lstrip("/")).exists()


def server_segments(pid: int) -> list[str]:
    """The named segments of server ``pid`` in /dev/shm."""
    return sorted(p.name for p in SHM.iterdir() if p.name.startswith(f"interleave-{pid}-"))


def wait_until(condition, timeout=5.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.02)
    return condition()


def pose(x=0.0):
    p = np.eye(4)
    p[0, 3] = -x
    return p


def frame_arrays(seed=0, size=(H, W), channels=3):
    rng = np.random.default_rng(seed)
    color = rng.uniform(0.05, 0.95, size + (channels,)).astype(np.float32)
    depth = np.broadcast_to(np.linspace(2.0, 5.0, size[0], dtype=np.float32)[:, None], size).copy()
    return color, depth


def config(**overrides) -> SessionConfig:
    return SessionConfig(**{"engine": "opencv", "width": W, "height": H, **overrides})


def raw_connect(address: str) -> socket.socket:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(10)
    sock.connect(address.removeprefix("unix:"))
    return sock


def read_reply(sock: socket.socket, version=None):
    """(type, request_id, status, payload) of the next reply, or None when the server closed the connection;
    ``version``: the protocol version the reply must carry (else any the server speaks)."""
    data = b""
    while len(data) < wire.HEADER.size:
        chunk = sock.recv(wire.HEADER.size - len(data))
        if not chunk:
            return None
        data += chunk
    magic, got_version, type_, request_id, status, size = wire.HEADER.unpack(data)
    assert magic == wire.MAGIC and got_version in wire.VERSIONS
    assert version is None or got_version == version
    payload = b""
    while len(payload) < size:
        payload += sock.recv(size - len(payload))
    return type_, request_id, status, payload


def closed(sock: socket.socket) -> bool:
    try:
        return sock.recv(1) == b""
    except ConnectionResetError:
        return True


def frame_payload(frame_id=0, time_s=0.0, view=None, projection=None) -> bytes:
    view = np.eye(4) if view is None else view
    projection = np.pad(K, ((0, 1), (0, 1))) if projection is None else projection
    return wire.FRAME.pack(frame_id, time_s, *np.ravel(view), *np.ravel(projection))


# --------------------------------------------------------------------------------------------
# The C header states the same protocol
# --------------------------------------------------------------------------------------------

HEADER_TEXT = (INCLUDE / "interleave_protocol.h").read_text()

#: C struct -> (Python struct, [(field, element count)] in declaration order)
C_STRUCTS = {
    "il_header": (wire.HEADER, [("magic", 1), ("version", 1), ("type", 1), ("request_id", 1), ("status", 1),
                                ("payload_size", 1)]),
    "il_hello": (wire.HELLO, [(n, 1) for n in ("engine", "depth_convention", "color_in", "color_out", "width",
                                              "height", "reserved0", "channels", "flags", "reserved", "near_plane",
                                              "far_plane", "meters_per_unit", "cut_translation",
                                              "cut_rotation_deg")] + [("method", 1)]),
    "il_layout": (wire.LAYOUT, [("shm_name", 1), ("shm_size", 1), ("color_in_offset", 1), ("depth_offset", 1),
                                ("color_out_offset", 1), ("holes_offset", 1), ("width", 1), ("height", 1)]),
    "il_frame": (wire.FRAME, [("frame_id", 1), ("time", 1), ("view", 16), ("projection", 16)]),
    "il_submit_reply": (wire.SUBMIT_REPLY, [("frame", 1), ("reset", 1), ("history", 1)]),
    "il_predict_reply": (wire.PREDICT_REPLY, [("frame", 1), ("fallback", 1), ("holes", 1), ("elapsed_ms", 1),
                                              ("method", 1)]),
    "il_reset": (wire.RESET, [("width", 1), ("height", 1)]),
    "il_motion": (wire.MOTION, [(n, 1) for n in ("units", "direction", "y_axis", "camera", "missing", "width",
                                                 "height", "channels", "format", "reserved", "scale_x", "scale_y")]),
    "il_submit_motion": (wire.SUBMIT_MOTION, [("flags", 1), ("reserved", 1)]),
    "il_reset_motion": (wire.RESET_MOTION, [("width", 1), ("height", 1)]),
    "il_motion_layout": (wire.MOTION_LAYOUT, [("motion_offset", 1), ("motion_valid_offset", 1), ("width", 1),
                                              ("height", 1)]),
}
#: Version-2 payloads: a version-1 struct followed by its motion extension (C struct -> (first, second)).
C_PAIRS = {"il_hello_with_motion": ("il_hello", "il_motion"), "il_submit_with_motion": ("il_frame", "il_submit_motion"),
           "il_reset_with_motion": ("il_reset", "il_reset_motion"),
           "il_layout_with_motion": ("il_layout", "il_motion_layout")}


def python_offsets(layout: struct.Struct) -> list[int]:
    """Byte offset of every element of a little-endian struct format ('16d' is 16 elements, '64s' one)."""
    offsets, offset = [], 0
    for count, code in re.findall(r"(\d*)([a-zA-Z?])", layout.format.lstrip("<")):
        n = int(count or 1)
        size = struct.calcsize("<" + code)
        if code == "s":
            offsets.append(offset)
            offset += n
        else:
            offsets.extend(offset + i * size for i in range(n))
            offset += n * size
    assert offset == layout.size
    return offsets


def header_defines() -> dict[str, int]:
    return {name: int(value, 0) for name, value in
            re.findall(r"^#define IL_(\w+) (0x[0-9A-Fa-f]+|\d+)u?\b", HEADER_TEXT, flags=re.MULTILINE)}


def test_header_constants_match_python():
    d = header_defines()
    assert (d["MAGIC"], d["VERSION"], d["VERSION_MIN"], d["MAX_PAYLOAD"], d["MAX_SIDE"], d["ALIGNMENT"]) == (
        wire.MAGIC, wire.VERSION, wire.VERSION_MIN, wire.MAX_PAYLOAD, wire.MAX_SIDE, wire.ALIGNMENT)
    assert wire.VERSIONS == tuple(range(wire.VERSION_MIN, wire.VERSION + 1))
    assert d["VERSION_FD"] == wire.VERSION_FD
    assert struct.pack("<I", wire.MAGIC) == b"INTL"
    assert {t.name: int(t) for t in MessageType} == {k[4:]: v for k, v in d.items() if k.startswith("MSG_")}
    assert {k: v for k, v in d.items() if k in Status.__members__} == {s.name: int(s) for s in Status}
    for prefix, codes in (("ENGINE_", wire.ENGINE_CODES), ("DEPTH_", wire.DEPTH_CODES), ("COLOR_", wire.COLOR_CODES),
                          ("RESET_", wire.RESET_CODES), ("FALLBACK_", wire.FALLBACK_CODES)):
        names = [(c or "none").upper() for c in codes]
        assert {k[len(prefix):]: v for k, v in d.items() if k.startswith(prefix)} == {n: i for i, n in enumerate(names)}
    assert (d["FLAG_FLIP_ROWS"], d["FLAG_NDC_Y_DOWN"], d["FLAG_COLUMN_MAJOR"]) == (
        wire.FLAG_FLIP_ROWS, wire.FLAG_NDC_Y_DOWN, wire.FLAG_COLUMN_MAJOR)
    motion_codes = {"PIXELS": wire.MOTION_UNIT_CODES.index("pixels"), "UV": wire.MOTION_UNIT_CODES.index("uv"),
                    "NDC": wire.MOTION_UNIT_CODES.index("ndc"),
                    "PREVIOUS": wire.MOTION_DIRECTION_CODES.index("previous"),
                    "NEXT": wire.MOTION_DIRECTION_CODES.index("next"), "Y_DOWN": wire.MOTION_Y_CODES.index(False),
                    "Y_UP": wire.MOTION_Y_CODES.index(True), "CAMERA_INCLUDED": wire.MOTION_CAMERA_CODES.index(True),
                    "OBJECT_ONLY": wire.MOTION_CAMERA_CODES.index(False),
                    "MISSING_NONE": wire.MOTION_MISSING_CODES.index("none"),
                    "MISSING_CAMERA": wire.MOTION_MISSING_CODES.index("camera"),
                    "F32": wire.MOTION_FORMATS.index("float32"), "F16": wire.MOTION_FORMATS.index("float16")}
    assert {k[7:]: v for k, v in d.items() if k.startswith("MOTION_")} == motion_codes
    assert (d["SUBMIT_VECTORS"], d["SUBMIT_VALID"]) == (wire.SUBMIT_VECTORS, wire.SUBMIT_VALID)


def test_header_static_asserts_state_every_python_size_and_offset():
    sizes = {name: int(size) for name, size in re.findall(r"IL_ASSERT_SIZE\((\w+), (\d+)\)", HEADER_TEXT)}
    offsets = {(name, field): int(at) for name, field, at in
               re.findall(r"IL_ASSERT_OFFSET\((\w+), (\w+), (\d+)\)", HEADER_TEXT)}
    expected_offsets = {}
    for name, (layout, fields) in C_STRUCTS.items():
        assert sizes.pop(name) == layout.size, name
        python, element = python_offsets(layout), 0
        for field, count in fields:
            expected_offsets[(name, field)] = python[element]
            element += count
    for name, (first, second) in C_PAIRS.items():
        assert sizes.pop(name) == C_STRUCTS[first][0].size + C_STRUCTS[second][0].size, name
    assert sizes == {}  # no struct asserted that Python does not have
    assert offsets == expected_offsets  # every field of every struct, at Python's offset


GCC = shutil.which("gcc")


@pytest.mark.skipif(GCC is None, reason="no gcc")
@pytest.mark.parametrize("std", ["c99", "c11"])
def test_header_compiles_pedantic_and_its_asserts_refuse_a_wrong_layout(tmp_path, std):
    """C99 (typedef-array asserts) and C11 (_Static_assert) compile the header without a warning, and in both a
    size that differs from protocol.py is a compile error."""
    flags = [GCC, f"-std={std}", "-pedantic", "-Wall", "-Wextra", "-Werror", "-fsyntax-only", "-x", "c"]
    run = subprocess.run(flags + [str(INCLUDE / "interleave_protocol.h")], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    wrong = tmp_path / "wrong.h"
    text = HEADER_TEXT.replace(f"IL_ASSERT_OFFSET(il_hello, method, {python_offsets(wire.HELLO)[-1]})",
                               f"IL_ASSERT_OFFSET(il_hello, method, {python_offsets(wire.HELLO)[-1] + 8})")
    assert text != HEADER_TEXT
    wrong.write_text(text)
    run = subprocess.run(flags + [str(wrong)], capture_output=True, text=True)
    assert run.returncode != 0 and "il_hello" in run.stderr


@pytest.mark.skipif(CC is None, reason="no C compiler")
def test_header_struct_layout_matches_python_when_compiled(tmp_path):
    lines = ['#include <stdio.h>', '#include "interleave_protocol.h"', "int main(void) {"]
    for name, (_, fields) in C_STRUCTS.items():
        lines.append(f'printf("{name} size %zu\\n", sizeof({name}));')
        lines += [f'printf("{name} {f} %zu\\n", offsetof({name}, {f}));' for f, _ in fields]
    for name in C_PAIRS:
        lines.append(f'printf("{name} size %zu\\n", sizeof({name}));')
    lines += ["return 0;", "}"]
    source = tmp_path / "layout.c"
    source.write_text("\n".join(lines) + "\n")
    exe = tmp_path / "layout"
    subprocess.run([CC, "-std=c11", "-Wall", "-Werror", "-I", str(INCLUDE), str(source), "-o", str(exe)], check=True)
    printed = dict(line.rsplit(" ", 1) for line in subprocess.run([str(exe)], capture_output=True, text=True,
                                                                  check=True).stdout.splitlines())
    for name, (layout, fields) in C_STRUCTS.items():
        assert int(printed[f"{name} size"]) == layout.size
        offsets, element = python_offsets(layout), 0
        for f, count in fields:
            assert int(printed[f"{name} {f}"]) == offsets[element], (name, f)
            element += count
        assert element == len(offsets)
    for name, (first, second) in C_PAIRS.items():  # no padding between a payload and its extension
        assert int(printed[f"{name} size"]) == C_STRUCTS[first][0].size + C_STRUCTS[second][0].size


@pytest.mark.skipif(CC is None, reason="no C compiler")
def test_c_example_client_talks_to_the_server(server, tmp_path):
    exe = tmp_path / "il_example"
    subprocess.run([CC, "-std=c11", "-Wall", "-Wextra", "-Werror", "-O2", "-I", str(INCLUDE),
                    str(INCLUDE / "interleave_example.c"), "-o", str(exe), "-lrt", "-lm"], check=True)
    _, address = server
    out = subprocess.run([str(exe), address.removeprefix("unix:")], capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr
    # A 1 cm step right in front of a wall 2 m away (fx = 50) moves the red ramp by 0.25 px: 32.25 / 64. The
    # motion vectors of the second frame reached mvec (it refuses a frame without them): a static wall.
    assert re.fullmatch(r"history=2 method=mvec fallback=0 holes=\d+ centre_red=0\.5039 centre_hole=0\n",
                        out.stdout)


# --------------------------------------------------------------------------------------------
# Sessions over the socket
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("cfg, channels, column_major, version", [
    (config(method="reproject"), 3, False, wire.VERSION),  # an anonymous segment (memfd passed with the reply)
    (config(method="flow2d", color_in="srgb8", color_out="srgb8", flip_rows=True), 4, True, wire.VERSION),
    (config(method="flow2d"), 4, False, 2),  # version 2: a named segment
    (config(method="flow2d"), 4, False, 1),  # a client that speaks version 1
])
def test_predictions_over_the_socket_equal_an_in_process_session(server, cfg, channels, column_major, version):
    proc, address = server
    local = Session(cfg)
    with Client(address, version=version) as client:
        layout = client.hello(cfg, channels=channels, column_major=column_major)
        assert (layout.width, layout.height) == (W, H)
        assert layout.anonymous == (version >= wire.VERSION_FD)
        assert layout.anonymous or segment_exists(layout.shm_name)
        for i in range(7):
            color, depth = frame_arrays(i, channels=channels)
            if cfg.color_in == "srgb8":
                color = (color * 255).astype(np.uint8)
            t = i / 60
            if i % 2 == 0:
                remote_result = client.submit(color, depth, pose(0.01 * i), K, t)
                assert remote_result == local.submit(color, depth, pose(0.01 * i), K, t)
            else:
                remote = client.predict(pose(0.01 * i), K, t)
                expected = local.predict(pose(0.01 * i), K, t)
                np.testing.assert_array_equal(remote.color, expected.color)
                np.testing.assert_array_equal(remote.holes, expected.holes)
                assert (remote.method, remote.fallback, remote.frame) == (expected.method, expected.fallback,
                                                                          expected.frame)
        client.bye()
    assert layout.anonymous or wait_until(lambda: not segment_exists(layout.shm_name))


@pytest.mark.parametrize("encoding", ["linear", "srgb8"])
def test_a_gl_server_predicts_what_an_in_process_gl_session_predicts(tmp_path, encoding):
    """Also with 8-bit frames in and out, which the gl backend uploads and reads back as codes."""
    from engine.geometry.backends import gl as glb

    if not glb.available():
        pytest.skip("no EGL context with compute shaders")
    proc, address = start_server(f"unix:{tmp_path / 'gl.sock'}", tmp_path / "server.log", "--backend", "gl")
    try:
        cfg = config(method="flow2d", color_in=encoding, color_out=encoding)
        local = Session(cfg, backend="gl")
        with Client(address) as client:
            client.hello(cfg)
            for i in range(5):
                color, depth = frame_arrays(i)
                if encoding == "srgb8":
                    color = (color * 255).astype(np.uint8)
                if i % 2 == 0:
                    assert client.submit(color, depth, pose(0.01 * i), K, i / 60) == local.submit(
                        color, depth, pose(0.01 * i), K, i / 60)
                else:  # the GL splat's sums are exact fixed point: runs agree bit for bit
                    remote, expected = client.predict(pose(0.01 * i), K, i / 60), local.predict(pose(0.01 * i), K,
                                                                                               i / 60)
                    np.testing.assert_array_equal(remote.color, expected.color)
                    np.testing.assert_array_equal(remote.holes, expected.holes)
            client.bye()
    finally:
        assert stop_server(proc) == 0


def test_pipelined_requests_are_answered_in_order_with_their_ids(server):
    _, address = server
    sock = raw_connect(address)
    hello = wire.HELLO.pack(0, wire.DEPTH_CODES.index("reversed"), 0, 0, W, H, 2, 3, 0, 0, 0.1, 100.0, 0.0, 0.0,
                            0.0, b"reproject")  # zero-filled shared memory = black sky: a valid frame
    requests = [(MessageType.HELLO, 42, hello), (MessageType.SUBMIT, 7, frame_payload(0, 0.0)),
                (MessageType.PREDICT, 1000, frame_payload(1, 1 / 60)), (99, 5, b""),
                (MessageType.PREDICT, 6, frame_payload(2, 2 / 60)), (MessageType.BYE, 0xFFFFFFFF, b"")]
    sock.sendall(b"".join(wire.pack_header(t, rid, len(p)) + p for t, rid, p in requests))
    replies = [read_reply(sock) for _ in requests]
    assert [(r[0], r[1], r[2]) for r in replies] == [
        (MessageType.HELLO | MessageType.REPLY, 42, Status.OK), (MessageType.SUBMIT | MessageType.REPLY, 7, Status.OK),
        (MessageType.PREDICT | MessageType.REPLY, 1000, Status.OK), (99 | MessageType.REPLY, 5, Status.UNKNOWN_TYPE),
        (MessageType.PREDICT | MessageType.REPLY, 6, Status.OK), (MessageType.BYE | MessageType.REPLY, 0xFFFFFFFF,
                                                                  Status.OK)]
    assert wire.PREDICT_REPLY.unpack(replies[4][3])[0] == 0  # predicted from session frame 0
    assert closed(sock)
    sock.close()


def test_reset_and_resolution_change(server):
    _, address = server
    with Client(address, version=2) as client:  # named segments: the old one is unlinked
        first = client.hello(config())
        color, depth = frame_arrays()
        client.submit(color, depth, pose(), K, 0.0)
        same = client.reset()
        assert same == first
        with pytest.raises(ServerError) as info:
            client.predict(pose(), K, 0.1)
        assert info.value.status == Status.NOT_READY
        small = client.reset(width=32, height=24)
        assert small.shm_name != first.shm_name and (small.width, small.height) == (32, 24)
        assert not segment_exists(first.shm_name) and segment_exists(small.shm_name)
        k_small = K * np.array([[0.5], [0.5], [1.0]])
        client.submit(*frame_arrays(size=(24, 32)), pose(), k_small, 0.2)
        out = client.predict(pose(0.01), k_small, 0.25)
        assert out.color.shape == (24, 32, 3) and out.fallback is None
        client.bye()
    assert wait_until(lambda: not segment_exists(small.shm_name))


def test_malformed_messages_get_an_error_reply_and_the_server_keeps_serving(server):
    proc, address = server
    with Client(address) as client:
        client.hello(config())
        for type_, payload, status in ((77, b"", Status.UNKNOWN_TYPE),
                                       (MessageType.SUBMIT, b"x" * 10, Status.BAD_SIZE),
                                       (MessageType.HELLO, b"\0" * 12, Status.BAD_SIZE),
                                       (MessageType.HELLO, wire.HELLO.pack(9, *([0] * 9), *([0.0] * 5), b""),
                                        Status.BAD_INPUT)):
            with pytest.raises(ServerError) as info:
                client.request(type_, payload)
            assert info.value.status == status and info.value.text
        color, depth = frame_arrays()
        color[5, 6, 1] = np.nan
        with pytest.raises(ServerError, match=r"BAD_INPUT: frame 123, field 'color': has 1 non-finite") as info:
            client.submit(color, depth, pose(), K, 0.5, frame_id=123)
        with pytest.raises(ServerError, match=r"BAD_INPUT: frame 124, field 'view'.*non-finite"):
            client.predict(np.full((4, 4), np.nan), K, 0.5, frame_id=124)
        client.submit(*frame_arrays(), pose(), K, 0.5)  # the same connection still works
        assert client.predict(pose(), K, 0.55).fallback is None

    with Client(address) as fresh:
        with pytest.raises(ServerError) as info:
            fresh.request(MessageType.PREDICT, frame_payload())
        assert info.value.status == Status.NO_SESSION

    fatal = [(wire.HEADER.pack(0xDEADBEEF, 1, 1, 9, 0, 0), MessageType.ERROR, Status.BAD_MAGIC),
             (wire.HEADER.pack(wire.MAGIC, wire.VERSION + 1, 1, 9, 0, 0), MessageType.ERROR, Status.BAD_VERSION),
             (wire.HEADER.pack(wire.MAGIC, 0, 1, 9, 0, 0), MessageType.ERROR, Status.BAD_VERSION),
             (wire.pack_header(MessageType.SUBMIT, 9, 1 << 40), MessageType.SUBMIT | MessageType.REPLY,
              Status.TOO_LARGE),
             (wire.pack_header(MessageType.SUBMIT, 9, wire.FRAME.size) + b"\0" * 100,
              MessageType.SUBMIT | MessageType.REPLY, Status.TRUNCATED),
             (b"INTL\x01\0", MessageType.ERROR, Status.TRUNCATED)]
    for data, reply_type, status in fatal:
        sock = raw_connect(address)
        sock.sendall(data)
        sock.shutdown(socket.SHUT_WR)  # the stream ends here
        type_, _, got_status, text = read_reply(sock)
        assert (type_, got_status) == (reply_type, status), text
        assert text and closed(sock)
        sock.close()

    assert proc.poll() is None
    with Client(address) as client:  # still serving
        client.hello(config(width=16, height=16))
        client.submit(*frame_arrays(size=(16, 16)), pose(), K, 0.0)
        client.bye()


def test_a_client_vanishing_mid_frame_loses_its_session_and_segment(server):
    proc, address = server
    client = Client(address, version=2)
    layout = client.hello(config())
    client.submit(*frame_arrays(), pose(), K, 0.0)
    client.send_raw(wire.pack_header(MessageType.SUBMIT, 2, wire.FRAME.size) + frame_payload(1, 0.1)[:100])
    client.sock.close()  # gone mid-message, without BYE
    client._unmap()
    assert wait_until(lambda: not segment_exists(layout.shm_name))
    assert_serves(proc, address)


def rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError("no VmRSS")


def test_sustained_load_of_10000_frames_without_memory_growth(server):
    proc, address = server
    size, warmup, cycles = 16, 500, 5000  # each cycle: one SUBMIT and one PREDICT, 10 000 frames in all
    k = np.array([[16.0, 0.0, 8.0], [0.0, 16.0, 8.0], [0.0, 0.0, 1.0]])
    color, depth = frame_arrays(size=(size, size))
    with Client(address) as client:
        client.hello(config(width=size, height=size, method="repeat"))
        start = time.perf_counter()
        for i in range(cycles):
            if i == warmup:
                before = rss_kib(proc.pid)
            client.submit(color, depth, pose(1e-4 * i), k, i / 30)
            out = client.predict(pose(1e-4 * i), k, i / 30 + 1 / 60, copy=False)
            assert out.frame == i
        elapsed = time.perf_counter() - start
        after = rss_kib(proc.pid)
        client.bye()
    print(f"\n{2 * cycles} frames in {elapsed:.1f} s ({1e3 * elapsed / cycles:.2f} ms per SUBMIT + PREDICT); "
          f"server RSS {before} -> {after} KiB")
    assert after - before < 2048  # a leak of even 0.5 KiB per message would show as > 2 MiB


def test_reference_client_process_over_tcp_and_clean_shutdown(tmp_path):
    proc, address = start_server("tcp:0", tmp_path / "tcp.log")
    try:
        assert re.fullmatch(r"tcp:127\.0\.0\.1:\d+", address)
        run = subprocess.run([sys.executable, "-m", "engine.runtime.client", address, "--frames", "12", "--width", "32",
                              "--height", "24"], cwd=ROOT, capture_output=True, text=True, timeout=60)
        assert run.returncode == 0, run.stderr
        assert "socket: PREDICT 32x24 reproject (reproject)" in run.stdout
        # Two sessions left open at shutdown: SIGTERM must unlink both segments.
        clients = [Client(address) for _ in range(2)]
        names = [c.hello(config()).shm_name for c in clients]
        clients[0].submit(*frame_arrays(), pose(), K, 0.0)
        assert all(segment_exists(n) for n in names)
        assert stop_server(proc) == 0
        assert not any(segment_exists(n) for n in names)
        for c in clients:
            assert closed(c.sock)
            c.close()
    finally:
        if proc.poll() is None:
            proc.kill()


def test_shutdown_removes_the_socket_file_and_segments(tmp_path):
    path = tmp_path / "s.sock"
    proc, address = start_server(f"unix:{path}", tmp_path / "unix.log")
    client = Client(address, version=2)
    name = client.hello(config()).shm_name
    assert path.exists() and segment_exists(name)
    assert stop_server(proc) == 0
    assert not path.exists() and not segment_exists(name)
    assert not any(p.name.startswith(f"interleave-{proc.pid}-") for p in SHM.iterdir())
    client.close()


def test_serve_refuses_other_hosts_and_a_live_socket(server, capsys):
    from engine.cli import main

    _, address = server
    assert main(["serve", "--listen", "tcp:10.1.2.3:9000"]) == 2
    assert main(["serve", "--listen", address]) == 2
    err = capsys.readouterr().err
    assert "127.0.0.1 only" in err and "another server is listening there" in err


def _hello_fields(**change) -> bytes:
    fields = dict(engine=0, depth=5, color_in=0, color_out=0, width=W, height=H, reserved0=0, channels=3, flags=0,
                  reserved=0, near=0.1, far=math.inf, mpu=0.0, cut_t=0.0, cut_r=0.0, method=b"reproject")
    fields.update(change)
    return wire.HELLO.pack(*fields.values())


def test_hello_rejects_bad_fields(server):
    _, address = server
    cases = [(dict(channels=5), "channels"), (dict(flags=64), "flags"), (dict(width=0), "size"),
             (dict(method=b"warp9"), "unknown method"), (dict(far=0.01), "far")]
    for change, match in cases:
        with Client(address) as client, pytest.raises(ServerError, match=match) as info:
            client.request(MessageType.HELLO, _hello_fields(**change))
        assert info.value.status == Status.BAD_INPUT


def test_a_client_shrinking_its_segment_gets_an_error_not_a_dead_server(server):
    """Issue 20, D1: a client that truncated the segment the server named and then sent SUBMIT killed the
    server with SIGBUS (every session lost). The server now reads the frame with pread: a short read is a
    BAD_INPUT answer, and the server keeps serving."""
    proc, address = server
    with Client(address, version=2) as client:  # a named segment (an anonymous one is sealed: test_memfd_...)
        layout = client.hello(config())
        client.submit(*frame_arrays(), pose(), K, 0.0)
        client._unmap()  # the client's own mapping would fault on the pages cut off next
        os.truncate(SHM / layout.shm_name.lstrip("/"), 0)
        with pytest.raises(ServerError, match="truncated") as info:
            client.request(MessageType.SUBMIT, frame_payload(1, 0.1))
        assert info.value.status == Status.BAD_INPUT
        client.request(MessageType.PREDICT, frame_payload(2, 0.05))  # written with pwrite: no fault either
    assert_serves(proc, address)


def test_segment_names_are_random_and_private(server):
    """Issue 20, D11: predictable names let another process pre-create the next one; they are now random,
    created exclusively and readable by the server's user only."""
    _, address = server
    with Client(address, version=2) as a, Client(address, version=2) as b:
        names = [a.hello(config()).shm_name, b.hello(config()).shm_name]
        assert names[0] != names[1]
        for name in names:
            assert len(name.rsplit("-", 1)[1]) == 16
            assert stat.S_IMODE((SHM / name.lstrip("/")).stat().st_mode) == 0o600


@pytest.mark.parametrize("change, match", [
    (dict(method=b"decomp[model=/etc/passwd]"), "names a file"),
    (dict(method=b"decomp[fill=infill,infill_model=/etc/hostname]"), "names a file"),
    (dict(method=b"decomp[threads=48]"), "threads=48 exceeds"),
    (dict(method=b"decomp[threads=+48]"), "exceeds"),  # read as the config reads it, not as digits
    (dict(width=8192, height=8192), "exceeds the server's limit"),
])
def test_a_client_cannot_name_files_or_take_more_than_its_share(server, change, match):
    """Issue 20, D2/D3: method options named any file for the server to open and run; sizes and threads had no
    limit. Each is now a BAD_INPUT answer, the same whether the file exists or not."""
    _, address = server
    with Client(address) as client, pytest.raises(ServerError, match=match) as info:
        client.request(MessageType.HELLO, _hello_fields(**change))
    assert info.value.status == Status.BAD_INPUT


def test_connection_limit_and_idle_timeout(tmp_path):
    """Issue 20, D3: stalled connections each held a thread forever. Past --max-connections a connection is
    closed at once; a silent one is closed after --idle-timeout."""
    sock_path = tmp_path / "s.sock"
    proc = subprocess.Popen([sys.executable, "-m", "engine.cli", "serve", "--listen", f"unix:{sock_path}",
                             "--max-connections", "2", "--idle-timeout", "1"], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)
    try:
        assert "listening on" in proc.stdout.readline()
        first, second, third = (socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) for _ in range(3))
        for s in (first, second, third):
            s.settimeout(5.0)
        first.connect(str(sock_path))
        second.connect(str(sock_path))
        time.sleep(0.3)  # both accepted
        third.connect(str(sock_path))
        start = time.monotonic()
        assert third.recv(1) == b"" and time.monotonic() - start < 2.0  # closed at once: over the limit
        assert first.recv(1) == b"" and 0.5 < time.monotonic() - start < 4.0  # closed for silence
        assert second.recv(1) == b""
        with Client(f"unix:{sock_path}") as client:  # room again
            client.hello(config())
    finally:
        for s in (first, second, third):
            s.close()
        assert stop_server(proc) == 0


def test_default_socket_folder_is_private_and_a_squatted_one_is_refused(tmp_path, monkeypatch):
    """Issue 20, D4: the default socket was /tmp/interleave.sock, which any user could squat."""
    from engine.runtime.server import default_socket_path

    monkeypatch.delenv("XDG_RUNTIME_DIR", raising=False)
    path = default_socket_path(tmp_path)
    assert path.parent == tmp_path / f"interleave-{os.getuid()}"
    assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700
    path.parent.chmod(0o777)  # as another user would leave a folder they made first
    with pytest.raises(InputError, match="only it can write"):
        default_socket_path(tmp_path)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "run"))
    (tmp_path / "run").mkdir(mode=0o700)
    assert default_socket_path(tmp_path) == tmp_path / "run" / "interleave.sock"


@pytest.mark.skipif(os.getuid() != 0, reason="making a file of another user needs root")
def test_another_users_socket_is_not_removed(tmp_path):
    from engine.runtime.server import Server

    path = tmp_path / "s.sock"
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(str(path))
    listener.close()  # a stale socket file, but not ours
    os.chown(path, 12345, 12345)
    with pytest.raises(InputError, match="another user's socket"):
        Server(path)
    assert path.exists()


_KNOWN_TYPES = [int(t) for t in MessageType if t != MessageType.REPLY]


@st.composite
def _messages(draw) -> bytes:
    """A request as a careless or hostile client might send it: known or unknown types, right or wrong
    sizes, random payloads, HELLOs with random field values, or bytes that are no header at all."""
    kind = draw(st.sampled_from(["header", "hello", "hello_motion", "submit_motion", "garbage"]))
    if kind == "garbage":
        return draw(st.binary(min_size=1, max_size=64))
    if kind in ("hello", "hello_motion"):
        ints = [draw(st.integers(0, 2 ** 32 - 1)) for _ in range(10)]
        ints[4], ints[5] = draw(st.integers(0, 20000)), draw(st.integers(0, 20000))  # width, height
        floats = [draw(st.floats(allow_nan=True, allow_infinity=True, width=64)) for _ in range(5)]
        method = draw(st.sampled_from([b"reproject", b"decomp[threads=64]", b"decomp[model=/etc/passwd]",
                                       b"flow2d[preset=x]", b"\xff\xfe", b"decomp[" + b"a" * 50, b"auto", b"mvec"]))
        payload = wire.HELLO.pack(*ints, *floats, method)
        if kind == "hello_motion":  # small codes mostly, so that some HELLOs get through to a session
            codes = [draw(st.integers(0, 4) | st.integers(0, 2 ** 32 - 1)) for _ in range(10)]
            scales = [draw(st.floats(allow_nan=True, allow_infinity=True, width=64)) for _ in range(2)]
            payload += wire.MOTION.pack(*codes, *scales)
        version = draw(st.sampled_from(wire.VERSIONS))
        return wire.pack_header(MessageType.HELLO, 1, len(payload), version=version) + payload
    if kind == "submit_motion":
        payload = frame_payload(draw(st.integers(0, 9)), draw(st.floats(0.0, 1.0))) + wire.SUBMIT_MOTION.pack(
            draw(st.integers(0, 7)), draw(st.integers(0, 2 ** 32 - 1)))
        version = draw(st.sampled_from(wire.VERSIONS))
        return wire.pack_header(MessageType.SUBMIT, 2, len(payload), version=version) + payload
    type_ = draw(st.sampled_from(_KNOWN_TYPES) | st.integers(0, 0xFFFF))
    payload = draw(st.binary(max_size=300))
    size = draw(st.sampled_from([len(payload), len(payload) + 7, 0, wire.MAX_PAYLOAD + 1]))
    return wire.pack_header(type_, draw(st.integers(0, 2 ** 32 - 1)), size) + payload


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(messages=st.lists(_messages(), min_size=1, max_size=4))
def test_fuzzed_requests_get_an_answer_or_a_close_and_the_server_lives(server, messages):
    """Bounded fuzz test of the protocol (issue 20): whatever a client sends, the server answers or closes
    the connection, and keeps serving others."""
    proc, address = server
    path = address.split(":", 1)[1]
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(0.5)
        sock.connect(path)
        try:
            for message in messages:
                sock.sendall(message)
            sock.recv(1 << 16)  # a reply, b"" for a close, or a timeout when it waits for more bytes
        except (socket.timeout, ConnectionError, BrokenPipeError):
            pass
    assert proc.poll() is None


def test_the_server_serves_after_the_fuzzing(server):
    assert_serves(*server)


def test_models_folder_is_the_servers_own_configuration(tmp_path):
    """Issue 20, D2: network files are the server's configuration (serve --models DIR), not a client's."""
    from engine.runtime.server import with_server_models

    assert with_server_models("reproject", tmp_path) == "reproject"
    assert with_server_models("decomp2d[flow_width=240]", tmp_path) == (
        f"decomp2d[flow_width=240,model={tmp_path / 'flow2d.onnx'},infill_model={tmp_path / 'infill.onnx'}]")
    empty = tmp_path / "empty"
    empty.mkdir()
    sock = tmp_path / "m.sock"
    proc = subprocess.Popen([sys.executable, "-m", "engine.cli", "serve", "--listen", f"unix:{sock}", "--models",
                             str(empty)], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        assert "listening on" in proc.stdout.readline()
        with Client(f"unix:{sock}") as client:
            client.hello(config(method="reproject"))
            with pytest.raises(ServerError, match="flow network not found"):
                client.hello(config(method="decomp"))  # looked for in the server's folder, which has none
    finally:
        assert stop_server(proc) == 0


# --------------------------------------------------------------------------------------------
# Motion vectors (protocol version 2) and version-1 clients
# --------------------------------------------------------------------------------------------

def _raw_request(sock, type_, payload, request_id, version):
    sock.sendall(wire.pack_header(type_, request_id, len(payload), version=version) + payload)
    reply = read_reply(sock, version=version)
    assert reply is not None and reply[1] == request_id
    return reply


def test_a_version_1_client_is_answered_exactly_as_before(server):
    """A client written before motion vectors: version-1 headers and payloads, answered in version 1 with
    the version-1 layout (il_layout alone); the version-2 extensions are wrong sizes for it."""
    proc, address = server
    sock = raw_connect(address)
    hello = _hello_fields(channels=4)
    type_, _, status, payload = _raw_request(sock, MessageType.HELLO, hello, 1, version=1)
    assert (type_, status, len(payload)) == (MessageType.HELLO | MessageType.REPLY, Status.OK, wire.LAYOUT.size)
    layout = wire.Layout.unpack(payload)
    assert not layout.has_motion and layout == wire.make_layout(layout.shm_name, W, H, 4, "linear", "linear")
    shm = _attach(layout.shm_name)
    try:
        color, depth = frame_arrays(channels=4)
        np.ndarray((H, W, 4), np.float32, buffer=shm.buf, offset=layout.color_in_offset)[...] = color
        np.ndarray((H, W), np.float32, buffer=shm.buf, offset=layout.depth_offset)[...] = depth
        assert _raw_request(sock, MessageType.SUBMIT, frame_payload(0, 0.0), 2, version=1)[2] == Status.OK
        _, _, status, reply = _raw_request(sock, MessageType.PREDICT, frame_payload(1, 0.05, pose(0.01)), 3, version=1)
        assert status == Status.OK and wire.cstring(wire.PREDICT_REPLY.unpack(reply)[4]) == "reproject"
        expected = Session(config()).submit(color, depth, pose(), K, 0.0)
        assert expected.frame == 0
        for type_, payload in ((MessageType.HELLO, hello + bytes(wire.MOTION.size)),
                               (MessageType.SUBMIT, frame_payload(2, 0.1) + wire.SUBMIT_MOTION.pack(1, 0)),
                               (MessageType.RESET, wire.RESET.pack(0, 0) + wire.RESET_MOTION.pack(0, 0))):
            _, _, status, text = _raw_request(sock, type_, payload, 4, version=1)
            assert status == Status.BAD_SIZE and b"protocol version 1" in text
        _, _, status, payload = _raw_request(sock, MessageType.RESET, wire.RESET.pack(0, 0), 5, version=1)
        assert status == Status.OK and len(payload) == wire.LAYOUT.size
        assert _raw_request(sock, MessageType.BYE, b"", 6, version=1)[2] == Status.OK
    finally:
        shm.close()
    sock.close()
    bad = raw_connect(address)  # a header the server cannot trust is answered in the version every client reads
    bad.sendall(wire.HEADER.pack(wire.MAGIC, 7, 1, 9, 0, 0))
    assert read_reply(bad, version=wire.VERSION_MIN)[2] == Status.BAD_VERSION
    bad.close()
    assert_serves(proc, address)


def motion_config(**overrides) -> SessionConfig:
    return config(**{"method": "mvec", **overrides})


def _vectors(shape, seed, dtype=np.float32):
    rng = np.random.default_rng(seed)
    return (rng.uniform(-0.02, 0.02, shape) + np.array([0.01, -0.005] + [0.0] * (shape[-1] - 2))).astype(dtype)


@pytest.mark.parametrize("cfg, plane", [
    # Unity-style: UV, y up, previous -> current; a bottom-up RGBA half-float readback at half resolution
    (motion_config(motion_units="uv", motion_y_up=True, motion_direction="next", flip_rows=True),
     MotionPlane(32, 24, 4, "float16")),
    # object motion only with a valid mask (Streamline cameraMotionIncluded = false), full resolution
    (motion_config(motion_units="pixels", motion_includes_camera=False, motion_scale=(40.0, 30.0)),
     MotionPlane(0, 0, 2, "float32")),
    # auto: mvec for the frames with vectors, flow2d for the one without
    (motion_config(method="auto", motion_units="ndc", motion_missing="camera"), MotionPlane(16, 12, 3, "float32")),
])
def test_motion_vectors_arrive_converted_as_in_an_in_process_session(server, cfg, plane):
    """The vectors written into the motion plane reach the session converted as an in-process Session
    converts them: mvec, which extrapolates them, predicts the same frames bit for bit."""
    _, address = server
    local = Session(cfg)
    with Client(address) as client:
        layout = client.hello(cfg, channels=3, motion=plane)
        mw, mh = plane.size(W, H)
        assert layout.has_motion and (layout.motion_width, layout.motion_height) == (mw, mh)
        assert layout.shm_size >= layout.motion_valid_offset + mw * mh
        methods = []
        for i in range(8):
            t = i / 60
            if i % 2 == 0:
                color, depth = frame_arrays(i)
                vectors = _vectors((mh, mw, plane.channels), i, np.dtype(plane.format))
                valid = np.random.default_rng(i).random((mh, mw)) > 0.2
                auto_without = cfg.method == "auto" and i == 4  # (mvec refuses a frame without vectors)
                kwargs = {} if auto_without else dict(motion_vectors=vectors, motion_valid=valid)
                assert client.submit(color, depth, pose(0.01 * i), K, t, **kwargs) == local.submit(
                    color, depth, pose(0.01 * i), K, t, **kwargs)
            else:
                remote, expected = client.predict(pose(0.01 * i), K, t), local.predict(pose(0.01 * i), K, t)
                np.testing.assert_array_equal(remote.color, expected.color)
                np.testing.assert_array_equal(remote.holes, expected.holes)
                assert (remote.method, remote.fallback) == (expected.method, expected.fallback)
                methods.append(remote.method if remote.fallback is None else remote.fallback)
        assert methods == ["history", "mvec", "flow2d" if cfg.method == "auto" else "mvec", "mvec"]
        kept = 2 if cfg.method == "auto" else 3
        assert local.stats["motion_vectors"] == {"kept": kept, "dropped": 1}  # frame 0: nothing to point into
        client.bye()


def test_reset_can_resize_the_motion_plane(server):
    _, address = server
    with Client(address, version=2) as client:
        first = client.hello(motion_config(), motion=MotionPlane(32, 24))
        color, depth = frame_arrays()
        client.submit(color, depth, pose(), K, 0.0, motion_vectors=np.zeros((24, 32, 2), np.float32))
        same = client.reset()
        assert same == first
        full = client.reset(motion_size=(0, 0))
        assert (full.motion_width, full.motion_height) == (W, H) and full.shm_name != first.shm_name
        small = client.reset(width=32, height=24)  # the plane follows the frame (0 x 0)
        assert (small.motion_width, small.motion_height) == (32, 24)
        k_small = K * np.array([[0.5], [0.5], [1.0]])
        client.submit(*frame_arrays(size=(24, 32)), pose(), k_small, 0.1,
                      motion_vectors=np.zeros((24, 32, 2), np.float32))
        with pytest.raises(ServerError, match="at most the frame's 32x24") as info:
            client.reset(motion_size=(64, 48))
        assert info.value.status == Status.BAD_INPUT
        client.bye()


def test_bad_motion_vectors_get_an_error_and_the_server_keeps_serving(server):
    proc, address = server
    with Client(address) as client:
        client.hello(motion_config(motion_units="uv"), motion=MotionPlane(32, 24))
        color, depth = frame_arrays()
        client.submit(color, depth, pose(), K, 0.0)
        bad = np.zeros((24, 32, 2), np.float32)
        bad[3, 4, 1] = np.inf
        with pytest.raises(ServerError, match=r"BAD_INPUT: frame 7, field 'motion_vectors': has 1 infinite values"):
            client.submit(color, depth, pose(0.01), K, 0.1, frame_id=7, motion_vectors=bad)
        bad[3, 4, 1] = 200.0  # 200 viewport heights: 9600 px once converted
        with pytest.raises(ServerError, match=r"frame 8, field 'motion_vectors': has a component of 9600 px once "
                                              r"converted"):
            client.submit(color, depth, pose(0.01), K, 0.1, frame_id=8, motion_vectors=bad)
        for flags, match in ((wire.SUBMIT_VALID, "valid mask without vectors"), (8, "unknown bits 0x8")):
            with pytest.raises(ServerError, match=match) as info:
                client.request(MessageType.SUBMIT, frame_payload(9, 0.1) + wire.SUBMIT_MOTION.pack(flags, 0))
            assert info.value.status == Status.BAD_INPUT
        client.submit(color, depth, pose(0.01), K, 0.1, motion_vectors=np.zeros((24, 32, 2), np.float32))
        assert client.predict(pose(0.02), K, 0.15).method == "mvec"  # the same connection still works
    with Client(address) as plain:
        plain.hello(config())
        with pytest.raises(ServerError, match="has no motion plane") as info:
            plain.request(MessageType.SUBMIT, frame_payload() + wire.SUBMIT_MOTION.pack(wire.SUBMIT_VECTORS, 0))
        assert info.value.status == Status.BAD_INPUT
    assert_serves(proc, address)


def _motion_hello(engine=0, **change) -> bytes:
    fields = dict(units=0, direction=0, y_axis=0, camera=0, missing=0, width=0, height=0, channels=2, format=0,
                  reserved=0, scale_x=0.0, scale_y=0.0)
    fields.update(change)
    return _hello_fields(engine=engine) + wire.MOTION.pack(*fields.values())


@pytest.mark.parametrize("payload, match", [
    (_motion_hello(units=4), "motion field 'units': code 4"),
    (_motion_hello(direction=3), "motion field 'direction'"),
    (_motion_hello(y_axis=3), "motion field 'y_axis'"),
    (_motion_hello(camera=9), "motion field 'camera'"),
    (_motion_hello(missing=3), "motion field 'missing'"),
    (_motion_hello(format=2), "motion field 'format'"),
    (_motion_hello(channels=1), "motion field 'channels' must be 2, 3 or 4"),
    (_motion_hello(width=W + 1, height=H), "at most the frame's 64x48"),
    (_motion_hello(width=0, height=10), "0x0 for the frame's size"),
    (_motion_hello(scale_x=float("nan")), "motion_scale"),
    (_motion_hello(engine=wire.ENGINE_CODES.index("opengl")), "field 'motion_units': engine 'opengl' has no"),
])
def test_hello_rejects_bad_motion_fields(server, payload, match):
    _, address = server
    with Client(address) as client, pytest.raises(ServerError, match=match) as info:
        client.request(MessageType.HELLO, payload)
    assert info.value.status == Status.BAD_INPUT
    with Client(address) as client:  # a zero-filled il_motion: the engine's conventions, a full-size plane
        layout = Layout.unpack(client.request(MessageType.HELLO, _motion_hello()))
        assert (layout.motion_width, layout.motion_height) == (W, H)
