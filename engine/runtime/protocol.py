"""The wire format of `interleave serve` (protocol versions 1 to 3), in one place for server and client.

Every message, request or reply, is a fixed 24-byte little-endian header followed by ``payload_size``
bytes. Pixels never travel over the socket: the server creates one shared-memory segment per session and
says where in it the client writes colour, depth (and motion vectors) and reads the prediction
(``LAYOUT``). ``docs/server.md`` describes the exchange; ``engine/runtime/include/interleave_protocol.h``
states the same layout for C and C++ clients, and ``tests/runtime/test_server.py`` checks the two agree.

Versions: a request's header carries the version it is written in and its reply carries the same one, so
a version-1 client is answered exactly as before. Version 2 adds motion vectors, each as an optional
extension appended to a version-1 payload (the payload size says whether it is there): HELLO + ``MOTION``
(the vectors' conventions and plane), SUBMIT + ``SUBMIT_MOTION`` (this frame's vectors are in the plane),
RESET + ``RESET_MOTION`` (the plane's new size), and the layout reply + ``MOTION_LAYOUT`` (where the plane
is) for a session that has one. Version 1 takes the version-1 sizes only. Version 3 has version 2's
messages and changes one thing, over a Unix socket only: the segment is an anonymous ``memfd`` that no
other process can look up by name; ``il_layout.shm_name`` is empty and the segment's file descriptor
arrives as SCM_RIGHTS ancillary data with the reply that carries the layout (HELLO's and RESET's). Over
TCP, and for versions 1 and 2, the segment is a named POSIX one (``/dev/shm/<name>``).

Matrices are 16 float64 in row-major order (``M[row][col]`` at ``4 * row + col``) unless the session was
opened with ``FLAG_COLUMN_MAJOR`` (GLM, Unity ``Matrix4x4``, Godot ``Projection`` memory order).
"""
from __future__ import annotations

import enum
import struct
from dataclasses import dataclass
from typing import Optional

from engine.conventions import DEPTH_CONVENTIONS, MOTION_DIRECTIONS, MOTION_UNITS
from engine.runtime.session import COLOR_SPACES, ENGINES, FALLBACK_REASONS, MOTION_MISSING, RESET_REASONS

#: b"INTL" read as a little-endian uint32: the first four bytes of every message.
MAGIC = 0x4C544E49
#: The newest protocol version (what the reference client writes).
VERSION = 3
#: Every version the server answers; a reply carries its request's version.
VERSIONS = (1, 2, 3)
#: The first version whose layout replies over a Unix socket pass an anonymous segment's descriptor.
VERSION_FD = 3
#: The version of the server's replies to a request whose header it cannot trust (bad magic, bad version):
#: the one every client reads.
VERSION_MIN = 1
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
#: struct il_layout: shm_name[64] (empty: the segment's descriptor came with the reply); shm_size,
#: color_in_offset, depth_offset, color_out_offset, holes_offset; width, height.
LAYOUT = struct.Struct("<64s5Q2I")
#: struct il_frame (SUBMIT and PREDICT): frame_id, time, view[16], projection[16].
FRAME = struct.Struct("<Qd16d16d")
#: struct il_submit_reply: frame, reset, history.
SUBMIT_REPLY = struct.Struct("<QII")
#: struct il_predict_reply: frame, fallback, holes, elapsed_ms, method[32].
PREDICT_REPLY = struct.Struct("<QIId32s")
#: struct il_reset: width, height (0 = keep).
RESET = struct.Struct("<II")
#: struct il_motion (version 2, after il_hello): units, direction, y_axis, camera, missing (codes, 0 = the
#: engine's default), width, height (the plane; 0 = the frame's), channels, format, reserved; scale_x,
#: scale_y (0 = 1).
MOTION = struct.Struct("<10I2d")
#: struct il_submit_motion (version 2, after il_frame in SUBMIT): flags (SUBMIT_*), reserved.
SUBMIT_MOTION = struct.Struct("<II")
#: struct il_reset_motion (version 2, after il_reset): the plane's new width, height (0 = the frame's).
RESET_MOTION = struct.Struct("<II")
#: struct il_motion_layout (version 2, after il_layout in a session with a plane): motion_offset,
#: motion_valid_offset; width, height of the plane.
MOTION_LAYOUT = struct.Struct("<2Q2I")

#: Bits of il_hello.flags.
FLAG_FLIP_ROWS = 1
FLAG_NDC_Y_DOWN = 2
FLAG_COLUMN_MAJOR = 4
KNOWN_FLAGS = FLAG_FLIP_ROWS | FLAG_NDC_Y_DOWN | FLAG_COLUMN_MAJOR

#: Bits of il_submit_motion.flags: the plane holds this frame's vectors; the valid plane holds its mask.
SUBMIT_VECTORS = 1
SUBMIT_VALID = 2
KNOWN_SUBMIT_FLAGS = SUBMIT_VECTORS | SUBMIT_VALID


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
    OVER_BUDGET = 11    # the session would pass the server's memory budget (serve --max-memory) or it is out
                        # of file descriptors; nothing changed, the connection stays usable: retry smaller or later


#: Statuses after which the server closes the connection (the byte stream cannot be trusted any more).
FATAL = (Status.BAD_MAGIC, Status.BAD_VERSION, Status.TOO_LARGE, Status.TRUNCATED)

