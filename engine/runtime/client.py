"""Reference client of `interleave serve` (``engine/runtime/protocol.py``, ``docs/server.md``).

It speaks the same bytes a C or C++ engine plugin would (``engine/runtime/include/interleave_protocol.h``):
HELLO, then SUBMIT / PREDICT with the pixels in the server's shared-memory segment, RESET, BYE. It speaks
protocol version 3: over a Unix socket the segment is an anonymous memfd whose descriptor comes with the
HELLO and RESET replies (SCM_RIGHTS), over TCP a named segment it opens by name. ``Client(..., version=2)``
speaks version 2 (named segments) and ``version=1`` version 1, as clients from before motion vectors do;
``hello(..., motion=MotionPlane(...))`` opens a motion-vector plane, and ``submit(..., motion_vectors=)``
writes each frame's vectors into it.

    >>> with Client("unix:/tmp/interleave.sock") as client:              # doctest: +SKIP
    ...     client.hello(SessionConfig(engine="opengl", width=640, height=360, method="reproject"))
    ...     client.submit(color, depth, view, projection, time=0.0)
    ...     out = client.predict(view_next, projection, time=1 / 60)

Run as a program it is a small benchmark: ``python -m engine.runtime.client unix:/tmp/interleave.sock --frames 200``
streams a synthetic scene (a camera sliding over a slanted textured plane) through the server and prints
the round-trip time of PREDICT; ``--in-process`` also times the same calls on an in-process ``Session``.
"""
from __future__ import annotations

import argparse
import array
import mmap
import os
import socket
import sys
import time
from dataclasses import dataclass
from multiprocessing import resource_tracker, shared_memory
from pathlib import Path
from typing import Optional

import numpy as np

from engine.core.errors import InterleaveError
from engine.runtime import protocol as wire
from engine.runtime.protocol import Layout, MessageType, MotionPlane, Status
from engine.runtime.server import Address, parse_address
from engine.runtime.session import Session, SessionConfig, SubmitResult


class ServerError(InterleaveError):
    """An error reply: ``status`` (:class:`~engine.runtime.protocol.Status`) and the server's text."""

    def __init__(self, status: int, text: str, request_id: int) -> None:
        self.status = Status(status) if status in Status._value2member_map_ else status
        self.text = text
        self.request_id = request_id
        name = self.status.name if isinstance(self.status, Status) else str(status)
        super().__init__(f"server error {name}: {text}")


@dataclass
class ClientPrediction:
    """A predicted frame read back from shared memory (see :class:`engine.runtime.session.SessionPrediction`)."""

    color: np.ndarray
    holes: np.ndarray
    method: str
    fallback: Optional[str]
    frame: int
    server_ms: float


def _attach(name: str) -> shared_memory.SharedMemory:
    """Open the server's named segment without letting this process's resource tracker unlink it at exit."""
    try:
        return shared_memory.SharedMemory(name=name.lstrip("/"), track=False)  # Python >= 3.13
    except TypeError:
        shm = shared_memory.SharedMemory(name=name.lstrip("/"))
        resource_tracker.unregister(shm._name, "shared_memory")  # type: ignore[attr-defined]
        return shm


class _Mapped:
    """An anonymous segment mapped from the descriptor the server passed (``buf`` and ``close`` like a
    ``SharedMemory``); the descriptor is closed once mapped."""

    def __init__(self, fd: int, size: int) -> None:
        try:
            self._mmap = mmap.mmap(fd, size, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE)
        finally:
            os.close(fd)
        self.buf = memoryview(self._mmap)

    def close(self) -> None:
        self.buf.release()
        self._mmap.close()


#: Room for the ancillary data of one received message: a few descriptors (the server sends one at most).
_ANCILLARY = socket.CMSG_SPACE(4 * array.array("i").itemsize)


