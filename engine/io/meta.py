"""Reading JSON metadata (sequence.json, rig.json, cameras.json): every check raises an ``InputError`` that
names the file, the frame and the field, so a bad entry in a long stream is found without a debugger."""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from engine.core.errors import InputError


def load_json(path: Path) -> dict[str, Any]:
    if path.parent.is_file():
        raise InputError("is a file, not a folder", file=path.parent)
    if path.is_dir():
        raise InputError("is a folder, not a file", file=path)
    if not path.is_file():
        raise InputError("file does not exist", file=path)
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"is not valid JSON ({exc})", file=path) from None
    except RecursionError:
        raise InputError("nests too deeply to be a metadata file", file=path) from None
    if not isinstance(data, dict):
        raise InputError(f"must hold a JSON object, got {type(data).__name__}", file=path)
    return data


def require(obj: Mapping[str, Any], key: str, file: Path, frame: int | None = None, name: str | None = None) -> Any:
    if key not in obj:
        raise InputError(f"missing key '{key}'", file=file, frame=frame, field=name or key)
    return obj[key]


def json_int(value: Any, file: Path, name: str, frame: int | None = None, minimum: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise InputError(f"must be an integer, got {value!r}", file=file, frame=frame, field=name)
    if minimum is not None and value < minimum:
        raise InputError(f"must be >= {minimum}, got {value}", file=file, frame=frame, field=name)
    return int(value)


def json_finite(value: Any, file: Path | None, name: str, frame: int | None = None, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not math.isfinite(value):
        raise InputError(f"must be a finite number, got {value!r}", file=file, frame=frame, field=name)
    if positive and value <= 0:
        raise InputError(f"must be > 0, got {value}", file=file, frame=frame, field=name)
    return float(value)


def json_choice(value: Any, allowed: tuple[str, ...], file: Path, name: str) -> str:
    if value not in allowed:
        raise InputError(f"must be one of {list(allowed)}, got {value!r}", file=file, field=name)
    return value
