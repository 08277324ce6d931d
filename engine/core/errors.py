"""Errors raised at Interleave's public entry points.

Every problem with user input is an :class:`InputError` whose message names where it was found
(file, frame, field), so a bad frame in a 10 000-frame stream can be located without a debugger.
"""
from __future__ import annotations

from pathlib import Path


class InterleaveError(Exception):
    """Base class of all errors Interleave raises on purpose."""


class InputError(InterleaveError, ValueError):
    """Bad input: wrong shape, dtype, non-finite value, missing file, malformed metadata.

    Args:
        problem: what is wrong, in words ("depth has 12 NaN values").
        file: the file the value came from, if any.
        frame: the frame index, if any.
        field: the field or channel name ("Z", "world_to_camera", ...), if any.
    """

    def __init__(self, problem: str, *, file: str | Path | None = None, frame: int | None = None,
                 field: str | None = None) -> None:
        self.problem = problem
        self.file = None if file is None else str(file)
        self.frame = frame
        self.field = field
        where = []
        if self.file is not None:
            where.append(f"file {self.file}")
        if frame is not None:
            where.append(f"frame {frame}")
        if field is not None:
            where.append(f"field '{field}'")
        super().__init__(f"{', '.join(where)}: {problem}" if where else problem)