class Client:
    """One connection to an `interleave serve` server, holding at most one session.

    Args:
        address: "unix:/path", a path, "tcp:PORT", or a parsed address.
        timeout: seconds to wait for any reply.
        version: the protocol version of every request (``wire.VERSIONS``); motion vectors need 2.
    """

    def __init__(self, address: Address | str, timeout: float = 30.0, version: int = wire.VERSION) -> None:
        if version not in wire.VERSIONS:
            raise InterleaveError(f"protocol version must be one of {wire.VERSIONS}, got {version}")
        addr = parse_address(address) if isinstance(address, str) else address
        if isinstance(addr, tuple):
            self.sock = socket.create_connection(addr, timeout=timeout)
            self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        else:
            self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            self.sock.settimeout(timeout)
            self.sock.connect(str(Path(addr)))
        self.version = version
        self._next_id = 1
        self._frame = 0
        self._unix = self.sock.family == socket.AF_UNIX
        self._fds: list[int] = []  # descriptors received with the reply being read (SCM_RIGHTS)
        self._shm: Optional[shared_memory.SharedMemory | _Mapped] = None
        self.layout: Optional[Layout] = None
        self.config: Optional[SessionConfig] = None
        self.channels = 3
        self.column_major = False
        self.motion: Optional[MotionPlane] = None
        self._views: dict[str, np.ndarray] = {}

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- raw messages -----------------------------------------------------------------------------

    def send_raw(self, data: bytes) -> None:
        """Send bytes as they are (tests use it for malformed messages)."""
        self.sock.sendall(data)

    def _read_exact(self, size: int) -> bytes:
        buf = bytearray(size)
        view, got = memoryview(buf), 0
        while got < size:
            if self._unix:  # recvmsg: a descriptor the server passes arrives with the bytes it rides on
                n, ancillary, flags, _ = self.sock.recvmsg_into([view[got:]], _ANCILLARY, socket.MSG_CMSG_CLOEXEC)
                for level, kind, data in ancillary:
                    if level == socket.SOL_SOCKET and kind == socket.SCM_RIGHTS:
                        fds = array.array("i")
                        fds.frombytes(data[:len(data) - len(data) % fds.itemsize])
                        self._fds.extend(fds)
                if flags & socket.MSG_CTRUNC:
                    raise ConnectionError("the server passed more descriptors than a reply carries")
            else:
                n = self.sock.recv_into(view[got:])
            if n == 0:
                raise ConnectionError(f"the server closed the connection ({got} of {size} bytes read)")
            got += n
        return bytes(buf)

    def _take_fds(self) -> list[int]:
        fds, self._fds = self._fds, []
        return fds

    def read_reply(self) -> tuple[int, int, int, bytes]:
        """(type, request_id, status, payload) of the next reply; descriptors passed with it wait in
        ``_take_fds()``."""
        for fd in self._take_fds():  # left from an earlier reply nobody asked for: not ours to keep
            os.close(fd)
        magic, version, type_, request_id, status, size = wire.HEADER.unpack(self._read_exact(wire.HEADER.size))
        if magic != wire.MAGIC or version not in wire.VERSIONS:
            raise ConnectionError(f"not an interleave server reply (magic 0x{magic:08x}, version {version})")
        return type_, request_id, status, self._read_exact(size)

    def send(self, type_: int, payload: bytes = b"", request_id: Optional[int] = None) -> int:
        """Send one request; returns its request id (consecutive from 1 unless given)."""
        if request_id is None:
            request_id, self._next_id = self._next_id, self._next_id + 1
        self.sock.sendall(wire.pack_header(type_, request_id, len(payload), version=self.version) + payload)
        return request_id

    def request(self, type_: int, payload: bytes = b"") -> bytes:
        """Send one request and return the payload of its reply; raises ServerError for an error reply."""
        request_id = self.send(type_, payload)
        reply_type, reply_id, status, reply = self.read_reply()
        if status != Status.OK:
            raise ServerError(status, reply.decode("utf-8", errors="replace"), reply_id)
        if reply_id != request_id or reply_type != (type_ | MessageType.REPLY):
            raise ConnectionError(f"reply {reply_type:#x}/{reply_id} does not answer request {type_:#x}/{request_id}")
        return reply

    # -- session ----------------------------------------------------------------------------------

    def hello(self, config: SessionConfig, *, channels: int = 3, column_major: bool = False,
              motion: Optional[MotionPlane] = None) -> Layout:
        """Open a session with ``config``; ``channels`` (3 or 4) of colour in shared memory; ``motion``: a
        motion-vector plane (protocol version 2) for vectors in ``config``'s ``motion_*`` conventions."""
        flags = ((wire.FLAG_FLIP_ROWS if config.flip_rows else 0) | (wire.FLAG_NDC_Y_DOWN if config.ndc_y_down else 0)
                 | (wire.FLAG_COLUMN_MAJOR if column_major else 0))
        payload = wire.HELLO.pack(
            wire.ENGINE_CODES.index(config.engine), wire.DEPTH_CODES.index(config.depth_convention),
            wire.COLOR_CODES.index(config.color_in), wire.COLOR_CODES.index(config.color_out),
            config.width, config.height, 0, channels, flags, 0,
            config.near, config.far, config.meters_per_unit, config.cut_translation, config.cut_rotation_deg,
            config.method.encode())
        if motion is not None:
            if self.version < 2:
                raise InterleaveError("motion vectors need protocol version 2 (Client(..., version=2))")
            payload += wire.MOTION.pack(
                wire.MOTION_UNIT_CODES.index(config.motion_units),
                wire.MOTION_DIRECTION_CODES.index(config.motion_direction),
                wire.MOTION_Y_CODES.index(config.motion_y_up),
                wire.MOTION_CAMERA_CODES.index(config.motion_includes_camera),
                wire.MOTION_MISSING_CODES.index(config.motion_missing), motion.width, motion.height, motion.channels,
                wire.MOTION_FORMATS.index(motion.format), 0, *config.motion_scale)
        layout = Layout.unpack(self.request(MessageType.HELLO, payload))
        self.config, self.channels, self.column_major, self.motion = config, channels, column_major, motion
        self._map(layout)
        return layout

    def _map(self, layout: Layout) -> None:
        fds = self._take_fds()
        if layout.anonymous:  # version 3 over a Unix socket: the segment is the descriptor of this reply
            if len(fds) != 1:
                for fd in fds:
                    os.close(fd)
                raise ConnectionError(f"a layout without a segment name came with {len(fds)} descriptors, not 1")
            self._unmap()
            self._shm = _Mapped(fds[0], layout.shm_size)
        else:
            for fd in fds:
                os.close(fd)
            if self._shm is None or self.layout is None or layout.shm_name != self.layout.shm_name:
                self._unmap()
                self._shm = _attach(layout.shm_name)
        self.layout = layout
        h, w, c = layout.height, layout.width, self.channels

        def view(offset, shape, space=None):
            dtype = np.uint8 if space in (None, "srgb8") else np.float32
            return np.ndarray(shape, dtype=dtype, buffer=self._shm.buf, offset=offset)

        self._views = {"color_in": view(layout.color_in_offset, (h, w, c), self.config.color_in),
                       "depth": np.ndarray((h, w), np.float32, buffer=self._shm.buf, offset=layout.depth_offset),
                       "color_out": view(layout.color_out_offset, (h, w, c), self.config.color_out),
                       "holes": view(layout.holes_offset, (h, w))}
        if layout.has_motion:
            mh, mw = layout.motion_height, layout.motion_width
            self._views["motion"] = np.ndarray((mh, mw, self.motion.channels), np.dtype(self.motion.format),
                                               buffer=self._shm.buf, offset=layout.motion_offset)
            self._views["motion_valid"] = view(layout.motion_valid_offset, (mh, mw))

    def _unmap(self) -> None:
        self._views = {}
        if self._shm is not None:
            self._shm.close()
            self._shm = None

    def _frame_payload(self, frame_id: Optional[int], time_s: float, view, projection) -> bytes:
        if frame_id is None:
            frame_id, self._frame = self._frame, self._frame + 1
        v, p = np.asarray(view, dtype=np.float64), np.asarray(projection, dtype=np.float64)
        if p.ndim == 0:  # Unreal: a horizontal FOV in degrees travels as the first entry of a zero matrix
            raise InterleaveError("over the wire, Unreal's projection is its 4x4 FMatrix, not an FOV")
        if p.shape == (3, 3):  # OpenCV K: top-left block of a 4x4
            p = np.pad(p, ((0, 1), (0, 1)))
        if v.shape != (4, 4) or p.shape != (4, 4):
            raise InterleaveError(f"view and projection must be 4x4 over the wire, got {v.shape} and {p.shape}")
        if self.column_major:
            v, p = v.T, p.T
        return wire.FRAME.pack(frame_id, time_s, *v.ravel(), *p.ravel())

    def submit(self, color, depth, view, projection, time: float, *, frame_id: Optional[int] = None,
               motion_vectors=None, motion_valid=None) -> SubmitResult:
        """Write colour and depth (and the frame's motion vectors, and their valid mask, into the session's
        motion plane) into shared memory and submit them with their camera and time."""
        color = np.asarray(color)
        self._views["color_in"][..., :min(color.shape[-1], self.channels)] = color[..., :self.channels]
        self._views["depth"][...] = depth
        payload = self._frame_payload(frame_id, time, view, projection)
        if motion_vectors is not None or motion_valid is not None:
            if "motion" not in self._views:
                raise InterleaveError("motion vectors need a motion plane: hello(..., motion=MotionPlane(...))")
            plane, flags = self._views["motion"], wire.SUBMIT_VECTORS
            vectors = np.asarray(motion_vectors)
            if vectors.shape != plane.shape:
                raise InterleaveError(f"motion_vectors must have the plane's shape {plane.shape}, got {vectors.shape}")
            plane[...] = vectors
            if motion_valid is not None:
                mask = np.asarray(motion_valid)
                if mask.shape != plane.shape[:2]:
                    raise InterleaveError(f"motion_valid must have shape {plane.shape[:2]}, got {mask.shape}")
                self._views["motion_valid"][...] = mask != 0
                flags |= wire.SUBMIT_VALID
            payload += wire.SUBMIT_MOTION.pack(flags, 0)
        reply = self.request(MessageType.SUBMIT, payload)
        frame, reset, history = wire.SUBMIT_REPLY.unpack(reply)
        return SubmitResult(frame=frame, reset=wire.RESET_CODES[reset], history=history)

    def predict(self, view, projection, time: float, *, frame_id: Optional[int] = None,
                copy: bool = True) -> ClientPrediction:
        """Predict a frame; with ``copy=False`` colour and holes are views of shared memory, valid until the
        next request of this client."""
        reply = self.request(MessageType.PREDICT, self._frame_payload(frame_id, time, view, projection))
        frame, fallback, _, server_ms, method = wire.PREDICT_REPLY.unpack(reply)
        color, holes = self._views["color_out"][..., :3], self._views["holes"]
        if copy:
            color, holes = color.copy(), holes.astype(bool)
        return ClientPrediction(color, holes, wire.cstring(method), wire.FALLBACK_CODES[fallback], frame, server_ms)

    def reset(self, width: Optional[int] = None, height: Optional[int] = None,
              motion_size: Optional[tuple[int, int]] = None) -> Layout:
        """Clear the session's history; a new size moves the pixels to a new segment (remapped here).
        ``motion_size``: the motion plane's new (width, height) ((0, 0): the frame's); else it is kept."""
        payload = wire.RESET.pack(width or 0, height or 0)
        if motion_size is not None:
            payload += wire.RESET_MOTION.pack(*motion_size)
        layout = Layout.unpack(self.request(MessageType.RESET, payload))
        if motion_size is not None:
            self.motion = MotionPlane(*motion_size, self.motion.channels, self.motion.format)
        self._map(layout)
        return layout

    def bye(self) -> None:
        """End the session (the server unlinks its segment) and the connection."""
        try:
            self.request(MessageType.BYE)
        finally:
            self.close()

    def close(self) -> None:
        self._unmap()
        for fd in self._take_fds():
            os.close(fd)
        try:
            self.sock.close()
        except OSError:
            pass


