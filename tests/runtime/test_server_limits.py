"""`interleave serve` at the edges of its resources and of what one client may reach (issue 41, items 2, 5, 6, 8).

File descriptors: a connection cap the open-file limit cannot hold refuses to start; a server that runs out of
descriptors anyway (its limit lowered under it) refuses new connections and keeps serving the open sessions.
Segments: over a Unix socket (protocol version 3) a session's segment is an anonymous sealed memfd whose
descriptor comes with the layout reply, so nothing of it is in /dev/shm; over TCP it is a named segment.
Memory: a HELLO (or RESET) whose estimated footprint would pass ``--max-memory`` gets OVER_BUDGET.
Error text names the wire field (``method``, ``view``).
"""
from __future__ import annotations

import os
import resource
import socket
import subprocess
import sys

import numpy as np
import pytest

from engine.runtime import protocol as wire
from engine.runtime.client import Client, ServerError
from engine.runtime.protocol import MessageType, Status
from engine.runtime.server import (FD_HEADROOM, FDS_PER_CONNECTION, METHOD_BYTES_PER_PIXEL, ServerLimits,
                                   host_memory, session_footprint)
from engine.runtime.session import Session, SessionConfig
from tests.runtime.test_server import (H, K, ROOT, SHM, W, assert_serves, config, frame_arrays, frame_payload, pose,
                                       server_segments, start_server, stop_server)
from tests.runtime.test_server import server  # noqa: F401 - its module-scoped server fixture, one for this module

pytestmark = pytest.mark.skipif(not SHM.is_dir() or not hasattr(socket, "AF_UNIX") or not hasattr(os, "memfd_create"),
                                reason="needs /dev/shm, Unix sockets and memfd (Linux)")


def _limit_fds(limit: int):
    def preexec() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (limit, limit))
    return preexec


def _open_fd_numbers(pid: int) -> set[int]:
    return {int(name) for name in os.listdir(f"/proc/{pid}/fd")}


# --------------------------------------------------------------------------------------------
# File descriptors (item 2)
# --------------------------------------------------------------------------------------------

def test_a_connection_cap_the_fd_limit_cannot_hold_refuses_to_start(tmp_path):
    """Issue 41, item 2: with `ulimit -n 1024` and --max-connections 600 the server started and died of EMFILE
    under a burst. A cap that the hard limit cannot hold is now a one-line error, exit 2."""
    run = subprocess.run([sys.executable, "-m", "engine.cli", "serve", "--listen", f"unix:{tmp_path / 's.sock'}",
                          "--max-connections", "600"], cwd=ROOT, capture_output=True, text=True, timeout=60,
                         preexec_fn=_limit_fds(256))
    assert run.returncode == 2
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "field '--max-connections'" in lines[0] and "at most" in lines[0], run.stderr
    fits = int(lines[0].split("give at most ")[1].split(",")[0])
    assert 0 < fits < 600 and fits * FDS_PER_CONNECTION + FD_HEADROOM <= 256
    assert not (tmp_path / "s.sock").exists()


def test_the_server_survives_running_out_of_descriptors(tmp_path):
    """Issue 41, item 2: an accept() that fails with EMFILE ended serve_forever and every session. Started
    under a low RLIMIT_NOFILE, then squeezed to no free descriptor at all, the server refuses a burst of
    connections, keeps serving the open session, and accepts again once descriptors are free."""
    log = tmp_path / "server.log"
    proc = subprocess.Popen([sys.executable, "-m", "engine.cli", "serve", "--listen", f"unix:{tmp_path / 's.sock'}",
                             "--max-connections", "8"], cwd=ROOT, stdout=subprocess.PIPE, stderr=log.open("w"),
                            text=True, preexec_fn=_limit_fds(128))
    try:
        line = proc.stdout.readline()
        assert "listening on" in line, log.read_text()
        address = line.split("listening on ", 1)[1].strip()
        with Client(address) as client:
            client.hello(config())
            client.submit(*frame_arrays(), pose(), K, 0.0)
            before = client.predict(pose(0.01), K, 0.05)
            used = _open_fd_numbers(proc.pid)
            lowest_free = min(set(range(len(used) + 1)) - used)
            resource.prlimit(proc.pid, resource.RLIMIT_NOFILE, (lowest_free, 128))  # no new descriptor at all
            refused = 0
            for _ in range(40):  # a burst over the budget: each is closed, none is served, none kills the server
                try:
                    with Client(address, timeout=5.0) as other:
                        other.hello(config())
                except (ConnectionError, OSError):
                    refused += 1
            assert refused == 40
            assert proc.poll() is None
            after = client.predict(pose(0.01), K, 0.05)  # the open session still predicts, the same frame
            np.testing.assert_array_equal(after.color, before.color)
            resource.prlimit(proc.pid, resource.RLIMIT_NOFILE, (128, 128))
        assert_serves(proc, address)
        text = log.read_text()
        assert "cannot accept a connection" in text and "accepting connections again" in text
    finally:
        if proc.poll() is None:
            stop_server(proc)


