"""Motion presets of the scene generator: named ``SceneConfig`` overrides that span the speeds frame
generation meets, from the generator's gentle defaults to path-traced game footage.

Speeds are screen speeds of the moving pixels at 640 px width (measured per preset with
``python -m tools.bench_motion``, which prints the median and 90th percentile of each sequence):

- ``gentle``: the generator's defaults (a median 1-7 px a frame);
- ``medium``: objects on longer, faster paths, camera 1.5x (about 5-15 px);
- ``fast``: 20 fps, objects on 3x longer paths at 2.5x the rates (spins to ~20 degrees a frame), camera 2x
  (fast yaw), thin structures always, Monte Carlo-like noise (about 10-30 px, the judged range);
- ``extreme``: the same at 10 fps (tens of pixels a frame, up to 80 and beyond between rendered frames);
- ``smooth``: as fast, but each object on a straight line at constant speed and spin (spins capped at 10
  degrees a frame), no pauses, a camera path without shake or handheld (turns to ~2.9 degrees a frame): content
  whose past motion predicts its next frames. Measured at 640x360, 16 frames (``tools.bench_motion``'s smooth
  set): seeds 7901-7904 move a median 22.4, 124.6, 15.0, 20.6 px a frame (90th percentile 82.6, 151.0, 34.9,
  22.2), seeds 7201-7206 3.8-50.5 (90th percentile 12-65), 7951-7954 1.7-25.0: most seeds 7-27, a few far
  faster (7902).

A preset fixes only motion, frame rate, thin structures and noise; the seed still draws the scene, and any
option given with it wins (``preset_config("fast", seed=7, render_noise=0)``).
"""
from __future__ import annotations

import dataclasses

from engine.core.errors import InputError
from engine.scenegen.scene import SceneConfig

__all__ = ["PRESETS", "preset_config"]

#: preset name -> SceneConfig overrides
PRESETS: dict[str, dict] = {
    "gentle": {},
    "medium": dict(object_travel=2.0, object_speed=1.5, camera_speed=1.5),
    "fast": dict(fps=20.0, object_travel=4.0, object_speed=2.0, camera_speed=2.5, num_objects=(2, 6),
                 thin_structures="on", render_noise=0.03),
    "smooth": dict(fps=20.0, object_motions=("linear",), object_speed=1.5, object_travel=2.0, pause_probability=0.0,
                   max_spin=10.0, camera_speed=2.0, shake_probability=0.0,
                   camera_paths=("static", "pan", "orbit", "dolly", "strafe", "crane"), num_objects=(2, 6),
                   thin_structures="on", render_noise=0.03),
    "extreme": dict(fps=12.0, object_travel=4.0, object_speed=2.0, camera_speed=2.5, num_objects=(2, 6),
                    thin_structures="on", render_noise=0.03),
}


def preset_config(name: str, **overrides) -> SceneConfig:
    """The ``SceneConfig`` of preset ``name`` with ``overrides`` (any SceneConfig field) on top."""
    if name not in PRESETS:
        raise InputError(f"unknown scene preset '{name}', expected one of {', '.join(PRESETS)}", field="preset")
    fields = {f.name for f in dataclasses.fields(SceneConfig)}
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise InputError(f"unknown SceneConfig option(s) {', '.join(unknown)}", field="preset")
    return SceneConfig(**{**PRESETS[name], **overrides})
