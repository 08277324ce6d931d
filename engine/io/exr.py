"""Small OpenEXR helpers over the ``OpenEXR`` 3.x package: channel dicts in, channel dicts out.

Arrays are (H, W), row 0 at the top of the image (EXR scanline order). HALF and FLOAT channels are
returned as float32; UINT channels as uint32. Only the first part of a multi-part file is read, unless
``read_exr(path, all_parts=True)`` (Blender 5 writes a multilayer EXR as one part per render pass).

>>> write_exr("a.exr", {"R": r, "G": g, "B": b, "Z": z}, half={"R", "G", "B"})  # doctest: +SKIP
>>> read_exr("a.exr")["Z"].dtype  # doctest: +SKIP
dtype('float32')
"""
from __future__ import annotations

import io
import os
import sys
import tempfile
import threading
from contextlib import contextmanager, redirect_stderr, redirect_stdout
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Mapping

import numpy as np
import OpenEXR

from engine.core.errors import InputError

_MAGIC = b"\x76\x2f\x31\x01"


@dataclass(frozen=True)
class ExrInfo:
    """What an EXR header says: image size and channel names (in file order)."""

    width: int
    height: int
    channels: tuple[str, ...]


def _check_exr(path: Path) -> None:
    if path.is_dir():
        raise InputError("is a folder, not an EXR file", file=path)
    if not path.is_file():
        raise InputError("file does not exist", file=path)
    with open(path, "rb") as f:
        if f.read(4) != _MAGIC:
            raise InputError("is not an OpenEXR file (bad magic number)", file=path)


def _reason(exc: Exception) -> str:
    """OpenEXR's message, with the one it gives for a cut-off file ("file has 0 parts") said plainly."""
    text = str(exc)
    if "0 parts" in text or "unexpected end of file" in text.lower():
        return "the file is truncated (it ends before its header or pixels do)"
    if "Unable to open" in text:  # the file exists and starts like an EXR (checked): its header is cut or damaged
        return "the file is truncated or damaged (OpenEXR cannot parse its header)"
    return text


class _Captured:
    """What the C library wrote to the process's stdout and stderr inside ``_library_messages``."""

    def __init__(self) -> None:
        self.text = ""

    def last_line(self) -> str:
        lines = [line.strip() for line in self.text.splitlines() if line.strip()]
        return lines[-1] if lines else ""


_OUTPUT_LOCK = threading.Lock()


@contextmanager
def _library_messages() -> Iterator[_Captured]:
    """Capture what OpenEXR's C++ code prints to file descriptors 1 and 2 while reading (a damaged file prints
    dozens of lines, and a warning on stdout, before the one-line error that reports it; the last line goes
    into that error). The descriptors are swapped for the whole process, so another thread's output in those
    milliseconds is captured too; the lock keeps two readers from swapping them at once."""
    captured = _Captured()
    printed = io.StringIO()  # the binding's own warnings go through Python's sys.stdout
    with _OUTPUT_LOCK, tempfile.TemporaryFile() as sink:
        sys.stdout.flush()
        sys.stderr.flush()
        saved = [os.dup(fd) for fd in (1, 2)]
        for fd in (1, 2):
            os.dup2(sink.fileno(), fd)
        try:
            with redirect_stdout(printed), redirect_stderr(printed):
                yield captured
        finally:
            for fd, old in zip((1, 2), saved):
                os.dup2(old, fd)
                os.close(old)
            sink.seek(0)
            captured.text = printed.getvalue() + sink.read().decode("utf-8", "replace")  # the library's last


def read_exr_info(path: str | Path) -> ExrInfo:
    """Read only the header of an EXR: size (from the data window) and channel names."""
    path = Path(path)
    _check_exr(path)
    try:
        with _library_messages():
            header = OpenEXR.File(str(path), header_only=True).header()
    except (RuntimeError, ValueError, OSError) as exc:
        raise InputError(f"cannot read EXR header: {_reason(exc)}", file=path) from None
    lo, hi = header["dataWindow"]
    names = tuple(c.name for c in header["channels"])
    return ExrInfo(width=int(hi[0] - lo[0] + 1), height=int(hi[1] - lo[1] + 1), channels=names)


def read_exr(path: str | Path, *, all_parts: bool = False) -> dict[str, np.ndarray]:
    """Read every channel of an EXR: name -> (H, W) array, float32 for HALF/FLOAT, uint32 for UINT.

    ``all_parts``: read the channels of every part of a multi-part file, not only the first (channel names
    must then be unique across parts, as in Blender's multilayer files, ``ViewLayer.Depth.Z``...; every
    part must have the first part's size).
    Raises InputError naming the file if it is missing, not an EXR, or unreadable (e.g. truncated).
    """
    path = Path(path)
    _check_exr(path)
    try:
        with _library_messages() as messages:
            exr = OpenEXR.File(str(path), separate_channels=True)
        parts = [[(name, ch.pixels) for name, ch in part.channels.items()]
                 for part in (exr.parts if all_parts else exr.parts[:1])]
    except (RuntimeError, ValueError, OSError) as exc:
        raise InputError(f"cannot read EXR pixels: {_reason(exc)}", file=path) from None
    if not parts:  # the pixels could not be read: OpenEXR printed why and kept no part
        said = messages.last_line()
        raise InputError("cannot read EXR pixels: the file is truncated or damaged"
                         + (f" (OpenEXR: {said})" if said else ""), file=path)
    out: dict[str, np.ndarray] = {}
    for k, part in enumerate(parts):
        for name, pixels in part:
            if name in out:
                raise InputError(f"channel {name!r} is in two parts (part {k} repeats it)", file=path, field=name)
            if out and pixels.shape != next(iter(out.values())).shape:
                raise InputError(f"part {k} is {pixels.shape[1]}x{pixels.shape[0]}, unlike part 0", file=path,
                                 field=name)
            out[name] = pixels
    return {name: (a.astype(np.float32) if a.dtype == np.float16 else a) for name, a in out.items()}


def write_exr(path: str | Path, channels: Mapping[str, np.ndarray],
              half: set[str] | frozenset[str] = frozenset()) -> None:
    """Write (H, W) channels to a single-part, ZIP-compressed scanline EXR.

    Channels named in ``half`` are stored as HALF (16-bit float); every other channel is stored as FLOAT
    (32-bit), so float32 data round-trips bit-exactly. Integer and boolean arrays are stored as FLOAT.
    """
    data = {name: np.ascontiguousarray(a, dtype=np.float16 if name in half else np.float32)
            for name, a in channels.items()}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    try:
        OpenEXR.File(header, data).write(str(path))
    except (RuntimeError, ValueError, OSError) as exc:
        raise InputError(f"cannot write EXR ({exc})", file=path) from None
