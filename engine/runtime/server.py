"""`interleave serve`: the frame-prediction session behind a local socket, for engines not written in Python.

One connection = one :class:`~engine.runtime.session.Session`. The client sends HELLO (the session config), the
server answers with a shared-memory segment and its layout (protocol version 3 over a Unix socket: an
anonymous memfd whose descriptor comes with the reply; else a named segment); then for each rendered frame the client
writes colour and depth into the segment and sends SUBMIT (pose, time), and for each frame in between it
sends PREDICT (pose, time) and reads the predicted colour and hole mask from the segment. RESET clears
the history (and may change the frame size, which moves to a new segment); BYE ends the session.
Protocol version 2 adds an optional motion-vector plane: HELLO carries its conventions and size, a SUBMIT
says whether the plane holds the frame's vectors (and their valid mask); version-1 clients are answered in
version 1, unchanged.
Wire format: ``engine/runtime/protocol.py``, ``engine/runtime/include/interleave_protocol.h``, ``docs/server.md``.

Resources: ``--max-connections`` is checked against the open-file limit at start; ``accept()`` errors refuse
the waiting connection and never end the server; each HELLO reserves its estimated memory
(:func:`session_footprint`) in ``--max-memory`` or gets OVER_BUDGET.

Robustness: each connection runs in its own thread. A malformed message gets an error reply with a
status code and text; if the byte stream is still in step (unknown type, wrong payload size, bad values)
the connection stays open, otherwise (bad magic or version, oversized or truncated message) the
connection is closed after the reply. Either way the server keeps serving. A client that disconnects,
even mid-message, loses its session and its segment; stopping the server (SIGINT / SIGTERM or
:meth:`Server.stop`) closes every connection, closes (and unlinks, if named) every segment and removes the socket
file.

Requests on one connection are answered in order, each reply echoing the request's ``request_id``;
a client may pipeline requests. Sockets listen on a Unix path or on 127.0.0.1 only.
"""
from __future__ import annotations

import errno
import fcntl
import math
import os
import resource
import secrets
import signal
import socket
import stat
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Union

import numpy as np

from engine.core.config import option, parse_value
from engine.core.errors import InputError, InterleaveError
from engine.geometry.backends import resolve_backend
from engine.predict.registry import (DECOMP_WEIGHTS, make_predictor, method_options, method_parts, method_with,
                                     names_no_file)
from engine.runtime import protocol as wire
from engine.runtime.protocol import MessageType, MotionPlane, Status
from engine.runtime.session import NotReadyError, Session, SessionConfig

Address = Union[str, Path, tuple]

#: Where POSIX shared memory lives (``shm_open("/name")`` is this folder's ``name`` on Linux).
SHM_DIR = Path("/dev/shm")


@dataclass(frozen=True)
class ServerLimits:
    """What one client may take (``interleave serve --max-connections 16 ...``)."""

    max_connections: int = option(16, "connections served at once; further ones are closed on accept")
    max_pixels: int = option(3840 * 2160, "largest frame (width x height) a session may ask for")
    max_threads: int = option(4, "largest 'threads' option a client may give a method (decomp[threads=N])")
    idle_timeout: float = option(300.0, "seconds a connection may stay silent before it is closed (0: never)")
    max_memory: int = option(0, "bytes all sessions together may take, estimated per HELLO from the measured "
                                "bytes per pixel of its method (docs/server.md); 0: half the host's (or the "
                                "container's) memory")

    def __post_init__(self) -> None:
        if min(self.max_connections, self.max_pixels, self.max_threads) < 1:
            raise InputError("max_connections, max_pixels and max_threads must be >= 1", field="ServerLimits")
        if not (math.isfinite(self.idle_timeout) and self.idle_timeout >= 0):
            raise InputError(f"must be >= 0 seconds, got {self.idle_timeout}", field="idle_timeout")
        if self.max_memory < 0:
            raise InputError(f"must be >= 0 bytes (0: half the host's memory), got {self.max_memory}",
                             field="max_memory")

    def memory_budget(self) -> int:
        """Bytes all sessions may take: ``max_memory``, or half of :func:`host_memory` when it is 0."""
        return self.max_memory or host_memory() // 2


#: Where a container's memory limit is (cgroup v2, then v1); ``max`` or a number above the host's means none.
CGROUP_MEMORY_LIMITS = (Path("/sys/fs/cgroup/memory.max"), Path("/sys/fs/cgroup/memory/memory.limit_in_bytes"))


def host_memory(cgroup_limits: tuple[Path, ...] = CGROUP_MEMORY_LIMITS) -> int:
    """The memory this process may use, in bytes: the host's physical memory (``sysconf``), or the limit
    of its cgroup (a container) when that is lower."""
    total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    for path in cgroup_limits:
        try:
            text = path.read_text().strip()
        except OSError:
            continue
        if text.isdigit():
            total = min(total, int(text))
    return total


#: The server's resident memory per session and frame pixel, by method: what one more open session of that
#: method adds once it has predicted (its history, the predictor's state and scratch arrays, the thread's
#: allocator arena), measured by ``python -m tools.bench_server_memory`` at 1280x720 and 1920x1080 (the
#: larger of the two, rounded up; the tables and commands: docs/results/2026-11-28-server-memory.md). The
#: shared-memory segment comes on top (``Layout.shm_size``: 29 to 54 bytes per pixel).
METHOD_BYTES_PER_PIXEL = {"repeat": 37, "reproject": 168, "flow2d": 271, "mvec": 353, "auto": 347, "decomp": 214,
                          "decomp2d": 207}


