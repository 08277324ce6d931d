"""Frames handed out as GPU textures: the output side of the GPU path (``Session.predict_texture``, ``play``).

A frame's colour buffer on the shared context (a ``GlPrediction``'s, a ``GlImage``'s, or a host frame uploaded
once) is stored by a compute pass (``color_to_texture``) into a texture that a ``TextureRing`` owns and hands out
as a ``FrameTexture``: what a renderer samples or draws, without a readback.

The contract (docs/gpu.md, "Frames handed out as textures"):

- **context**: the texture is an object of the frame backend's context (``shared_context()``, an EGL context
  on its own thread): draw or copy it from that context (``FrameTexture.gl.call``); ``glo`` is its GL name
  there. It is not shared with another context (a window's) yet.
- **formats** (``TEXTURE_FORMATS``): ``rgba16f`` (default; linear Rec.709, the float colour converted to half
  floats, rounded or truncated as the driver does: GL leaves that open, llvmpipe truncates; relative error
  < 2^-10 above 2^-14), ``rgba32f`` (linear, the float colour exactly), ``srgb8`` (RGBA8 holding the
  8-bit sRGB codes of ``engine.geometry.encoding.encode8``, bit for bit; the texture's internal format is
  GL_RGBA8, so sample it without sRGB decoding and show the values as they are). Alpha is 1.
- **rows**: GL's: texel row 0 is the picture's bottom row (drawn with v = 0 at the bottom, it shows upright);
  ``read()`` returns rows top to bottom like every host array.
- **lifetime**: the ring owns the textures. A handle stays valid until ``count`` (2) later frames were written
  into its ring (double-buffered: show one while the next is made), or ``release()``; afterwards ``valid`` is
  False and ``read()`` refuses. A size or format change makes new textures; the old ones go when their ring
  slot is reused.
"""
from __future__ import annotations

import weakref
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from engine.core.checks import checked_size
from engine.core.colorspace import ENCODE8_BUCKETS
from engine.core.errors import InputError
from engine.geometry.backends.gl.context import GlContext, shared_context
from engine.geometry.backends.gl.frame import encode8_table_rows

__all__ = ["TEXTURE_FORMATS", "FrameTexture", "TextureRing"]

#: Texture formats a frame is handed out in: name -> (moderngl dtype, GLSL image format, colour space).
TEXTURE_FORMATS = {"rgba16f": ("f2", "rgba16f", "linear"), "rgba32f": ("f4", "rgba32f", "linear"),
                   "srgb8": ("f1", "rgba8", "srgb")}


@dataclass(eq=False)
class FrameTexture:
    """A frame as a texture of the shared GL context (module docstring for the contract): ``texture`` (the
    moderngl object), ``glo`` (its GL name), ``size`` (width, height), ``format`` (``TEXTURE_FORMATS``),
    ``color_space`` (``linear`` or ``srgb``: what the values are), ``serial`` (the ring's count of frames when it
    was written)."""

    texture: object = field(repr=False)
    glo: int
    size: tuple[int, int]
    format: str
    color_space: str
    serial: int
    gl: GlContext = field(repr=False)
    ring: "TextureRing" = field(repr=False)

    @property
    def valid(self) -> bool:
        """Whether the texture still holds this frame (its ring slot was not reused, nor released)."""
        return self.ring.holds(self)

    def read(self) -> np.ndarray:
        """The texture on the host, rows top to bottom: (H, W, 3) float32 (linear formats) or uint8 codes
        (``srgb8``). For tests and recordings: a display path draws the texture instead."""
        if not self.valid:
            raise InputError("the texture was reused by a later frame or released: a handle is valid until two "
                             "more frames are written into its ring", field="texture")
        w, h = self.size
        data = self.gl.call(lambda: self.texture.read())
        image = np.frombuffer(data, TEXTURE_DTYPES[self.format]).reshape(h, w, 4)[::-1, :, :3]
        return np.ascontiguousarray(image, dtype=np.uint8 if self.format == "srgb8" else np.float32)

    def release(self) -> None:
        """Give the texture back to its ring now (the handle turns invalid)."""
        self.ring.release(self)


#: numpy dtype of a texture's texels as ``Texture.read`` returns them.
TEXTURE_DTYPES = {"rgba16f": np.float16, "rgba32f": np.float32, "srgb8": np.uint8}


def _discard_ring(gl: GlContext, slots: list, table: list) -> None:
    """Free a dropped ring's textures and table on the GL thread, before its next call."""
    gl.discard([kept[0] for kept in slots if kept is not None] + list(table))


