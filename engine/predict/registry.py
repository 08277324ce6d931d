"""Method names -> predictors, for the command line, the evaluation, the demo and the runtime session.

A name may carry options in brackets: ``decomp`` and ``decomp2d`` take ``DecompConfig``'s (through
``engine.core.config.config_from_text``: ``decomp[flow_width=240,gate.tile=16]``) and ``motion=truth``, the
true object motion instead of the estimated one (``DecompTrueMotion``, the bound of thesis Table 6.3);
``flow2d`` its DIS preset, its flow estimator and the correlation network of ``estimator=corr``,
``flow2d[preset=fast]``, ``flow2d[estimator=gl]``, ``flow2d[estimator=corr,network=my.onnx]``; ``mvec`` its
``MvecConfig``, ``mvec[undilate=true]``.
``auto`` is not a predictor but a choice made where frames arrive (``resolve_auto``): ``mvec`` for frames
that carry the renderer's motion vectors, ``flow2d`` for frames that do not (``decomp`` scores as ``flow2d``
to 0.05 dB on every held-out set at 2-2.5x its time: docs/results/2026-11-25-fast-motion.md).
"""
from __future__ import annotations

import dataclasses
import threading
import types
import typing
from dataclasses import dataclass
from typing import Any, Callable, Literal, Optional, Sequence

from engine.core.config import config_from_text, option, option_kinds
from engine.core.errors import InputError
from engine.core.frames import SceneObject
from engine.geometry.backends import resolve_backend
from engine.predict.backend import GlFrames
from engine.predict.base import CpuFrames, Predictor
from engine.predict.classic import Flow2D, Oracle, Repeat, Reproject
from engine.predict.decomp.network import DEFAULT_MODEL
from engine.predict.decomp.predictor import DecompConfig, DecompPredictor, DecompTrueMotion
from engine.predict.mvec import Mvec, MvecConfig

__all__ = ["AUTO", "resolve_auto", "METHODS", "DECOMP_WEIGHTS", "MOTIONS", "decomp_config", "make_decomp",
           "split_methods", "make_predictor", "use_backend",
           "option_parts", "method_parts", "method_with", "Flow2DOptions", "method_options", "names_no_file"]

#: Committed flow network (in ``engine/weights``) of each DeCOMPnet method name.
DECOMP_WEIGHTS = {"decomp": "flow3d.onnx", "decomp2d": "flow2d.onnx"}
#: Values of a decomp method's ``motion`` option: the estimated object motion or the true one.
MOTIONS = ("predicted", "truth")


def option_parts(options: str) -> list[str]:
    """The bracket options ``"key=value, sub.key=value"`` as stripped ``key=value`` parts, empty ones dropped."""
    return [p.strip() for p in options.split(",") if p.strip()]


def method_parts(name: str) -> tuple[str, list[str]]:
    """``"decomp[flow_width=240,gate.tile=16]"`` -> ``("decomp", ["flow_width=240", "gate.tile=16"])``: the
    base name and :func:`option_parts` of its brackets (a missing ``]`` is :func:`make_predictor`'s to refuse)."""
    base, _, rest = name.partition("[")
    return base, option_parts(rest[:-1] if rest.endswith("]") else rest)


def method_with(base: str, parts: Sequence[str]) -> str:
    """The method name of ``base`` with option ``parts`` (the inverse of :func:`method_parts`)."""
    return f"{base}[{','.join(parts)}]" if parts else base


@dataclass(frozen=True)
class Flow2DOptions:
    """Options of ``flow2d`` (``flow2d[preset=fast]``, ``flow2d[estimator=corr,network=my.onnx]``)."""

    preset: Literal["ultrafast", "fast", "medium"] = option("medium", "OpenCV DIS preset")
    estimator: Literal["dis", "gl", "corr"] = option("dis", "the optical flow: OpenCV DIS, the GPU's, or DIS "
                                                             "started from the correlation network's estimate")
    network: str = option("", "an exported correlation flow network (ONNX file) for estimator=corr (default: the "
                              "committed engine/weights one)")
    fallback: bool = option(False, "regions whose estimated motion explains frame n from n-k worse than no object "
                                   "motion take the camera-only warp (engine.predict.dis.explained_motion)")