def session_footprint(method: str, layout: wire.Layout) -> int:
    """Estimated bytes a session of ``method`` takes with that segment: the method's measured bytes per pixel
    (:data:`METHOD_BYTES_PER_PIXEL`; the largest for a name not in it, which the registry then refuses)
    times the frame's pixels, plus the segment."""
    base = method_parts(method)[0].strip()
    per_pixel = METHOD_BYTES_PER_PIXEL.get(base, max(METHOD_BYTES_PER_PIXEL.values()))
    return per_pixel * layout.width * layout.height + layout.shm_size


def with_server_models(method: str, models: Optional[Path]) -> str:
    """``method`` with the server's own network files (``serve --models DIR``: ``flow3d.onnx`` /
    ``flow2d.onnx`` and ``infill.onnx`` there) for the DeCOMPnet methods; unchanged without ``models``."""
    base, options = method_parts(method)
    if models is None or base not in DECOMP_WEIGHTS:
        return method
    return method_with(base, options + [f"model={models / DECOMP_WEIGHTS[base]}",
                                        f"infill_model={models / 'infill.onnx'}"])


def check_models_dir(models: Path) -> Path:
    """``serve --models DIR``: an existing folder whose path can sit inside a method's options."""
    models = Path(models).resolve()
    if not models.is_dir():
        raise InputError("is not a folder", file=models, field="--models")
    if any(c in str(models) for c in ",[]="):
        raise InputError("must not contain ',', '[', ']' or '='", file=models, field="--models")
    return models


def check_remote_method(method: str, limits: ServerLimits) -> None:
    """A method string as a client may send it, refused by allow-list: each bracket option must be one of the
    method's options whose values name no file (``engine.predict.registry.names_no_file``: numbers,
    booleans, a closed set of words; free text such as decomp's ``model`` or flow2d's ``network`` is the
    server's own configuration, ``serve --models``), its value must parse, and ``threads`` stays within
    ``limits.max_threads``. A name that is no method is the registry's to refuse (it names no file either)."""
    base, parts = method_parts(method)
    kinds = method_options(base)
    if kinds is None:
        return
    allowed = [name for name, kind in kinds.items() if names_no_file(kind)]
    for part in parts:
        key, _, value = (x.strip() for x in part.partition("="))
        if key in kinds and not names_no_file(kinds[key]):
            raise _ProtocolError(Status.BAD_INPUT, f"method option '{key}' of {base} names a file: files are the "
                                                   "server's own configuration (serve --models), not a client's; "
                                                   f"a client may give {_listing(allowed)}")
        if key not in allowed:
            raise _ProtocolError(Status.BAD_INPUT, f"method option '{key}' is not an option of {base}; a client "
                                                   f"may give {_listing(allowed)}")
        try:
            parsed = parse_value(kinds[key], value, key)
        except InputError as exc:
            raise _ProtocolError(Status.BAD_INPUT, f"method option '{key}' of {base}: {exc.problem}") from None
        if key == "threads" and parsed > limits.max_threads:
            raise _ProtocolError(Status.BAD_INPUT, f"method option threads={value} exceeds the server's limit "
                                                   f"{limits.max_threads} (serve --max-threads)")


def _listing(options: list[str]) -> str:
    return ", ".join(options) if options else "no options"


class _ProtocolError(Exception):
    """A request that gets an error reply: status code and text."""

    def __init__(self, status: Status, text: str) -> None:
        super().__init__(text)
        self.status = status
        self.text = text


def _check_codes(label: str, fields) -> None:
    """BAD_INPUT naming the first of ``fields`` ((name, code, codes), ...) whose code is out of range."""
    for name, value, codes in fields:
        if value >= len(codes):
            names = ", ".join("default" if c is None else str(c) for c in codes)
            raise _ProtocolError(Status.BAD_INPUT, f"{label} '{name}': code {value} is not one of 0..{len(codes) - 1} "
                                                   f"({names})")


def parse_address(text: str) -> Address:
    """``unix:/path`` or a path -> Unix socket; ``tcp:PORT`` or ``tcp:127.0.0.1:PORT`` -> loopback TCP;
    ``default`` -> :func:`default_socket_path`."""
    if text.startswith("tcp:"):
        host, _, port = text[4:].rpartition(":")
        if host not in ("", "127.0.0.1", "localhost"):
            raise InputError(f"the server listens on 127.0.0.1 only, got host {host!r}", field="address")
        try:
            number = int(port)
        except ValueError:
            raise InputError(f"bad TCP port in {text!r}", field="address") from None
        if not 0 <= number <= 65535:
            raise InputError(f"TCP port must be 0..65535, got {number}", field="address")
        return ("127.0.0.1", number)
    if text in ("", "unix:", "default"):
        return default_socket_path()
    return Path(text[5:] if text.startswith("unix:") else text)


def format_address(address: Address) -> str:
    return f"tcp:{address[0]}:{address[1]}" if isinstance(address, tuple) else f"unix:{address}"