class TextureRing:
    """``count`` textures on ``gl`` (the shared context by default) that frames are written into in turn
    (``write``; a handle stays valid for ``count`` - 1 later writes, module docstring). Thread-safe through the
    context's thread; release it (or its owner) when done."""

    def __init__(self, gl: Optional[GlContext] = None, count: int = 2) -> None:
        if count < 1:
            raise InputError(f"must be >= 1, got {count}", field="count")
        self.gl = shared_context() if gl is None else gl
        self.count = int(count)
        self._slots: list = [None] * self.count  # (texture, size, format) per slot
        self._serials = [-1] * self.count  # the serial each slot holds (-1: none)
        self._serial = 0
        self._table: list = []  # the encode8 table's buffer, once made
        # a ring dropped without release_all gives its textures back on the GL thread (as dropped buffers are)
        weakref.finalize(self, _discard_ring, self.gl, self._slots, self._table)

    def holds(self, handle: FrameTexture) -> bool:
        slot = handle.serial % self.count
        return handle.ring is self and self._serials[slot] == handle.serial

    def release(self, handle: FrameTexture) -> None:
        if self.holds(handle):
            self._serials[handle.serial % self.count] = -1

    def write(self, color, shape: tuple[int, int], format: str = "rgba16f",
              gpu_ms: Optional[dict] = None) -> FrameTexture:
        """The colour buffer ``color`` ((H, W, 3) float32, rows top to bottom, a buffer of the ring's context:
        ``GlPrediction.color``, ``GlImage.color``) stored into the ring's next texture, on the GPU. With
        ``gpu_ms``, the GPU milliseconds of stage ``texture`` are added."""
        if format not in TEXTURE_FORMATS:
            raise InputError(f"must be one of {', '.join(TEXTURE_FORMATS)}, got {format!r}", field="format")
        h, w = checked_size(shape, "shape")
        if getattr(color, "size", -1) < 12 * h * w or getattr(color, "ctx", None) is not self.gl.ctx:
            raise InputError(f"must be a colour buffer of the ring's context of at least {12 * h * w} bytes",
                             field="color")
        return self.gl.call(self._write, color, h, w, format, gpu_ms)

    def upload(self, color: np.ndarray, format: str = "rgba16f") -> FrameTexture:
        """A host colour (H, W, 3) float32 linear, rows top to bottom (a frame a method made on the CPU) uploaded
        once and stored as ``write`` stores a buffer."""
        color = np.ascontiguousarray(color, np.float32)
        if color.ndim != 3 or color.shape[2] != 3:
            raise InputError(f"must have shape (H, W, 3), got {color.shape}", field="color")

        def run() -> FrameTexture:
            buffer = self.gl.new_buffer(data=color)
            try:
                return self._write(buffer, color.shape[0], color.shape[1], format)
            finally:
                self.gl.discard([buffer])
        return self.gl.call(run)

    def _write(self, color, h: int, w: int, format: str, gpu_ms: Optional[dict] = None) -> FrameTexture:
        gl = self.gl
        dtype, image_format, space = TEXTURE_FORMATS[format]
        serial = self._serial
        slot = serial % self.count
        kept = self._slots[slot]
        if kept is None or kept[1:] != ((w, h), format):
            if kept is not None:
                kept[0].release()
            texture = gl.ctx.texture((w, h), 4, dtype=dtype)
            self._slots[slot] = kept = (texture, (w, h), format)
        texture = kept[0]
        color.bind_to_storage_buffer(0)
        defines: dict = {"IMAGE_FORMAT": image_format}
        if format == "srgb8":
            if not self._table:
                self._table.append(gl.ctx.buffer(encode8_table_rows()))
            self._table[0].bind_to_storage_buffer(1)
            defines = {"SRGB8": None, "BUCKETS": ENCODE8_BUCKETS}
        texture.bind_to_image(0, read=False, write=True)
        with gl.timing(gpu_ms), gl.gpu_stage("texture"):
            gl.dispatch(gl.program("color_to_texture", defines), h * w, {"size": (h, w)})
        self._serials[slot] = serial
        self._serial += 1
        return FrameTexture(texture, int(texture.glo), (w, h), format, space, serial, gl, self)

    def release_all(self) -> None:
        """Free the ring's textures (every handle turns invalid)."""
        def free() -> None:
            for kept in self._slots:
                if kept is not None:
                    kept[0].release()
            for buffer in self._table:
                buffer.release()
            self._slots[:] = [None] * self.count
            self._table.clear()
        self.gl.call(free)
        self._serials = [-1] * self.count