def method_options(base: str) -> Optional[dict[str, Any]]:
    """The bracket options of method ``base``, dotted name -> the type its value is read as, from the method's
    config: ``DecompConfig``'s and ``motion`` for decomp and decomp2d, ``MvecConfig``'s for mvec,
    ``Flow2DOptions``' for flow2d, none for the others; None for a name that is not a method."""
    if base in DECOMP_WEIGHTS:
        return {**option_kinds(DecompConfig), "motion": Literal[MOTIONS]}
    configs = {"mvec": MvecConfig, "flow2d": Flow2DOptions}
    if base in configs:
        return option_kinds(configs[base])
    return {} if base in METHODS else None


def names_no_file(kind: Any) -> bool:
    """Whether no value of an option of type ``kind`` can name a file: numbers, booleans, one of a
    ``Literal``'s choices, tuples and ``Optional`` of those. Free text (``str``, or a type added later)
    can, and is refused where files are not the caller's to name (``interleave serve``'s clients)."""
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if kind in (bool, int, float) or origin is Literal:
        return True
    if origin in (tuple, typing.Union, types.UnionType):
        return bool(args) and all(a in (Ellipsis, type(None)) or names_no_file(a) for a in args)
    return False


def decomp_config(text: str, weights: str = "flow3d.onnx") -> DecompConfig:
    """The ``DecompConfig`` of bracket options ``"key=value,sub.key=value"`` on top of the defaults with the
    committed network ``weights`` (its ``model`` may be overridden). Unknown keys and bad values raise
    InputError."""
    base = DecompConfig(model=str(DEFAULT_MODEL.with_name(weights)))
    try:
        return config_from_text(DecompConfig, text, base)
    except InputError as exc:
        raise InputError(f"options '{text}': {exc.problem}", field="decomp") from None


def make_decomp(weights: str = "flow3d.onnx", options: str = "", objects: Sequence[SceneObject] = ()) -> Predictor:
    """A DeCOMPnet predictor with committed ``weights`` and bracket ``options``; ``motion=truth`` among them
    gives the true-motion bound (``DecompTrueMotion``), ``motion=predicted`` (the default) ``DecompPredictor``."""
    motion, rest = "predicted", []
    for part in option_parts(options):
        key, sep, value = part.partition("=")
        if key.strip() == "motion" and sep:
            motion = value.strip()
        else:
            rest.append(part)
    if motion not in MOTIONS:
        raise InputError(f"motion must be 'predicted' or 'truth', got {motion!r}", field="motion")
    kind = DecompTrueMotion if motion == "truth" else DecompPredictor
    predictor = kind(decomp_config(",".join(rest), weights), objects=objects)
    predictor.name = next((name for name, file in DECOMP_WEIGHTS.items() if file == weights), predictor.name)
    return predictor


#: The method name that picks ``mvec`` when motion vectors come and ``flow2d`` otherwise.
AUTO = "auto"


def resolve_auto(name: str, has_motion_vectors: bool) -> str:
    """``name``, or for ``auto`` the method it stands for: ``mvec`` with motion vectors, else ``flow2d``."""
    if name.strip() != AUTO:
        return name
    return "mvec" if has_motion_vectors else "flow2d"


#: Registry of method names -> factory(objects) for the CLI and the evaluation.
METHODS: dict[str, Callable[[Sequence[SceneObject]], Predictor]] = {
    "repeat": lambda objects: Repeat(),
    "reproject": lambda objects: Reproject(),
    "flow2d": lambda objects: Flow2D(),
    "mvec": lambda objects: Mvec(),
    "oracle": lambda objects: Oracle(objects),
    "decomp": lambda objects: make_decomp(DECOMP_WEIGHTS["decomp"], objects=objects),
    "decomp2d": lambda objects: make_decomp(DECOMP_WEIGHTS["decomp2d"], objects=objects),
}