# --------------------------------------------------------------------------------------------
# Benchmark / smoke run
# --------------------------------------------------------------------------------------------

def synthetic_stream(width: int, height: int, frames: int, fps: float = 60.0):
    """(color, depth, world_to_camera, K, time) of a camera sliding over a slanted textured plane (OpenCV)."""
    k = np.array([[0.8 * width, 0.0, width / 2.0], [0.0, 0.8 * width, height / 2.0], [0.0, 0.0, 1.0]])
    rows = np.arange(height, dtype=np.float32)[:, None]
    cols = np.arange(width, dtype=np.float32)[None, :]
    depth = np.broadcast_to(2.0 + 3.0 * rows / height, (height, width)).astype(np.float32)
    for i in range(frames):
        t = i / fps
        pose = np.eye(4)
        pose[0, 3] = -0.2 * t
        phase = cols + 0.2 * t * k[0, 0] / depth  # the texture moves with the camera, like the real plane
        color = np.stack([0.5 + 0.4 * np.sin(phase / 7.0), np.broadcast_to(0.5 + 0.4 * np.cos(rows / 5.0), phase.shape),
                          np.full_like(phase, 0.3)], axis=-1).astype(np.float32)
        yield color, depth, pose, k, t


def _percentiles(samples: list[float]) -> str:
    a = np.asarray(samples)
    return f"median {np.median(a):.2f} ms, p90 {np.percentile(a, 90):.2f} ms, n={a.size}"


