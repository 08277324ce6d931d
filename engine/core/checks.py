"""Shape, dtype and range checks at public entry points: one ``check_shape`` with named dimensions (kornia's
``KORNIA_CHECK_SHAPE``), for numpy arrays and torch tensors alike, and one ``check_range`` for the numbers of
configs and options, each raising ``InputError`` naming the argument."""
from __future__ import annotations

import math
import operator
from typing import Optional, Sequence, Union

import numpy as np

from engine.core.errors import InputError


def numeric_array(value, *, copy: bool = False, file=None, frame: Optional[int] = None,
                  field: Optional[str] = None) -> np.ndarray:
    """``value`` (any array-like) as a float64 array (a copy with ``copy``); InputError naming ``file``,
    ``frame`` and ``field`` when it is not numeric (strings, ragged lists, dicts, None)."""
    try:
        return (np.array if copy else np.asarray)(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"is not a numeric array ({exc})", file=file, frame=frame, field=field) from None


def check_shape(value, name: str, dims: Sequence, sizes: Optional[dict] = None, *, floating: bool = True):
    """Check that ``value`` (numpy array or torch tensor) has shape ``dims``; raise InputError naming it.

    ``dims`` holds ints (exact sizes) and names ("H", "W", ...); a name binds to the size it first meets in
    ``sizes`` and must match wherever it appears again. A leading "..." accepts any leading axes.
    With ``floating``, the dtype must be a floating-point one.
    """
    shape = getattr(value, "shape", None)
    if shape is None:
        raise InputError(f"must be an array, got {type(value).__name__}", field=name)
    shape = tuple(int(n) for n in shape)
    want = "(" + ", ".join(str(d) for d in dims) + ")"
    if dims and dims[0] == "...":
        dims = dims[1:]
        if len(shape) < len(dims):
            raise InputError(f"must have shape {want}, got {shape}", field=name)
        shape = shape[len(shape) - len(dims):]
    elif len(shape) != len(dims):
        raise InputError(f"must have shape {want}, got {shape}", field=name)
    sizes = {} if sizes is None else sizes
    for dim, n in zip(dims, shape):
        if isinstance(dim, int):
            if n != dim:
                raise InputError(f"must have shape {want}, got {tuple(getattr(value, 'shape'))}", field=name)
        elif dim in sizes and sizes[dim] != n:
            raise InputError(f"has {dim} = {n}, expected {dim} = {sizes[dim]} (shape {want}, got "
                             f"{tuple(getattr(value, 'shape'))})", field=name)
        else:
            sizes[dim] = n
    if floating:
        is_float = getattr(value, "is_floating_point", None)
        ok = is_float() if callable(is_float) else np.issubdtype(value.dtype, np.floating)
        if not ok:
            raise InputError(f"must be a floating-point array, got dtype {value.dtype}", field=name)
    return value


def check_range(value, field: str, *, low: Optional[float] = None, high: Optional[float] = None,
                low_open: bool = False, high_open: bool = False, integer: bool = False
                ) -> Union[int, float]:
    """``value`` if it lies in the interval from ``low`` to ``high`` (closed ends unless ``low_open`` /
    ``high_open``; None: unbounded on that side), else InputError naming ``field``.

    With ``integer`` the value must be an integer (an ``int`` or numpy integer; ``bool`` and floats are refused)
    and comes back as ``int``; otherwise any finite real number, returned as ``float``. The message states the
    interval, e.g. ``must be an integer >= 1, got 0`` or ``must be in (0, 1], got 1.5``.

    >>> check_range(3, "rays", low=1, integer=True)
    3
    >>> check_range(0.0, "fade_to", low=0, high=1)
    0.0
    """
    if low is not None and high is not None:
        interval = f"in {'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"
    elif low is not None:
        interval = f"{'>' if low_open else '>='} {low}"
    elif high is not None:
        interval = f"{'<' if high_open else '<='} {high}"
    else:
        interval = ""
    want = ("an integer " + interval if integer else interval or "a finite number").strip()
    try:
        if integer:
            if isinstance(value, bool):
                raise TypeError
            number: Union[int, float] = operator.index(value)
        else:
            if isinstance(value, (bool, str, bytes)):
                raise TypeError
            number = float(value)
            if not math.isfinite(number):
                raise ValueError
    except (TypeError, ValueError):
        raise InputError(f"must be {want}, got {value!r}", field=field) from None
    if ((low is not None and (number <= low if low_open else number < low))
            or (high is not None and (number >= high if high_open else number > high))):
        raise InputError(f"must be {want}, got {value!r}", field=field)
    return number


def checked_array(value, name, dims, sizes, dtype=np.float32, floating=True):
    arr = np.asarray(value)
    check_shape(arr, name, dims, sizes, floating=floating)
    return arr.astype(dtype, copy=False)


def checked_matrix(value, name, n):
    return checked_array(value, name, (n, n), None, np.float64, floating=False)


def checked_sharpness(sharpness) -> float:
    """The splat's soft z-buffer sharpness as a float; InputError unless finite and >= 0."""
    s = float(sharpness)
    if not np.isfinite(s) or s < 0:
        raise InputError(f"must be finite and >= 0, got {sharpness!r}", field="sharpness")
    return s


def checked_size(size, name: str = "size") -> tuple[int, int]:
    """``(height, width)`` of an image; InputError (naming ``name``) unless two positive ints."""
    try:
        h, w = (int(n) for n in size)
    except (TypeError, ValueError):
        raise InputError(f"must be (height, width), got {size!r}", field=name) from None
    if h < 1 or w < 1:
        raise InputError(f"must be positive, got {size!r}", field=name)
    return h, w


def checked_out_size(out_size, default):
    """``(height, width)`` of an output image, ``default`` when None; InputError unless two positive ints."""
    return default if out_size is None else checked_size(out_size, "out_size")
