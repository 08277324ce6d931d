"""Shape and dtype checks at public entry points: one ``check_shape`` with named dimensions (kornia's
``KORNIA_CHECK_SHAPE``), for numpy arrays and torch tensors alike, raising ``InputError`` naming the argument."""
from __future__ import annotations

from typing import Optional, Sequence

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