def main(argv: Optional[list[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m engine.runtime.client",
                                     description="Stream a synthetic scene through `interleave serve`, time PREDICT.")
    parser.add_argument("address", help="unix:/path or tcp:PORT")
    parser.add_argument("--frames", type=int, default=100, help="displayed frames (default: 100)")
    parser.add_argument("--k", type=int, default=2, help="one rendered frame every k (default: 2)")
    parser.add_argument("--width", type=int, default=640, help="frame width (default: 640)")
    parser.add_argument("--height", type=int, default=360, help="frame height (default: 360)")
    parser.add_argument("--method", default="reproject", help="predictor (default: reproject)")
    parser.add_argument("--in-process", action="store_true", help="also time an in-process Session")
    args = parser.parse_args(argv)
    config = SessionConfig(engine="opencv", width=args.width, height=args.height, method=args.method)
    try:
        with Client(args.address) as client:
            client.hello(config)
            targets = {"socket": client}
            if args.in_process:
                targets["in-process"] = Session(config)
            times = {name: [] for name in targets}
            methods: set[str] = set()
            for i, (color, depth, pose, k, t) in enumerate(synthetic_stream(args.width, args.height, args.frames)):
                for name, target in targets.items():  # alternate, so both see the same machine load
                    if i % args.k == 0:
                        target.submit(color, depth, pose, k, t)
                        continue
                    start = time.perf_counter()
                    out = target.predict(pose, k, t)
                    times[name].append(1e3 * (time.perf_counter() - start))
                    methods.add(out.method)
            for name, samples in times.items():
                print(f"{name}: PREDICT {args.width}x{args.height} {args.method} ({', '.join(sorted(methods))}): "
                      f"{_percentiles(samples)}")
            if args.in_process:
                extra = np.subtract(times["socket"], times["in-process"])
                print(f"socket - in-process, paired: median {np.median(extra):.2f} ms")
            client.bye()
    except (InterleaveError, OSError) as exc:
        print(f"python -m engine.runtime.client: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
