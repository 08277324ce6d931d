"""The wire format of `interleave serve` (protocol version 1), in one place for server and client.

Every message, request or reply, is a fixed 24-byte little-endian header followed by ``payload_size``
bytes. Pixels never travel over the socket: the server creates one POSIX shared-memory segment per
session and says where in it the client writes colour and depth and reads the prediction (``LAYOUT``).
``docs/server.md`` describes the exchange; ``engine/runtime/include/interleave_protocol.h`` states the same
layout for C and C++ clients, and ``tests/runtime/test_server.py`` checks the two agree.

Matrices are 16 float64 in row-major order (``M[row][col]`` at ``4 * row + col``) unless the session was
opened with ``FLAG_COLUMN_MAJOR`` (GLM, Unity ``Matrix4x4``, Godot ``Projection`` memory order).
"""
from __future__ import annotations

import enum
import struct
from dataclasses import dataclass

from engine.conventions import DEPTH_CONVENTIONS
from engine.runtime.session import COLOR_SPACES, ENGINES, FALLBACK_REASONS, RESET_REASONS

#: b"INTL" read as a little-endian uint32: the first four bytes of every message.
MAGIC = 0x4C544E49
VERSION = 1
#: Largest payload accepted; a bigger ``payload_size`` closes the connection (frames go through shared memory).
MAX_PAYLOAD = 1 << 16
#: Largest frame width or height accepted (pixels).
MAX_SIDE = 16384
#: Offsets of the regions inside the shared-memory segment are multiples of this.
ALIGNMENT = 64

#: struct il_header: magic, version, type, request_id, status, payload_size.
HEADER = struct.Struct("<IHHIIQ")
#: struct il_hello: engine, depth_convention, color_in, color_out, width, height, reserved0 (ignored; was k),
#: channels, flags, reserved; near, far, meters_per_unit, cut_translation, cut_rotation_deg; method[64].
HELLO = struct.Struct("<10I5d64s")
#: struct il_layout: shm_name[64]; shm_size, color_in_offset, depth_offset, color_out_offset,
#: holes_offset; width, height.
LAYOUT = struct.Struct("<64s5Q2I")
#: struct il_frame (SUBMIT and PREDICT): frame_id, time, view[16], projection[16].
FRAME = struct.Struct("<Qd16d16d")
#: struct il_submit_reply: frame, reset, history.
SUBMIT_REPLY = struct.Struct("<QII")
#: struct il_predict_reply: frame, fallback, holes, elapsed_ms, method[32].
PREDICT_REPLY = struct.Struct("<QIId32s")
#: struct il_reset: width, height (0 = keep).
RESET = struct.Struct("<II")

#: Bits of il_hello.flags.
FLAG_FLIP_ROWS = 1
FLAG_NDC_Y_DOWN = 2
FLAG_COLUMN_MAJOR = 4
KNOWN_FLAGS = FLAG_FLIP_ROWS | FLAG_NDC_Y_DOWN | FLAG_COLUMN_MAJOR


class MessageType(enum.IntEnum):
    """il_header.type of requests; a reply carries the request's type | REPLY."""

    HELLO = 1
    SUBMIT = 2
    PREDICT = 3
    RESET = 4
    BYE = 5
    REPLY = 0x8000
    #: reply to a message whose header could not be read (bad magic or version)
    ERROR = 0xFFFF


class Status(enum.IntEnum):
    """il_header.status of replies (0 in requests). Non-zero replies carry UTF-8 error text."""

    OK = 0
    BAD_MAGIC = 1       # connection closed after the reply
    BAD_VERSION = 2     # connection closed after the reply
    UNKNOWN_TYPE = 3
    BAD_SIZE = 4        # payload_size does not match the message type
    TOO_LARGE = 5       # payload_size > MAX_PAYLOAD; connection closed after the reply
    TRUNCATED = 6       # the stream ended inside a message; connection closed after the reply
    NO_SESSION = 7      # SUBMIT / PREDICT / RESET before HELLO
    BAD_INPUT = 8       # invalid values (NaN pixels, non-rigid pose, unknown method, ...): text names the frame
    NOT_READY = 9       # PREDICT before any SUBMIT since HELLO or RESET
    INTERNAL = 10       # unexpected server error; the connection stays usable


#: Statuses after which the server closes the connection (the byte stream cannot be trusted any more).
FATAL = (Status.BAD_MAGIC, Status.BAD_VERSION, Status.TOO_LARGE, Status.TRUNCATED)

#: Enumerations carried as uint32 indices: il_hello.engine, .depth_convention, .color_in / .color_out,
#: il_submit_reply.reset (0 = none) and il_predict_reply.fallback (0 = none).
ENGINE_CODES = ENGINES
DEPTH_CODES = DEPTH_CONVENTIONS
COLOR_CODES = COLOR_SPACES
RESET_CODES = (None,) + RESET_REASONS
FALLBACK_CODES = (None,) + FALLBACK_REASONS


def pack_header(type_: int, request_id: int, payload_size: int, status: int = 0) -> bytes:
    return HEADER.pack(MAGIC, VERSION, type_, request_id, status, payload_size)


def cstring(raw: bytes) -> str:
    """A NUL-terminated fixed-size char field as text."""
    return raw.split(b"\0", 1)[0].decode("utf-8", errors="replace")


@dataclass(frozen=True)
class Layout:
    """Where the pixels of a session live in its shared-memory segment (byte offsets; rows top first).

    color_in: (H, W, channels) float32, or uint8 for "srgb8"; depth: (H, W) float32; color_out: like
    color_in but in the session's color_out encoding; holes: (H, W) uint8, 1 where no pixel landed.
    """

    shm_name: str
    shm_size: int
    color_in_offset: int
    depth_offset: int
    color_out_offset: int
    holes_offset: int
    width: int
    height: int

    def pack(self) -> bytes:
        return LAYOUT.pack(self.shm_name.encode(), self.shm_size, self.color_in_offset, self.depth_offset,
                           self.color_out_offset, self.holes_offset, self.width, self.height)

    @classmethod
    def unpack(cls, payload: bytes) -> "Layout":
        name, *rest = LAYOUT.unpack(payload)
        return cls(cstring(name), *rest)


def color_itemsize(space: str) -> int:
    """Bytes per colour channel in shared memory: 1 for "srgb8", 4 (float32) otherwise."""
    return 1 if space == "srgb8" else 4


def _align(offset: int) -> int:
    return -(-offset // ALIGNMENT) * ALIGNMENT


def make_layout(shm_name: str, width: int, height: int, channels: int, color_in: str, color_out: str) -> Layout:
    """The region offsets for one frame size: colour in, depth, colour out, holes, each 64-byte aligned."""
    pixels = width * height
    color_in_offset = 0
    depth_offset = _align(color_in_offset + pixels * channels * color_itemsize(color_in))
    color_out_offset = _align(depth_offset + pixels * 4)
    holes_offset = _align(color_out_offset + pixels * channels * color_itemsize(color_out))
    size = _align(holes_offset + pixels)
    return Layout(shm_name, size, color_in_offset, depth_offset, color_out_offset, holes_offset, width, height)