#: Enumerations carried as uint32 indices: il_hello.engine, .depth_convention, .color_in / .color_out,
#: il_submit_reply.reset (0 = none) and il_predict_reply.fallback (0 = none).
ENGINE_CODES = ENGINES
DEPTH_CODES = DEPTH_CONVENTIONS
COLOR_CODES = COLOR_SPACES
RESET_CODES = (None,) + RESET_REASONS
FALLBACK_CODES = (None,) + FALLBACK_REASONS
#: il_motion codes: index 0 is the engine's default (SessionConfig's "" / None), then the values.
MOTION_UNIT_CODES = ("",) + MOTION_UNITS
MOTION_DIRECTION_CODES = ("",) + MOTION_DIRECTIONS
MOTION_Y_CODES = (None, False, True)          # 1: y points down the picture, 2: up
MOTION_CAMERA_CODES = (None, True, False)     # 1: camera motion included, 2: object motion only
MOTION_MISSING_CODES = ("",) + MOTION_MISSING
#: il_motion.format: the plane's element type.
MOTION_FORMATS = ("float32", "float16")


def pack_header(type_: int, request_id: int, payload_size: int, status: int = 0, version: int = VERSION) -> bytes:
    return HEADER.pack(MAGIC, version, type_, request_id, status, payload_size)


def cstring(raw: bytes) -> str:
    """A NUL-terminated fixed-size char field as text."""
    return raw.split(b"\0", 1)[0].decode("utf-8", errors="replace")


@dataclass(frozen=True)
class MotionPlane:
    """The motion-vector plane a session asks for (il_motion): its size in pixels (0 = the frame's; at
    most the frame's), ``channels`` interleaved per pixel (2, 3 or 4; x and y are the first two: the RG
    of an RGB(A) texture) and the element ``format`` ("float32" or "float16")."""

    width: int = 0
    height: int = 0
    channels: int = 2
    format: str = "float32"

    def size(self, frame_width: int, frame_height: int) -> tuple[int, int]:
        """(width, height) of the plane for a frame of that size."""
        return self.width or frame_width, self.height or frame_height

    @property
    def itemsize(self) -> int:
        return 2 if self.format == "float16" else 4


@dataclass(frozen=True)
class Layout:
    """Where the pixels of a session live in its shared-memory segment (byte offsets; rows top first).

    color_in: (H, W, channels) float32, or uint8 for "srgb8"; depth: (H, W) float32; color_out: like
    color_in but in the session's color_out encoding; holes: (H, W) uint8, 1 where no pixel landed.
    Sessions with a motion plane (version 2) also have motion: (motion_height, motion_width, channels) in
    the plane's format, and motion_valid: (motion_height, motion_width) uint8, non-zero where a pixel has
    a vector; ``motion_width`` is 0 without a plane.
    """

    shm_name: str
    shm_size: int
    color_in_offset: int
    depth_offset: int
    color_out_offset: int
    holes_offset: int
    width: int
    height: int
    motion_offset: int = 0
    motion_valid_offset: int = 0
    motion_width: int = 0
    motion_height: int = 0

    @property
    def has_motion(self) -> bool:
        return self.motion_width > 0

    @property
    def anonymous(self) -> bool:
        """The segment has no name: its descriptor came with the reply (version 3 over a Unix socket)."""
        return not self.shm_name

    def pack(self, version: int = VERSION) -> bytes:
        """il_layout, followed by il_motion_layout for a session with a plane answered in version 2."""
        base = LAYOUT.pack(self.shm_name.encode(), self.shm_size, self.color_in_offset, self.depth_offset,
                           self.color_out_offset, self.holes_offset, self.width, self.height)
        if version < 2 or not self.has_motion:
            return base
        return base + MOTION_LAYOUT.pack(self.motion_offset, self.motion_valid_offset, self.motion_width,
                                         self.motion_height)

    @classmethod
    def unpack(cls, payload: bytes) -> "Layout":
        name, *rest = LAYOUT.unpack(payload[:LAYOUT.size])
        motion = MOTION_LAYOUT.unpack(payload[LAYOUT.size:]) if len(payload) > LAYOUT.size else ()
        return cls(cstring(name), *rest, *motion)


def color_itemsize(space: str) -> int:
    """Bytes per colour channel in shared memory: 1 for "srgb8", 4 (float32) otherwise."""
    return 1 if space == "srgb8" else 4


def _align(offset: int) -> int:
    return -(-offset // ALIGNMENT) * ALIGNMENT


def make_layout(shm_name: str, width: int, height: int, channels: int, color_in: str, color_out: str,
                motion: Optional[MotionPlane] = None) -> Layout:
    """The region offsets for one frame size: colour in, depth, colour out, holes (and, with a motion
    plane, motion vectors and their valid mask after them), each 64-byte aligned. Without a plane the
    layout is version 1's."""
    pixels = width * height
    color_in_offset = 0
    depth_offset = _align(color_in_offset + pixels * channels * color_itemsize(color_in))
    color_out_offset = _align(depth_offset + pixels * 4)
    holes_offset = _align(color_out_offset + pixels * channels * color_itemsize(color_out))
    size = _align(holes_offset + pixels)
    if motion is None:
        return Layout(shm_name, size, color_in_offset, depth_offset, color_out_offset, holes_offset, width, height)
    mw, mh = motion.size(width, height)
    motion_offset = size
    valid_offset = _align(motion_offset + mw * mh * motion.channels * motion.itemsize)
    size = _align(valid_offset + mw * mh)
    return Layout(shm_name, size, color_in_offset, depth_offset, color_out_offset, holes_offset, width, height,
                  motion_offset, valid_offset, mw, mh)
