"""Small validators shared by the convention converters: one check per public entry point, each raising
``InputError`` naming the field."""
from __future__ import annotations

import math

import numpy as np

from engine.core.errors import InputError


def positive(value: object, field: str, *, allow_inf: bool = False) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise InputError(f"must be a number, got {value!r}", field=field) from None
    if math.isnan(x) or x <= 0 or (math.isinf(x) and not allow_inf):
        raise InputError(f"must be a positive {'' if allow_inf else 'finite '}number, got {x}", field=field)
    return x


def frame_size(width: object, height: object) -> tuple[int, int]:
    out = []
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
            raise InputError(f"must be a positive integer (pixels), got {value!r}", field=name)
        out.append(int(value))
    return out[0], out[1]


def float_buffer(buffer: object, where: dict) -> np.ndarray:
    d = np.asarray(buffer)
    if not np.issubdtype(d.dtype, np.floating):
        raise InputError(f"must be a float array, got dtype {d.dtype} (divide a UNORM integer depth buffer "
                         "by 2**bits - 1 first)", **where)
    return d.astype(np.float64)  # always a copy


def count_bad(d: np.ndarray, out_of_range: np.ndarray, range_text: str, where: dict) -> None:
    nan_mask = np.isnan(d)
    nan = int(np.count_nonzero(nan_mask))
    bad = int(np.count_nonzero(out_of_range & ~nan_mask))
    if nan or bad:
        parts = ([f"{nan} NaN values"] if nan else []) + ([f"{bad} values outside {range_text}"] if bad else [])
        raise InputError(f"has {' and '.join(parts)} (depth-buffer values are never clamped)", **where)


def near_far(near: object, far: object, *, allow_inf: bool) -> tuple[float, float]:
    n = positive(near, "near")
    f = math.inf if far is None else positive(far, "far", allow_inf=allow_inf)
    if f <= n:
        raise InputError(f"must be greater than near ({n}), got {f}", field="far")
    return n, f