#: File descriptors one connection holds: its socket, its segment, and the next segment while a RESET that
#: changes the frame size replaces the first.
FDS_PER_CONNECTION = 3
#: Descriptors kept for the rest of the process, beyond those open when the server starts: network files
#: and caches opened while a method loads, a GL context, the accept loop's spare descriptor, stderr.
FD_HEADROOM = 32
#: ``accept()`` errors that mean the process or the host is out of descriptors or buffers: the pending
#: connection is refused and the accept loop backs off; every existing session keeps being served.
ACCEPT_EXHAUSTED = (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM)
#: ``accept()`` errors of the listening socket itself (closed, not a socket): the loop cannot go on.
ACCEPT_FATAL = (errno.EBADF, errno.EINVAL, errno.ENOTSOCK, errno.EOPNOTSUPP)
#: Back-off of the accept loop after an exhaustion error: first and longest pause, seconds.
ACCEPT_BACKOFF = (0.01, 0.5)


def open_descriptors() -> int:
    """File descriptors this process holds now (``/proc/self/fd``; 3, the standard streams, without /proc)."""
    try:
        return len(os.listdir("/proc/self/fd")) - 1  # listdir's own descriptor is in the listing
    except OSError:
        return 3


def ensure_fd_limit(max_connections: int, log: Callable[[str], None]) -> int:
    """Make room for ``max_connections`` connections in the open-file limit (``RLIMIT_NOFILE``); returns the
    descriptors needed.

    A connection holds :data:`FDS_PER_CONNECTION` descriptors, and the process keeps those open now plus
    :data:`FD_HEADROOM`. A soft limit below that is raised towards the hard limit (``log`` says so); a hard
    limit below it is an InputError naming ``--max-connections`` and the largest value that fits, so the
    server never starts with a cap its descriptors cannot hold (it would refuse connections under it)."""
    reserved = open_descriptors() + FD_HEADROOM
    needed = reserved + max_connections * FDS_PER_CONNECTION
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY or needed <= soft:
        return needed
    if hard != resource.RLIM_INFINITY and needed > hard:
        fits = max((hard - reserved) // FDS_PER_CONNECTION, 0)
        raise InputError(f"{max_connections} connections need {needed} file descriptors ({FDS_PER_CONNECTION} "
                         f"each, {reserved} for the process) but the open-file limit is {hard} (ulimit -n): "
                         f"give at most {fits}, or raise the limit", field="--max-connections")
    resource.setrlimit(resource.RLIMIT_NOFILE, (needed, hard))
    log(f"interleave serve: raised the open-file limit from {soft} to {needed} for {max_connections} connections")
    return needed


def _mib(size: int) -> str:
    return f"{size / 2**20:.1f}"


def _log(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def _open_spare() -> Optional[int]:
    """A descriptor held in reserve (``/dev/null``); None if even that cannot be opened now."""
    try:
        return os.open(os.devnull, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        return None


class _Segment:
    """A shared-memory segment owned by the server: created for a layout, closed (and unlinked) on release.

    ``anonymous``: a ``memfd`` with no name anywhere (the client gets its descriptor with SCM_RIGHTS),
    sealed against shrinking and growing; else a named POSIX segment ``/dev/shm/<name>``, random, created
    exclusively, readable and writable by the server's user only.
    The client maps it; the server never does. It reads the submitted frame with ``pread`` and writes the
    prediction with ``pwrite`` on the segment's file descriptor, so a client that shrinks a named segment
    (``ftruncate``) gets a BAD_INPUT answer (a short read) instead of killing the server with SIGBUS.
    """

    def __init__(self, config: SessionConfig, channels: int, width: int, height: int,
                 motion: Optional[MotionPlane] = None, anonymous: bool = False) -> None:
        self.path: Optional[Path] = None
        try:
            if anonymous:
                self.fd = os.memfd_create("interleave-segment", os.MFD_CLOEXEC | os.MFD_ALLOW_SEALING)
                name = ""
            else:
                self.fd, name = self._create_named()
                self.path = SHM_DIR / name[1:]
        except OSError as exc:
            if exc.errno in (errno.EMFILE, errno.ENFILE):
                raise _ProtocolError(Status.OVER_BUDGET, "the server is out of file descriptors for a shared-memory "
                                                         "segment; try again when other sessions have ended") from None
            raise _ProtocolError(Status.INTERNAL,
                                 f"could not create a shared-memory segment ({exc.strerror})") from None
        self.layout = wire.make_layout(name, width, height, channels, config.color_in, config.color_out, motion)
        try:
            os.ftruncate(self.fd, self.layout.shm_size)
            if anonymous:
                fcntl.fcntl(self.fd, fcntl.F_ADD_SEALS, fcntl.F_SEAL_SHRINK | fcntl.F_SEAL_GROW | fcntl.F_SEAL_SEAL)
        except OSError as exc:
            self.release()
            raise _ProtocolError(Status.INTERNAL, f"could not size the shared-memory segment ({exc.strerror})")
        self.anonymous = anonymous
        self.channels = channels
        self.config = config
        self.motion = motion

    @staticmethod
    def _create_named() -> tuple[int, str]:
        for _ in range(8):
            name = f"interleave-{os.getpid()}-{secrets.token_hex(8)}"
            try:
                return os.open(SHM_DIR / name, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600), "/" + name
            except FileExistsError:  # a name someone created first: draw another
                continue
        raise _ProtocolError(Status.INTERNAL, "could not create a shared-memory segment with a fresh name")

    @property
    def description(self) -> str:
        return self.layout.shm_name or "(anonymous memfd)"

    def read(self, offset: int, shape: tuple, dtype) -> np.ndarray:
        """A private copy of the region at ``offset``; BAD_INPUT if the client shrank the segment."""
        out = np.empty(shape, dtype=dtype)
        view = memoryview(out).cast("B")
        done = 0
        while done < out.nbytes:
            n = os.preadv(self.fd, [view[done:]], offset + done)
            if n <= 0:
                raise _ProtocolError(Status.BAD_INPUT, f"the shared-memory segment {self.description} holds "
                                                       f"{os.fstat(self.fd).st_size} bytes, fewer than its layout "
                                                       f"({self.layout.shm_size}): the client truncated it")
            done += n
        return out

    def write(self, offset: int, values: np.ndarray) -> None:
        """Write ``values`` (C-contiguous) at ``offset``."""
        view = memoryview(np.ascontiguousarray(values)).cast("B")
        done = 0
        while done < len(view):
            done += os.pwrite(self.fd, view[done:], offset + done)

    def release(self) -> None:
        try:
            os.close(self.fd)
        except OSError:
            pass
        if self.path is not None:
            try:
                os.unlink(self.path)
            except FileNotFoundError:
                pass


class _Connection:
    """One client: reads requests, answers them in order, owns the session and its segment."""

    def __init__(self, sock: socket.socket, server: "Server") -> None:
        self.sock = sock
        self.server = server
        self.session: Optional[Session] = None
        self.segment: Optional[_Segment] = None
        self.column_major = False
        self._header = bytearray(wire.HEADER.size)
        #: the segment's descriptor goes with this request's reply (SCM_RIGHTS): a layout of an anonymous segment
        self._reply_fd: Optional[int] = None

    # -- byte stream ------------------------------------------------------------------------------

    def _read_into(self, view: memoryview) -> int:
        got = 0
        while got < len(view):
            n = self.sock.recv_into(view[got:])
            if n == 0:
                break
            got += n
        return got

    def _send(self, type_: int, request_id: int, payload: bytes = b"", status: int = Status.OK,
              version: int = wire.VERSION_MIN, fd: Optional[int] = None) -> None:
        data = wire.pack_header(type_, request_id, len(payload), status, version) + payload
        if fd is None:
            self.sock.sendall(data)
            return
        sent = socket.send_fds(self.sock, [data], [fd])  # the descriptor rides on the reply's first bytes
        if sent < len(data):
            self.sock.sendall(data[sent:])

    def _send_error(self, type_: int, request_id: int, status: Status, text: str,
                    version: int = wire.VERSION_MIN) -> None:
        try:
            self._send(type_, request_id, text.encode("utf-8")[:4096], status, version)
        except OSError:
            pass

    # -- main loop --------------------------------------------------------------------------------

    def run(self) -> None:
        try:
            while not self.server.stopping:
                got = self._read_into(memoryview(self._header))
                if got == 0:
                    return  # clean end of stream between messages
                if got < wire.HEADER.size:
                    self._send_error(MessageType.ERROR, 0, Status.TRUNCATED,
                                     f"truncated header: {got} of {wire.HEADER.size} bytes")
                    return
                magic, version, type_, request_id, _, size = wire.HEADER.unpack(self._header)
                if magic != wire.MAGIC:
                    self._send_error(MessageType.ERROR, request_id, Status.BAD_MAGIC,
                                     f"bad magic 0x{magic:08x}, expected 0x{wire.MAGIC:08x} (b'INTL')")
                    return
                if version not in wire.VERSIONS:
                    self._send_error(MessageType.ERROR, request_id, Status.BAD_VERSION,
                                     f"protocol version {version} is not supported; this server speaks "
                                     f"{', '.join(map(str, wire.VERSIONS))}")
                    return
                reply_type = (type_ | MessageType.REPLY) & 0xFFFF
                if size > wire.MAX_PAYLOAD:
                    self._send_error(reply_type, request_id, Status.TOO_LARGE,
                                     f"payload_size {size} exceeds the limit {wire.MAX_PAYLOAD}", version)
                    return
                payload = bytearray(size)
                got = self._read_into(memoryview(payload))
                if got < size:
                    self._send_error(reply_type, request_id, Status.TRUNCATED,
                                     f"truncated message: {got} of {size} payload bytes before the stream ended",
                                     version)
                    return
                self._reply_fd = None
                try:
                    reply = self._handle(type_, bytes(payload), version)
                except _ProtocolError as exc:
                    self._send_error(reply_type, request_id, exc.status, exc.text, version)
                    continue
                except NotReadyError as exc:
                    self._send_error(reply_type, request_id, Status.NOT_READY, str(exc), version)
                    continue
                except InterleaveError as exc:
                    self._send_error(reply_type, request_id, Status.BAD_INPUT, str(exc), version)
                    continue
                except Exception as exc:  # noqa: BLE001 - the server must outlive any one request
                    self._send_error(reply_type, request_id, Status.INTERNAL, f"{type(exc).__name__}: {exc}",
                                     version)
                    continue
                self._send(reply_type, request_id, reply, version=version, fd=self._reply_fd)
                if type_ == MessageType.BYE:
                    return
        except OSError:
            return  # the peer went away (or the server is stopping)
        finally:
            self.close()

    def close(self) -> None:
        self._end_session()
        try:
            self.sock.close()
        except OSError:
            pass

    def _end_session(self) -> None:
        """Free the session, its segment and its share of the memory budget."""
        self.session = None
        if self.segment is not None:
            self.segment.release()
            self.server._untrack(self.segment)
            self.segment = None
        self.server._reserve(self, 0)

    def _bye(self, payload: bytes, version: int) -> bytes:
        self._end_session()  # before the reply: a client that saw it may count on the freed budget
        return b""

    # -- messages ---------------------------------------------------------------------------------

    def _handle(self, type_: int, payload: bytes, version: int) -> bytes:
        v2 = version >= 2  # version 2: an optional motion extension after the version-1 payload
        handlers: dict[int, tuple[tuple[int, ...], Callable[[bytes, int], bytes]]] = {
            MessageType.HELLO: ((wire.HELLO.size,) + ((wire.HELLO.size + wire.MOTION.size,) if v2 else ()),
                                self._hello),
            MessageType.SUBMIT: ((wire.FRAME.size,) + ((wire.FRAME.size + wire.SUBMIT_MOTION.size,) if v2 else ()),
                                 self._submit),
            MessageType.PREDICT: ((wire.FRAME.size,), self._predict),
            MessageType.RESET: ((wire.RESET.size,) + ((wire.RESET.size + wire.RESET_MOTION.size,) if v2 else ()),
                                self._reset),
            MessageType.BYE: ((0,), self._bye),
        }
        if type_ not in handlers:
            raise _ProtocolError(Status.UNKNOWN_TYPE, f"unknown message type {type_}; expected one of "
                                 + ", ".join(f"{t.name}={int(t)}" for t in MessageType if t < MessageType.REPLY))
        sizes, handler = handlers[type_]
        if len(payload) not in sizes:
            raise _ProtocolError(Status.BAD_SIZE, f"{MessageType(type_).name} takes a "
                                 f"{' or '.join(map(str, sizes))}-byte payload in protocol version {version}, "
                                 f"got {len(payload)}")
        if type_ in (MessageType.SUBMIT, MessageType.PREDICT, MessageType.RESET) and self.session is None:
            raise _ProtocolError(Status.NO_SESSION, f"{MessageType(type_).name} before HELLO: no session")
        return handler(payload, version)

    @staticmethod
    def _motion_fields(raw: bytes, width: int, height: int) -> tuple[dict, MotionPlane]:
        """il_motion -> SessionConfig's motion fields and the plane; BAD_INPUT naming the field."""
        (units, direction, y_axis, camera, missing, mw, mh, channels, fmt, _reserved,
         scale_x, scale_y) = wire.MOTION.unpack(raw)
        _check_codes("HELLO motion field", (("units", units, wire.MOTION_UNIT_CODES),
                                            ("direction", direction, wire.MOTION_DIRECTION_CODES),
                                            ("y_axis", y_axis, wire.MOTION_Y_CODES),
                                            ("camera", camera, wire.MOTION_CAMERA_CODES),
                                            ("missing", missing, wire.MOTION_MISSING_CODES),
                                            ("format", fmt, wire.MOTION_FORMATS)))
        if channels not in (2, 3, 4):
            raise _ProtocolError(Status.BAD_INPUT, f"HELLO motion field 'channels' must be 2, 3 or 4, got {channels}")
        if not (mw <= width and mh <= height) or (mw == 0) != (mh == 0):
            raise _ProtocolError(Status.BAD_INPUT, f"HELLO motion field 'width', 'height': the plane is {mw}x{mh}; "
                                                   f"it must be at most the frame's {width}x{height}, or 0x0 for "
                                                   "the frame's size")
        fields = dict(motion_units=wire.MOTION_UNIT_CODES[units],
                      motion_direction=wire.MOTION_DIRECTION_CODES[direction],
                      motion_y_up=wire.MOTION_Y_CODES[y_axis], motion_includes_camera=wire.MOTION_CAMERA_CODES[camera],
                      motion_missing=wire.MOTION_MISSING_CODES[missing],
                      motion_scale=(scale_x if scale_x != 0 else 1.0, scale_y if scale_y != 0 else 1.0))
        return fields, MotionPlane(mw, mh, channels, wire.MOTION_FORMATS[fmt])

    def _hello(self, payload: bytes, version: int) -> bytes:
        (engine, depth, color_in, color_out, width, height, _reserved, channels, flags, _,
         near, far, meters_per_unit, cut_translation, cut_rotation, method) = wire.HELLO.unpack(
            payload[:wire.HELLO.size])
        _check_codes("HELLO field", (("engine", engine, wire.ENGINE_CODES),
                                     ("depth_convention", depth, wire.DEPTH_CODES),
                                     ("color_in", color_in, wire.COLOR_CODES),
                                     ("color_out", color_out, wire.COLOR_CODES)))
        self._check_size(width, height)
        check_remote_method(wire.cstring(method) or "reproject", self.server.limits)
        if channels not in (3, 4):
            raise _ProtocolError(Status.BAD_INPUT, f"HELLO field 'channels' must be 3 or 4, got {channels}")
        if flags & ~wire.KNOWN_FLAGS:
            raise _ProtocolError(Status.BAD_INPUT,
                                 f"HELLO field 'flags' has unknown bits 0x{flags & ~wire.KNOWN_FLAGS:x}")
        motion_fields, plane = {}, None
        if len(payload) > wire.HELLO.size:
            motion_fields, plane = self._motion_fields(payload[wire.HELLO.size:], width, height)
        config = SessionConfig(
            engine=wire.ENGINE_CODES[engine], width=width, height=height, depth_convention=wire.DEPTH_CODES[depth],
            near=near, far=far, meters_per_unit=meters_per_unit, ndc_y_down=bool(flags & wire.FLAG_NDC_Y_DOWN),
            flip_rows=bool(flags & wire.FLAG_FLIP_ROWS), color_in=wire.COLOR_CODES[color_in],
            color_out=wire.COLOR_CODES[color_out], method=wire.cstring(method) or "reproject",
            cut_translation=cut_translation if cut_translation > 0 else SessionConfig.cut_translation,
            cut_rotation_deg=cut_rotation if cut_rotation > 0 else SessionConfig.cut_rotation_deg, **motion_fields)
        if plane is not None:
            config.motion_conventions()  # an engine without defaults (OpenGL) must state them now
        # version 3 over a Unix socket: an anonymous segment, its descriptor passed with the reply
        anonymous = version >= wire.VERSION_FD and self.sock.family == socket.AF_UNIX
        layout = wire.make_layout("", width, height, channels, config.color_in, config.color_out, plane)
        previous = self.server._reserve(self, session_footprint(config.method, layout))
        try:
            models = self.server.models
            session = Session(config, make_method=lambda name: make_predictor(with_server_models(name, models)),
                              backend=self.server.backend)
            self._replace_segment(_Segment(config, channels, width, height, plane, anonymous))
        except BaseException:
            self.server._reserve(self, previous)
            raise
        self.session = session
        self.column_major = bool(flags & wire.FLAG_COLUMN_MAJOR)
        return self._layout_reply(version)

    def _layout_reply(self, version: int) -> bytes:
        """The segment's il_layout (+ il_motion_layout); an anonymous segment's descriptor goes with it."""
        if self.segment.anonymous:
            self._reply_fd = self.segment.fd
        return self.segment.layout.pack(version)

    def _check_size(self, width: int, height: int) -> None:
        if not (1 <= width <= wire.MAX_SIDE and 1 <= height <= wire.MAX_SIDE):
            raise _ProtocolError(Status.BAD_INPUT, f"frame size {width}x{height} is outside 1..{wire.MAX_SIDE} pixels")
        if width * height > self.server.limits.max_pixels:
            raise _ProtocolError(Status.BAD_INPUT, f"frame size {width}x{height} exceeds the server's limit of "
                                                   f"{self.server.limits.max_pixels} pixels (serve --max-pixels)")

    def _replace_segment(self, segment: _Segment) -> None:
        old, self.segment = self.segment, segment
        self.server._track(segment)
        if old is not None:
            old.release()
            self.server._untrack(old)

    def _pose(self, payload: bytes):
        frame_id, time_s, *values = wire.FRAME.unpack(payload)
        view = np.array(values[:16], dtype=np.float64).reshape(4, 4)
        projection = np.array(values[16:], dtype=np.float64).reshape(4, 4)
        if self.column_major:
            view, projection = view.T, projection.T
        return frame_id, time_s, view, projection

    def _submit(self, payload: bytes, version: int) -> bytes:
        frame_id, time_s, view, projection = self._pose(payload[:wire.FRAME.size])
        seg, lay = self.segment, self.segment.layout
        flags = 0
        if len(payload) > wire.FRAME.size:
            flags, _reserved = wire.SUBMIT_MOTION.unpack(payload[wire.FRAME.size:])
        if flags & ~wire.KNOWN_SUBMIT_FLAGS:
            raise _ProtocolError(Status.BAD_INPUT, f"frame {frame_id}: SUBMIT motion field 'flags' has unknown bits "
                                                   f"0x{flags & ~wire.KNOWN_SUBMIT_FLAGS:x}")
        if flags and seg.motion is None:
            raise _ProtocolError(Status.BAD_INPUT, f"frame {frame_id}: SUBMIT carries motion vectors but the session "
                                                   "has no motion plane (HELLO without il_motion)")
        if flags == wire.SUBMIT_VALID:
            raise _ProtocolError(Status.BAD_INPUT, f"frame {frame_id}: SUBMIT has a valid mask without vectors")
        dtype = np.uint8 if seg.config.color_in == "srgb8" else np.float32
        color = seg.read(lay.color_in_offset, (lay.height, lay.width, seg.channels), dtype)
        depth = seg.read(lay.depth_offset, (lay.height, lay.width), np.float32)
        vectors = valid = None
        if flags & wire.SUBMIT_VECTORS:
            shape = (lay.motion_height, lay.motion_width)
            vectors = seg.read(lay.motion_offset, shape + (seg.motion.channels,),
                               np.float16 if seg.motion.format == "float16" else np.float32)
            if flags & wire.SUBMIT_VALID:
                valid = seg.read(lay.motion_valid_offset, shape, np.uint8) != 0
        result = self.session.submit(color, depth, view, projection, time_s, frame=frame_id, copy=False,
                                     motion_vectors=vectors, motion_valid=valid)
        return wire.SUBMIT_REPLY.pack(result.frame, wire.RESET_CODES.index(result.reset), result.history)

    def _predict(self, payload: bytes, version: int) -> bytes:
        frame_id, time_s, view, projection = self._pose(payload)
        start = time.perf_counter()
        out = self.session.predict(view, projection, time_s, frame=frame_id)
        seg, lay = self.segment, self.segment.layout
        dtype = np.uint8 if seg.config.color_out == "srgb8" else np.float32
        color = np.empty((lay.height, lay.width, seg.channels), dtype)
        color[..., :3] = out.color
        if seg.channels == 4:
            color[..., 3] = 255 if dtype == np.uint8 else 1.0
        seg.write(lay.color_out_offset, color)
        seg.write(lay.holes_offset, out.holes.astype(np.uint8))
        elapsed = 1e3 * (time.perf_counter() - start)
        return wire.PREDICT_REPLY.pack(out.frame, wire.FALLBACK_CODES.index(out.fallback), int(out.holes.sum()),
                                       elapsed, out.method.encode()[:31])

    def _reset(self, payload: bytes, version: int) -> bytes:
        width, height = wire.RESET.unpack(payload[:wire.RESET.size])
        session, plane = self.session, self.segment.motion
        width, height = width or session.width, height or session.height
        self._check_size(width, height)
        if len(payload) > wire.RESET.size:
            mw, mh = wire.RESET_MOTION.unpack(payload[wire.RESET.size:])
            if plane is None:
                raise _ProtocolError(Status.BAD_INPUT, "RESET gives a motion plane size but the session has no "
                                                       "motion plane (HELLO without il_motion)")
            plane = MotionPlane(mw, mh, plane.channels, plane.format)
        if plane is not None and (not (plane.width <= width and plane.height <= height)
                                  or (plane.width == 0) != (plane.height == 0)):
            raise _ProtocolError(Status.BAD_INPUT, f"RESET motion field 'width', 'height': the plane is "
                                                   f"{plane.width}x{plane.height}; it must be at most the frame's "
                                                   f"{width}x{height}, or 0x0 for the frame's size (RESET takes "
                                                   "il_reset_motion in version 2)")
        if (width, height) != (session.width, session.height) or plane != self.segment.motion:
            config, channels = session.config, self.segment.channels
            layout = wire.make_layout("", width, height, channels, config.color_in, config.color_out, plane)
            previous = self.server._reserve(self, session_footprint(config.method, layout))
            try:
                segment = _Segment(config, channels, width, height, plane, self.segment.anonymous)
            except BaseException:
                self.server._reserve(self, previous)
                raise
            session.reset(width=width, height=height)
            self._replace_segment(segment)
        else:
            session.reset()
        return self._layout_reply(version)




class Server:
    """Listens on ``address`` (a Unix socket path, or ("127.0.0.1", port)) and serves sessions.

    ``serve_forever()`` returns after :meth:`stop`; everything it created is released on return.
    """

    def __init__(self, address: Address, limits: ServerLimits = ServerLimits(),
                 models: Optional[Path] = None, backend: str = "auto",
                 log: Callable[[str], None] = _log) -> None:
        self.limits = limits
        self.log = log
        self.models = None if models is None else check_models_dir(models)
        self.backend = resolve_backend(backend)  # before listening: 'gl' without a GL context fails here
        ensure_fd_limit(limits.max_connections, log)
        if isinstance(address, tuple):
            host, port = address
            if host not in ("127.0.0.1", "localhost"):
                raise InputError(f"the server listens on 127.0.0.1 only, got {host!r}", field="address")
            self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._listener.bind(("127.0.0.1", int(port)))
            self.address: Address = self._listener.getsockname()
            self._path: Optional[Path] = None
        else:
            path = Path(address)
            _remove_stale_socket(path)
            self._listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            self._listener.bind(str(path))
            self.address = path
            self._path = path
        self._listener.listen(16)
        self._listener.settimeout(0.1)
        self._spare = _open_spare()  # closed for a moment to refuse a connection when descriptors run out
        self._exhausted = False
        self.stopping = False
        self._lock = threading.Lock()
        self._connections: dict[_Connection, threading.Thread] = {}
        self._segments: set[_Segment] = set()
        self.memory_budget = limits.memory_budget()
        self._reserved: dict[_Connection, int] = {}

    def _reserve(self, conn: "_Connection", size: int) -> int:
        """Set the estimated bytes of ``conn``'s session to ``size`` (0: none); returns its previous amount.
        OVER_BUDGET if the sessions together would pass the memory budget (``serve --max-memory``)."""
        with self._lock:
            previous = self._reserved.get(conn, 0)
            others = sum(self._reserved.values()) - previous
            if size > previous and others + size > self.memory_budget:
                raise _ProtocolError(Status.OVER_BUDGET, f"this session needs about {_mib(size)} MiB and the open "
                                                         f"sessions hold {_mib(others)} MiB of the server's memory "
                                                         f"budget of {_mib(self.memory_budget)} MiB (serve "
                                                         f"--max-memory): try a smaller frame or a lighter method, "
                                                         f"or later")
            if size:
                self._reserved[conn] = size
            else:
                self._reserved.pop(conn, None)
            return previous

    def reserved_memory(self) -> int:
        """Estimated bytes of the open sessions (:func:`session_footprint`)."""
        with self._lock:
            return sum(self._reserved.values())

    def _track(self, segment: _Segment) -> None:
        with self._lock:
            self._segments.add(segment)

    def _untrack(self, segment: _Segment) -> None:
        with self._lock:
            self._segments.discard(segment)

    def segment_names(self) -> list[str]:
        """Names of the named shared-memory segments held now (POSIX names, leading slash); anonymous ones
        have none."""
        with self._lock:
            return sorted(s.layout.shm_name for s in self._segments if not s.anonymous)

    def serve_forever(self) -> None:
        """Accept connections until :meth:`stop`. An ``accept()`` that fails for want of descriptors or
        buffers (:data:`ACCEPT_EXHAUSTED`) refuses the pending connection with the spare descriptor, and
        backs off (10 ms doubling to 0.5 s) when even that fails, while the existing sessions go on; an
        aborted connection is skipped."""
        backoff = 0.0
        try:
            while not self.stopping:
                try:
                    sock, _ = self._listener.accept()
                except socket.timeout:
                    continue
                except OSError as exc:
                    if self.stopping or exc.errno in ACCEPT_FATAL:
                        if self.stopping:
                            break
                        raise
                    if exc.errno in ACCEPT_EXHAUSTED and not self._refuse_pending(exc):
                        backoff = min(max(2 * backoff, ACCEPT_BACKOFF[0]), ACCEPT_BACKOFF[1])
                        time.sleep(backoff)
                    continue  # ECONNABORTED, EPROTO, EPERM (a firewall), EINTR...: that peer only
                backoff = 0.0
                if self._exhausted:
                    self._exhausted = False
                    self.log("interleave serve: accepting connections again")
                self._start_connection(sock)
        finally:
            self._shutdown()

    def _start_connection(self, sock: socket.socket) -> None:
        with self._lock:
            full = len(self._connections) >= self.limits.max_connections
        if full:  # over the limit: closed at once, before it can hold a thread
            sock.close()
            return
        sock.settimeout(self.limits.idle_timeout or None)  # a silent peer is dropped (socket.timeout)
        if sock.family == socket.AF_INET:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn = _Connection(sock, self)
        thread = threading.Thread(target=self._run_connection, args=(conn,), daemon=True,
                                  name="interleave-connection")
        with self._lock:
            self._connections[conn] = thread
        try:
            thread.start()
        except RuntimeError:  # no thread to be had: refused like a connection over the cap
            with self._lock:
                self._connections.pop(conn, None)
            sock.close()

    def _refuse_pending(self, exc: OSError) -> bool:
        """Out of descriptors: free the spare one, accept the waiting connection and close it at once (its
        client sees the connection closed instead of waiting in the backlog), then take the spare back.
        False if no connection could be taken even so (no spare, or the host itself is out)."""
        if not self._exhausted:
            self._exhausted = True
            self.log(f"interleave serve: cannot accept a connection ({exc.strerror}); refusing new connections "
                     f"until descriptors are free, serving the {len(self._connections)} open ones")
        if self._spare is None:
            self._spare = _open_spare()
            return False
        os.close(self._spare)
        try:
            sock, _ = self._listener.accept()
            sock.close()
            refused = True
        except OSError:
            refused = False
        self._spare = _open_spare()
        return refused

    def _run_connection(self, conn: _Connection) -> None:
        try:
            conn.run()
        finally:
            with self._lock:
                self._connections.pop(conn, None)

    def stop(self) -> None:
        """Ask ``serve_forever`` to return (safe from any thread and from signal handlers)."""
        self.stopping = True

    def _shutdown(self) -> None:
        self.stopping = True
        try:
            self._listener.close()
        except OSError:
            pass
        if self._spare is not None:
            os.close(self._spare)
            self._spare = None
        with self._lock:
            connections = dict(self._connections)
        for conn in connections:
            try:
                conn.sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        for thread in connections.values():
            thread.join(timeout=5.0)
        with self._lock:
            segments, self._segments = list(self._segments), set()
        for segment in segments:
            segment.release()
        if self._path is not None:
            try:
                self._path.unlink()
            except FileNotFoundError:
                pass


def default_socket_path(tmp: Path = Path("/tmp")) -> Path:
    """The default socket: ``$XDG_RUNTIME_DIR/interleave.sock`` (a folder only its user can enter), else
    ``/tmp/interleave-<uid>/interleave.sock`` in a folder made with mode 0700. A folder of that name that is
    not this user's own, or that others can write into, is refused (another user squatting the name)."""
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    if runtime and Path(runtime).is_dir():
        folder = Path(runtime)
    else:
        folder = Path(tmp) / f"interleave-{os.getuid()}"
        try:
            folder.mkdir(mode=0o700)
        except FileExistsError:
            pass
    info = os.lstat(folder)
    if not stat.S_ISDIR(info.st_mode) or info.st_uid != os.getuid() or info.st_mode & 0o022:
        raise InputError("is not a folder of this user's that only it can write into", file=folder,
                         field="address")
    return folder / "interleave.sock"


def _remove_stale_socket(path: Path) -> None:
    """Remove a socket file that nobody listens on; refuse to replace a live server, a non-socket file or
    a socket file of another user."""
    if not path.exists():
        return
    if not stat.S_ISSOCK(path.stat().st_mode):
        raise InputError("exists and is not a socket", file=path, field="address")
    if path.stat().st_uid != os.getuid():
        raise InputError("is another user's socket", file=path, field="address")
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        probe.connect(str(path))
    except OSError:
        path.unlink()
        return
    finally:
        probe.close()
    raise InputError("another server is listening there", file=path, field="address")


def _announce(text: str) -> None:
    print(text, flush=True)


def serve(address: Address, limits: ServerLimits = ServerLimits(), models: Optional[Path] = None, *,
          announce: Callable[[str], None] = _announce, backend: str = "auto") -> None:
    """Run a server until SIGINT or SIGTERM; prints ``listening on <address>`` once it accepts connections.
    ``models``: the folder of the DeCOMPnet networks its sessions use (default: ``engine/weights``);
    ``backend``: where its sessions' warps run (``engine.geometry.backends.resolve_backend``)."""
    try:
        server = Server(address, limits, models, backend)
    except OSError as exc:
        raise InterleaveError(f"cannot listen on {format_address(address)}: {exc}") from None
    previous = {sig: signal.signal(sig, lambda *_: server.stop()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        announce(f"interleave serve: listening on {format_address(server.address)}")
        server.serve_forever()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


__all__ = ["Server", "ServerLimits", "serve", "parse_address", "format_address", "check_remote_method",
           "default_socket_path"]