# --------------------------------------------------------------------------------------------
# Segments (item 5)
# --------------------------------------------------------------------------------------------

def _raw_hello(sock: socket.socket, version: int = wire.VERSION, request_id: int = 1) -> tuple[int, bytes, list[int]]:
    """Send a HELLO of :func:`config` and read its reply with recvmsg: (status, payload, descriptors)."""
    cfg = config()
    payload = wire.HELLO.pack(0, wire.DEPTH_CODES.index(cfg.depth_convention), 0, 0, W, H, 0, 3, 0, 0, cfg.near,
                              cfg.far, 0.0, 0.0, 0.0, b"reproject")
    sock.sendall(wire.pack_header(MessageType.HELLO, request_id, len(payload), version=version) + payload)
    return _raw_reply(sock)


def _raw_reply(sock: socket.socket) -> tuple[int, bytes, list[int]]:
    data, fds = b"", []
    while len(data) < wire.HEADER.size or len(data) < wire.HEADER.size + wire.HEADER.unpack(
            data[:wire.HEADER.size])[5]:
        chunk, more, _, _ = socket.recv_fds(sock, 4096, 4)
        assert chunk, "connection closed"
        data, fds = data + chunk, fds + list(more)
    status = wire.HEADER.unpack(data[:wire.HEADER.size])[4]
    return status, data[wire.HEADER.size:], fds


def test_over_a_unix_socket_no_segment_is_in_dev_shm_and_predictions_are_right(server):
    """Issue 41, item 5: any process of the user could list /dev/shm, read another client's prediction and
    overwrite its colour. Version 3 over a Unix socket: the layout has no name, the descriptor of an anonymous
    memfd comes with the HELLO and RESET replies, and /dev/shm holds nothing of the server's."""
    proc, address = server
    local = Session(config())
    with Client(address) as client:
        layout = client.hello(config())
        assert layout.anonymous and server_segments(proc.pid) == []
        color, depth = frame_arrays()
        client.submit(color, depth, pose(), K, 0.0)
        local.submit(color, depth, pose(), K, 0.0)
        out = client.predict(pose(0.01), K, 0.05)
        np.testing.assert_array_equal(out.color, local.predict(pose(0.01), K, 0.05).color)
        small = client.reset(width=32, height=24)  # a new segment, a new descriptor
        assert small.anonymous and (small.width, small.height) == (32, 24) and server_segments(proc.pid) == []
        k_small = K * np.array([[0.5], [0.5], [1.0]])
        client.submit(*frame_arrays(size=(24, 32)), pose(), k_small, 0.1)
        assert client.predict(pose(0.01), k_small, 0.15).color.shape == (24, 32, 3)
        client.bye()


def test_the_passed_descriptor_is_a_sealed_memfd_sent_with_the_layout_reply_only(server):
    _, address = server
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(10)
    sock.connect(address.removeprefix("unix:"))
    try:
        status, payload, fds = _raw_hello(sock)
        assert status == Status.OK and len(fds) == 1
        layout = wire.Layout.unpack(payload)
        fd = fds[0]
        assert layout.shm_name == "" and os.readlink(f"/proc/self/fd/{fd}").startswith("/memfd:")
        assert os.fstat(fd).st_size == layout.shm_size
        with pytest.raises(PermissionError):  # sealed: the client cannot shrink it under the server
            os.ftruncate(fd, 0)
        os.pwrite(fd, np.full((H, W), 2.0, np.float32).tobytes(), layout.depth_offset)  # a wall 2 m away
        os.close(fd)
        # SUBMIT's reply passes nothing
        sock.sendall(wire.pack_header(MessageType.SUBMIT, 2, wire.FRAME.size) + frame_payload(0, 0.0))
        status, _, fds = _raw_reply(sock)
        assert status == Status.OK and fds == []
    finally:
        sock.close()


def test_over_tcp_and_in_version_2_the_segment_is_named(tmp_path, server):
    proc, address = server
    with Client(address, version=2) as client:
        layout = client.hello(config())
        assert not layout.anonymous and server_segments(proc.pid) == [layout.shm_name[1:]]
    tcp, tcp_address = start_server("tcp:0", tmp_path / "tcp.log")
    try:
        with Client(tcp_address) as client:  # version 3 over TCP: no descriptors to pass, a name
            layout = client.hello(config())
            assert not layout.anonymous and server_segments(tcp.pid) == [layout.shm_name[1:]]
            client.submit(*frame_arrays(), pose(), K, 0.0)
            assert client.predict(pose(0.01), K, 0.05).method == "reproject"
    finally:
        stop_server(tcp)


