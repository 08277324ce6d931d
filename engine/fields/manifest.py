"""Checks of an exported field's manifest (``field.json``, ``dynamic.json``; format: ``docs/field-assets.md``)
before anything reads it: every value the renderers use, with its type and range, and the layout that ties the
planes and the MLPs together. A bad value is an InputError naming the file and the key path (``scene.near``,
``field.mlps.color[1].out``), never a KeyError, a broadcast error or a frame of NaN later.

``check_scene(manifest, file)``: what static and dynamic fields share (scene, background, sampling, ONNX file
name); ``check_static_layout(manifest, file)``: a static field's planes and MLPs. The arrays themselves are
checked where they are loaded (``engine.fields.render.load_field``: shapes against this layout, finite values).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from engine.core.checks import numeric_array
from engine.core.errors import InputError
from engine.core.frames import validate_intrinsics, validate_pose
from engine.fields.encoding import direction_encoding_np

__all__ = ["MAX_SAMPLES", "SCENE_KINDS", "SPACINGS", "SHADINGS", "DIRECTION_ENCODINGS", "check_scene",
           "check_static_layout", "check_shading", "check_time_range", "section", "number", "choice", "array_name"]

#: Most samples per ray a manifest may ask for (the trained fields use 64; the renderers allocate per sample).
MAX_SAMPLES = 1024
SCENE_KINDS = ("bounded-360", "forward-facing")
SPACINGS = ("linear", "disparity")
#: ``field.shading`` (absent: per-sample): the colour MLP at every sample, or once per pixel on composited features.
SHADINGS = ("per-sample", "deferred")
DIRECTION_ENCODINGS = {"sh": (1, 4), "fourier": (0, 16), "none": (0, 0)}  # kind -> allowed direction_degree


def _error(problem: str, file, where: str) -> InputError:
    return InputError(problem, file=file, field=where)


def section(parent: Any, key: str, file, where: str = "") -> dict:
    """``parent[key]`` when it is a JSON object."""
    path = f"{where}.{key}" if where else key
    value = parent.get(key) if isinstance(parent, dict) else None
    if not isinstance(value, dict):
        raise _error(f"must be an object, got {type(value).__name__}", file, path)
    return value


def number(parent: dict, key: str, file, where: str, *, low: Optional[float] = None, high: Optional[float] = None,
           above: bool = False, integer: bool = False, infinite: bool = False) -> float:
    """``parent[key]`` as a number >= ``low`` (> with ``above``) and <= ``high``, an integer with ``integer``,
    +inf allowed with ``infinite``."""
    path = f"{where}.{key}"
    value = parent.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (integer and not isinstance(value, int)):
        raise _error(f"must be {'an integer' if integer else 'a number'}, got {value!r}", file, path)
    if math.isnan(value) or (math.isinf(value) and not (infinite and value > 0)):
        raise _error(f"must be finite{' or +inf' if infinite else ''}, got {value!r}", file, path)
    if low is not None and (value <= low if above else value < low):
        raise _error(f"must be {'>' if above else '>='} {low:g}, got {value!r}", file, path)
    if high is not None and value > high:
        raise _error(f"must be <= {high:g}, got {value!r}", file, path)
    return value


def choice(parent: dict, key: str, options: Sequence[str], file, where: str) -> str:
    """``parent[key]`` when it is one of ``options``."""
    value = parent.get(key)
    if value not in options:
        raise _error(f"must be one of {', '.join(options)}, got {value!r}", file, f"{where}.{key}")
    return value


def array_name(parent: dict, key: str, file, where: str) -> str:
    """``parent[key]``: the name of an array of the ``.npz`` (a non-empty string)."""
    value = parent.get(key)
    if not isinstance(value, str) or not value:
        raise _error(f"must name an array of the .npz, got {value!r}", file, f"{where}.{key}")
    return value


def _finite(parent: dict, key: str, shape: tuple, file, where: str) -> np.ndarray:
    path = f"{where}.{key}" if where else key
    value = numeric_array(parent.get(key), file=file, field=path)
    if value.shape != shape:
        raise _error(f"must have shape {shape}, got {value.shape}", file, path)
    if not np.isfinite(value).all():
        raise _error("must be finite", file, path)
    return value


def check_scene(manifest: Any, file: Path, onnx: bool = True) -> None:
    """The parts static and dynamic manifests share: ``scene`` (kind, near, far, the box of a bounded scene or
    the NDC reference camera of a forward-facing one), ``background``, ``render`` and (with ``onnx``; a baked
    field has no query graph) ``onnx.file``."""
    if not isinstance(manifest, dict):
        raise InputError(f"must hold a JSON object, got {type(manifest).__name__}", file=file)
    scene = section(manifest, "scene", file)
    kind = choice(scene, "kind", SCENE_KINDS, file, "scene")
    near = number(scene, "near", file, "scene", low=0.0)
    number(scene, "far", file, "scene", low=near, above=True, infinite=True)
    if kind == "bounded-360":
        lo, hi = (_finite(scene, key, (3,), file, "scene") for key in ("box_min", "box_max"))
        if not (hi > lo).all():
            raise _error(f"must exceed box_min on every axis, got {hi.tolist()} and {lo.tolist()}", file,
                         "scene.box_max")
    else:
        validate_intrinsics(scene.get("ndc_intrinsics"), file=file, field_name="scene.ndc_intrinsics")
        validate_pose(scene.get("ndc_world_to_camera"), file=file, field_name="scene.ndc_world_to_camera")
        if not (_finite(scene, "ndc_size", (2,), file, "scene") > 0).all():
            raise _error("must be positive (width, height)", file, "scene.ndc_size")
    _finite(manifest, "background", (3,), file, "")
    render = section(manifest, "render", file)
    number(render, "num_samples", file, "render", low=1, high=MAX_SAMPLES, integer=True)
    choice(render, "spacing", SPACINGS, file, "render")
    number(render, "ndc_margin", file, "render", low=0.0)
    if not onnx:
        return
    name = section(manifest, "onnx", file).get("file")
    if not isinstance(name, str) or not name or Path(name).name != name or name in (".", ".."):
        raise _error(f"must be a file name beside the manifest, got {name!r}", file, "onnx.file")


def check_time_range(manifest: dict, file) -> tuple[float, float]:
    """A dynamic field's ``time.range`` (exact or baked): [t_min, t_max], finite numbers, t_min <= t_max; returns
    it."""
    span = section(manifest, "time", file).get("range")
    if not (isinstance(span, list) and len(span) == 2
            and all(isinstance(t, (int, float)) and not isinstance(t, bool) and math.isfinite(t) for t in span)
            and span[1] >= span[0]):
        raise _error(f"must be [t_min, t_max], finite, t_min <= t_max, got {span!r}", file, "time.range")
    return float(span[0]), float(span[1])


def check_shading(spec: dict, file) -> int:
    """A ``field`` section's ``shading`` (absent: per-sample) and latent size ``geo_feature_dim`` (>= 3 with
    deferred shading: the diffuse colour), static or dynamic; returns the latent size."""
    latent = int(number(spec, "geo_feature_dim", file, "field", low=0, integer=True))
    if "shading" in spec and choice(spec, "shading", SHADINGS, file, "field") == "deferred" and latent < 3:
        raise _error(f"must be >= 3 with deferred shading (the diffuse colour), got {latent}", file,
                     "field.geo_feature_dim")
    return latent


def check_static_layout(manifest: dict, file: Path) -> None:
    """A static field's ``field`` section: the three planes' axes, the planes of every scale, the density and
    colour MLPs, and how they chain (density input = the planes' channels, density output = 1 + the latent,
    colour input = the latent + the direction encoding, colour output = 3), and ``occupancy``."""
    spec = section(manifest, "field", file)
    if spec.get("plane_axes") != [[0, 1], [0, 2], [1, 2]]:
        raise _error(f"must be [[0, 1], [0, 2], [1, 2]] (xy, xz, yz), got {spec.get('plane_axes')!r}", file,
                     "field.plane_axes")
    planes = spec.get("planes")
    if not isinstance(planes, list) or not planes:
        raise _error("must be a non-empty list of plane scales", file, "field.planes")
    channels = 0
    for i, p in enumerate(planes):
        where = f"field.planes[{i}]"
        if not isinstance(p, dict):
            raise _error("must be an object", file, where)
        number(p, "resolution", file, where, low=2, high=8192, integer=True)
        channels += int(number(p, "channels", file, where, low=1, high=1024, integer=True))
        for key in ("float", "uint8", "range"):
            array_name(p, key, file, where)
    number(spec, "density_bias", file, "field")
    number(spec, "max_log_density", file, "field", high=80.0)  # exp(80) is near float32's largest
    latent = check_shading(spec, file)
    encoding = choice(spec, "direction_encoding", tuple(DIRECTION_ENCODINGS), file, "field")
    low, high = DIRECTION_ENCODINGS[encoding]
    degree = int(number(spec, "direction_degree", file, "field", low=low, high=high, integer=True))
    mlps = section(spec, "mlps", file, "field")
    directions = direction_encoding_np(np.zeros((1, 3)), encoding, degree).shape[-1]
    for name, first, last in (("density", channels, 1 + latent), ("color", latent + directions, 3)):
        layers = mlps.get(name)
        if not isinstance(layers, list) or not layers:
            raise _error("must be a non-empty list of layers", file, f"field.mlps.{name}")
        expected = first
        for i, layer in enumerate(layers):
            where = f"field.mlps.{name}[{i}]"
            if not isinstance(layer, dict):
                raise _error("must be an object", file, where)
            if number(layer, "in", file, where, low=1, integer=True) != expected:
                raise _error(f"must be {expected} (what feeds this layer), got {layer['in']}", file, f"{where}.in")
            expected = int(number(layer, "out", file, where, low=1, high=4096, integer=True))
            array_name(layer, "weight", file, where)
            array_name(layer, "bias", file, where)
        if expected != last:
            raise _error(f"must be {last}, got {expected}", file, f"field.mlps.{name}[{len(layers) - 1}].out")
    occupancy = manifest.get("occupancy")
    if occupancy is not None:
        array_name(section(manifest, "occupancy", file), "array", file, "occupancy")
