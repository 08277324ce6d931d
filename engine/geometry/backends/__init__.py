"""Where the per-frame geometry runs: ``cpu`` (numpy + numba kernels, ``engine.geometry``: the default without a
GPU and the oracle of every GL pass) or ``gl`` (OpenGL 4.5 compute passes, ``engine.geometry.backends.gl``,
with the frames kept in GPU buffers).

``resolve_backend("auto")`` picks ``gl`` when a hardware OpenGL context exists and ``cpu`` otherwise: Mesa's
llvmpipe runs the GL passes correctly (the tests use it) but on the CPU, slower than the numba kernels.
"""
from __future__ import annotations

from engine.core.errors import InputError

__all__ = ["BACKENDS", "BACKEND_CHOICES", "gl_renderer", "resolve_backend"]

#: The backends a predictor can run on.
BACKENDS = ("cpu", "gl")
#: What a caller may ask for: a backend, or ``auto``.
BACKEND_CHOICES = ("auto",) + BACKENDS


def gl_renderer() -> tuple[bool, bool, str]:
    """(the GL backend can run, on a hardware GPU, the renderer's name or why it cannot run)."""
    from engine.geometry.backends.gl.context import shared_context

    try:
        gl = shared_context()
    except RuntimeError as exc:
        return False, False, str(exc)
    return True, not gl.software, gl.renderer


def resolve_backend(name: str = "auto") -> str:
    """``cpu`` or ``gl`` for a requested ``name`` (``auto``: ``gl`` on a hardware GL context, else ``cpu``);
    InputError for an unknown name or ``gl`` where no GL 4.5 compute context can be made."""
    if name not in BACKEND_CHOICES:
        raise InputError(f"must be one of {', '.join(BACKEND_CHOICES)}, got {name!r}", field="backend")
    if name == "cpu":
        return name
    runs, hardware, renderer = gl_renderer()
    if name == "gl" and not runs:
        raise InputError(f"the gl backend cannot run here ({renderer}); use --backend cpu", field="backend")
    return "gl" if name == "gl" or hardware else "cpu"
