"""The spin set: generated sequences of objects spinning fast about off-centre axes while the camera yaws.

``python -m tools.spin_set OUT [--size 640x360] [--frames 16] [--seeds 4101,4102,4103]``

The hard case of issue 42 (path-traced footage of fast-spinning objects under a turning camera, where
``mvec``'s straight lines fall below camera-only reprojection), made with exact motion vectors: each seed
draws a scene of the generator's ``SPIN_CONFIG`` (a panning camera, thin structures, 2-4 objects, no
pauses), then every object's path is replaced by a constant spin of 5-15 degrees a frame (uniform, either
sense) about an axis that misses its origin by 0.2-1 m (vertical for objects near the ground, else a random
direction; the origin circles the axis, so the motion is a screw, not a turn in place), and the camera's
yaw is set to 0.5-3 degrees a frame. The rates are drawn from the seed before anything is scored (seeds
4101-4103 are the set; not tuned on). Rendering and the rgbd-seq output (exact vectors ``motion.X/Y``,
``object_id``, per-frame object transforms) are ``engine.scenegen``'s.

Prints, per sequence, the objects' spin rates (degrees a frame, measured from the written transforms) and
the camera's yaw rate.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from engine.io.rgbd import write_sequence
from engine.scenegen import make_scene, render_scene
from engine.scenegen.presets import preset_config
from engine.scenegen.scene import CAMERA_CLEARANCE, Motion, MovingObject, Scene

__all__ = ["SPIN_CONFIG", "SPIN_SEEDS", "spin_scene", "render_spin", "spin_rates", "yaw_rates"]

#: the SceneConfig overrides every spin scene starts from (the objects' paths are then replaced)
SPIN_CONFIG = dict(fps=30.0, camera_path="pan", thin_structures="on", num_objects=(2, 4), pause_probability=0.0)
#: the seeds of the set
SPIN_SEEDS = (4101, 4102, 4103)
#: degrees a frame: the objects' spin rates and the camera's yaw rates are drawn uniformly in these ranges
SPIN_DEGREES = (5.0, 15.0)
YAW_DEGREES = (0.5, 3.0)
#: metres: how far the spin axis passes from an object's origin
AXIS_OFFSET = (0.2, 1.0)


def _random_unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _spin_motion(obj: MovingObject, scene: Scene, rng: np.random.Generator) -> Motion:
    """A constant screw motion for ``obj``: turning at the drawn rate about an axis ``AXIS_OFFSET`` from its
    origin, through the place the object had at mid-sequence (so it stays where the generator put it in view).

    The origin circles the axis: with d the offset (perpendicular to the axis a) and theta the angle, it is at
    c + d cos(theta) + (a x d) sin(theta), which ``Motion``'s sine terms write exactly (one per axis, all at
    the spin's frequency)."""
    old = obj.motion
    fps = scene.config.fps
    t_mid = old.t_ref
    rate = math.radians(rng.uniform(*SPIN_DEGREES)) * fps * rng.choice([-1.0, 1.0])  # rad/s
    radius = obj.bounding_radius()
    here = old.position(t_mid)
    near_ground = here[2] < radius + 0.1
    axis = np.array([0.0, 0.0, 1.0]) if near_ground else _random_unit(rng)
    eye = scene.camera.eye(t_mid)
    room = float(np.linalg.norm(here - eye)) - radius - CAMERA_CLEARANCE - 0.1  # never towards the camera
    offset = float(min(rng.uniform(*AXIS_OFFSET), max(room, 0.0)))
    side = np.cross(axis, _random_unit(rng))
    d = offset * side / np.linalg.norm(side)
    e = np.cross(axis, d)
    amplitude = np.hypot(d, e)
    centre = here - d
    if not near_ground:  # the circle stays above the ground (a vertical axis keeps the height)
        centre[2] = max(centre[2], radius + 0.05 + amplitude[2])
    phase = np.arctan2(d, e) - rate * t_mid
    return Motion(kind="spin", anchor=centre, t_ref=t_mid, amplitude=amplitude, frequency=np.full(3, rate),
                  phase=phase, spin_axis=axis, spin_rate=float(rate), orientation=old.orientation)


def spin_scene(seed: int, width: int = 640, height: int = 360, frames: int = 16) -> Scene:
    """The spin scene of ``seed`` (module docstring): the generator's scene of ``SPIN_CONFIG`` with every object
    on a fast off-centre spin and the camera yawing at the drawn rate."""
    config = preset_config("gentle", seed=seed, width=width, height=height, num_frames=frames, **SPIN_CONFIG)
    scene = make_scene(config)
    rng = np.random.default_rng([seed, 42])  # its own stream: the generator's draws stay the seed's
    objects = tuple(dataclasses.replace(o, motion=_spin_motion(o, scene, rng)) for o in scene.objects)
    yaw = math.radians(rng.uniform(*YAW_DEGREES)) * config.fps * rng.choice([-1.0, 1.0])
    return dataclasses.replace(scene, objects=objects, camera=dataclasses.replace(scene.camera, pan_rate=float(yaw)))


def render_spin(out: Path, seed: int, width: int, height: int, frames: int) -> Path:
    """The sequence folder ``out/spin<seed>_<W>x<H>x<frames>``, rendered unless it is already there."""
    folder = Path(out) / f"spin{seed}_{width}x{height}x{frames}"
    if not (folder / "sequence.json").exists():
        scene = spin_scene(seed, width, height, frames)
        write_sequence(folder, render_scene(scene), fps=scene.config.fps, objects=scene.scene_objects(),
                       color_space="linear-srgb")
        (folder / "scenegen_config.json").write_text(json.dumps(
            {**dataclasses.asdict(scene.config), "spin_set": {"seed": seed, "degrees": SPIN_DEGREES,
                                                              "yaw_degrees": YAW_DEGREES,
                                                              "axis_offset": AXIS_OFFSET}}, indent=2) + "\n")
    return folder


def _angle(rotation: np.ndarray) -> np.ndarray:
    """Rotation angles (...) in degrees of rotation matrices (..., 3, 3)."""
    cos = (np.trace(rotation, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def spin_rates(sequence) -> list[float]:
    """Each moving object's median rotation between consecutive frames, degrees (from its transforms)."""
    out = []
    for obj in sequence.objects:
        r = obj.world_from_object[:, :3, :3]
        out.append(float(np.median(_angle(r[1:] @ np.swapaxes(r[:-1], -1, -2)))))
    return out


def yaw_rates(sequence) -> float:
    """The camera's median rotation between consecutive frames, degrees."""
    r = np.stack([f.camera.world_to_camera[:3, :3] for f in sequence])
    return float(np.median(_angle(r[1:] @ np.swapaxes(r[:-1], -1, -2))))


def main(argv=None) -> None:
    from engine.io.rgbd import read_sequence

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--size", default="640x360")
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--seeds", default=",".join(map(str, SPIN_SEEDS)))
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.lower().split("x"))
    for seed in (int(s) for s in args.seeds.split(",")):
        seq = read_sequence(render_spin(args.out, seed, width, height, args.frames))
        print(f"spin{seed}: objects spin " + ", ".join(f"{a:.1f}" for a in spin_rates(seq))
              + f" degrees a frame; camera turns {yaw_rates(seq):.2f} degrees a frame")


if __name__ == "__main__":
    main()