def split_methods(text: str) -> list[str]:
    """Comma-separated method names, where a name may carry options in brackets with commas inside:
    ``"reproject,decomp[gate.enabled=false,flow_width=240]"`` -> ``["reproject",
    "decomp[gate.enabled=false,flow_width=240]"]``."""
    out, depth, current = [], 0, ""
    for ch in text:
        depth += (ch == "[") - (ch == "]")
        if ch == "," and depth == 0:
            out.append(current.strip())
            current = ""
        else:
            current += ch
    out.append(current.strip())
    return [m for m in out if m]


def make_predictor(name: str, objects: Sequence[SceneObject] = (), backend: str = "auto") -> Predictor:
    """Build a predictor by name (see ``METHODS``); unknown names raise InputError listing the known ones.

    ``decomp`` and ``decomp2d`` take options of ``engine.predict.decomp.predictor.DecompConfig`` and
    ``motion=truth`` in brackets, e.g. ``decomp[flow_width=240,gate.tile=16]``; ``flow2d`` its DIS preset,
    ``flow2d[preset=fast]``, its estimator ``flow2d[estimator=gl]`` (the GPU's optical flow) and, for
    ``estimator=corr``, the correlation network ``flow2d[estimator=corr,network=PATH.onnx]``. ``backend``
    (``auto``, ``cpu``, ``gl``: :func:`use_backend`) is where its warps run.
    """
    return use_backend(_make_predictor(name, objects), backend)


_GL_FRAMES: list = []
_GL_LOCK = threading.Lock()


def use_backend(predictor: Predictor, backend: str = "auto") -> Predictor:
    """Run ``predictor``'s warps on ``backend`` (``engine.geometry.backends.resolve_backend``: ``auto`` is
    ``gl`` on a hardware GL context, else ``cpu``); a method without GL passes (``predictor.backends``: decomp,
    decomp2d, repeat) stays on ``cpu``. The ``gl`` predictors of a process share one ``GlFrames``."""
    if resolve_backend(backend) == "gl" and "gl" in predictor.backends:
        with _GL_LOCK:
            if not _GL_FRAMES:
                _GL_FRAMES.append(GlFrames())
        predictor.frames = _GL_FRAMES[0]
    else:
        predictor.frames = CpuFrames()
    return predictor


def _make_predictor(name: str, objects: Sequence[SceneObject]) -> Predictor:
    base, _, rest = name.partition("[")
    if base == AUTO:
        raise InputError("method 'auto' is chosen per stream: resolve it with resolve_auto (mvec with motion "
                         "vectors, flow2d without)", field="methods")
    if base not in METHODS:
        raise InputError(f"unknown method '{name}', expected one of {', '.join(METHODS)}, or auto",
                         field="methods")
    if not rest:
        return METHODS[base](objects)
    if base == "mvec" and rest.endswith("]"):
        try:
            return Mvec(config_from_text(MvecConfig, rest[:-1]))
        except InputError as exc:
            raise InputError(f"method '{name}': {exc.problem}", field="methods") from None
    if base == "flow2d" and rest.endswith("]"):
        try:
            options = config_from_text(Flow2DOptions, rest[:-1])
        except InputError as exc:
            field = exc.field if exc.field in option_kinds(Flow2DOptions) else "methods"
            raise InputError(f"method '{name}': {exc.problem}", field=field) from None
        return Flow2D(**dataclasses.asdict(options))
    if base not in DECOMP_WEIGHTS or not rest.endswith("]"):
        raise InputError(f"method '{name}': only decomp, decomp2d (options of engine.predict.decomp.predictor."
                         f"DecompConfig), mvec (MvecConfig) and flow2d (preset=..., estimator=..., network=...) take "
                         f"options, as "
                         f"decomp[key=value,...]",
                         field="methods")
    return make_decomp(DECOMP_WEIGHTS[base], rest[:-1], objects)
