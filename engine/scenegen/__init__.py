"""Procedural dynamic scenes with exact ground truth: the demo scene, evaluation sequences, training data.

- ``SceneConfig`` / ``make_scene``: the random scene description (pure numpy, deterministic by seed);
- ``render_scene`` / ``SceneRenderer``: the moderngl renderer (headless EGL), yielding ``engine.core.frames.Frame``;
- ``generate_sequence``: both, written as an rgbd-seq folder by ``engine.io.rgbd.write_sequence``;
- ``RigConfig`` / ``make_rig`` / ``render_rig`` / ``generate_rig``: fixed multi-camera rigs on a scene, written as
  an rgbd-rig capture by ``engine.io.rgbd.write_rig`` (training data for the radiance fields).

See ``docs/scenegen.md`` for what is randomised and how the ground truth is computed.

>>> path = generate_sequence(SceneConfig(seed=1, num_frames=60), "out/seq1")  # doctest: +SKIP
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from engine.io.rgbd import write_sequence
from engine.scenegen.render import SceneRenderer, render_scene
from engine.scenegen.rig import ARRANGEMENTS, Rig, RigConfig, generate_rig, make_rig, render_rig
from engine.scenegen.sample import make_scene
from engine.scenegen.scene import CAMERA_PATHS, LIGHTING_STYLES, MOTIONS, OBJECT_SHAPES, PATTERNS, Scene, SceneConfig

__all__ = ["ARRANGEMENTS", "CAMERA_PATHS", "LIGHTING_STYLES", "MOTIONS", "OBJECT_SHAPES", "PATTERNS", "Rig",
           "RigConfig", "Scene", "SceneConfig", "SceneRenderer", "generate_rig", "generate_sequence", "make_rig",
           "make_scene", "render_rig", "render_scene"]


def generate_sequence(config: SceneConfig, out_dir: str | Path, *, progress: bool = True) -> Path:
    """Sample the scene of ``config``, render it and write it as rgbd-seq to ``out_dir``; returns the path.

    Writes linear-sRGB colour, planar depth, object_id, moving, flow, object_flow and the per-frame
    world_from_object transforms of every moving object; the config that produced it is saved beside
    as ``scenegen_config.json``.
    """

    scene = make_scene(config)
    out = Path(out_dir)
    write_sequence(out, render_scene(scene, progress=progress), fps=config.fps, objects=scene.scene_objects(),
                   color_space="linear-srgb")
    (out / "scenegen_config.json").write_text(json.dumps(dataclasses.asdict(config), indent=2) + "\n")
    return out