# --------------------------------------------------------------------------------------------
# Memory (item 6)
# --------------------------------------------------------------------------------------------

def test_a_hello_over_the_memory_budget_is_refused_and_one_under_it_accepted(tmp_path):
    """Issue 41, item 6: 16 connections x 4K could exhaust a 23 GB host within every cap. The server now
    estimates each session (measured bytes per pixel of its method + its segment) against --max-memory."""
    one = session_footprint("reproject", wire.make_layout("", W, H, 3, "linear", "linear"))
    proc, address = start_server(f"unix:{tmp_path / 's.sock'}", tmp_path / "server.log",
                                 "--max-memory", str(int(1.5 * one)))
    try:
        with Client(address) as first, Client(address) as second:
            first.hello(config())
            with pytest.raises(ServerError, match="max-memory") as info:
                second.hello(config())
            assert info.value.status == Status.OVER_BUDGET
            with pytest.raises(ServerError) as info:  # a bigger frame for the open session: refused, kept
                first.reset(width=2 * W, height=2 * H)
            assert info.value.status == Status.OVER_BUDGET
            first.submit(*frame_arrays(), pose(), K, 0.0)
            assert first.predict(pose(0.01), K, 0.05).color.shape == (H, W, 3)
            first.bye()
            second.hello(config())  # the budget freed by the first session takes the second
            second.submit(*frame_arrays(), pose(), K, 0.0)
            assert second.predict(pose(0.01), K, 0.05).fallback is None
            second.bye()  # freed before the reply: the next HELLO fits
        assert_serves(proc, address)
    finally:
        stop_server(proc)


def test_the_default_budget_is_half_the_host_memory_and_footprints_follow_the_table(tmp_path):
    assert ServerLimits().memory_budget() == host_memory() // 2
    physical = host_memory(())
    (tmp_path / "v2").write_text("max\n")
    (tmp_path / "v1").write_text(f"{physical // 4}\n")  # a container limited to a quarter of the host
    assert host_memory((tmp_path / "missing", tmp_path / "v2")) == physical
    assert host_memory((tmp_path / "v2", tmp_path / "v1")) == physical // 4
    assert ServerLimits(max_memory=123).memory_budget() == 123
    layout = wire.make_layout("", 1280, 720, 3, "linear", "linear")
    for method in ("reproject", "flow2d", "mvec", "decomp[gate.tile=16]", "auto"):
        base = method.split("[")[0]
        assert session_footprint(method, layout) == METHOD_BYTES_PER_PIXEL[base] * 1280 * 720 + layout.shm_size
    assert session_footprint("warp9", layout) == max(METHOD_BYTES_PER_PIXEL.values()) * 1280 * 720 + layout.shm_size


# --------------------------------------------------------------------------------------------
# Error text names the wire field (item 8)
# --------------------------------------------------------------------------------------------

def test_errors_name_the_wire_fields_method_and_view(server):
    _, address = server
    with Client(address) as client, pytest.raises(ServerError, match="field 'method'") as info:
        client.hello(config(method="warp9"))
    assert "'methods'" not in info.value.text
    unity = SessionConfig(engine="unity", width=W, height=H, depth_convention="reversed", near=0.3, far=1000.0)
    projection = np.array([[1.3, 0, 0, 0], [0, 1.7, 0, 0], [0, 0, -1.0006, -0.6], [0, 0, -1, 0]])
    with Client(address) as client:
        client.hello(unity)
        scaled = np.diag([2.0, 1.0, 1.0, 1.0])  # not a rigid view
        with pytest.raises(ServerError, match="field 'view'") as info:
            client.submit(frame_arrays()[0], np.full((H, W), 0.5, np.float32), scaled, projection, 0.0)
        assert "'matrix'" not in info.value.text


@pytest.mark.parametrize("engine, view", [
    ("unity", np.diag([2.0, 1.0, 1.0, 1.0])),                                         # from_unity's 'matrix'
    ("unreal", np.array([[1.0, 0, 0, 1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])),  # from_unreal's 'transform'
    ("unreal", np.array([0.0, 0.0, 0.0, np.nan, 0.0, 0.0])),                           # from_unreal's 'rotation'
])
def test_a_bad_view_is_named_view_whatever_the_converter_calls_it(engine, view):
    from engine.core.errors import InputError
    from engine.runtime.session import engine_camera

    projection = 90.0 if engine == "unreal" else np.array([[1.3, 0, 0, 0], [0, 1.7, 0, 0], [0, 0, -1.0006, -0.6],
                                                             [0, 0, -1, 0]])
    with pytest.raises(InputError) as info:
        engine_camera(SessionConfig(engine=engine, width=W, height=H), view, projection)
    assert info.value.field == "view"
