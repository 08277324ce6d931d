"""Check the Blender importer's motion vectors against a real Cycles render of a known motion.

Two steps, two interpreters (bpy is NOT a project dependency; install it in a throwaway venv)::

    python3.11 -m venv /tmp/bpyenv && /tmp/bpyenv/bin/pip install bpy==5.0.1
    /tmp/bpyenv/bin/python tools/blender_vector_check.py render /tmp/bvc             # Blender side
    .venv/bin/python -m tools.blender_vector_check check /tmp/bvc                    # project side

``render OUT`` builds a small scene in Blender (Cycles, CPU): a ground plane (object index 0), a cube
(object index 1) that translates by a fixed step per frame, sky above the horizon, and a camera that pans
(turns about the world z axis) and moves sideways every frame. It renders frames ``1..frames`` with
motion blur OFF (Cycles only offers the Vector pass without motion blur) and the Depth, Vector and Object
Index passes into multilayer EXRs ``OUT/render/NNNN.exr`` (the default view layer, ``ViewLayer``), and
writes ``OUT/cameras.json`` (the importer's camera JSON) and ``OUT/truth.json``: the cube's
``matrix_world`` at every frame from ``0`` to ``frames + 1`` and, per rendered frame, a few surface
points with their pixel position now and in the previous frame computed by Blender itself
(``bpy_extras.object_utils.world_to_camera_view``, i.e. independently of this project's camera code).

``check OUT`` imports OUT with :func:`engine.io.importers.frames_from_blender` and compares each frame's
``motion_vectors`` with

1. the exact rigid vectors of :func:`engine.geometry.motion.rigid_motion_vectors` (from the imported depth,
   cameras, the Object Index pass and the cube's transforms), on pixels whose 3x3 neighbourhood is one
   surface (the Vector pass is anti-aliased over the pixel filter, the Depth and Index passes are not);
2. Blender's own projections of the sample points (the vector at the point's pixel);
3. the background: pixels Cycles marks as no surface (depth 1e10) must import as NaN.

It prints the error statistics and exits 1 when an error is over ``--tolerance`` (0.5 px).

The fixture ``tests/io/data/blender_vectors`` (checked the same way, without bpy, by
``tests/io/test_importers.py``) was made with::

    /tmp/bpyenv/bin/python tools/blender_vector_check.py render tests/io/data/blender_vectors \
        --frames 2 --width 32 --height 24 --motion 2

Measured with Blender 5.0.1 (CPU): errors <= 0.12 px at 64x48 (mean 0.001 px), background NaN.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Optional, Sequence

#: Cube (edge CUBE_SIZE): its centre at frame f is START + f * STEP (world units; Blender world, z up).
CUBE_SIZE = 1.6
CUBE_START = (-0.5, 0.0, 0.9)
CUBE_STEP = (0.12, 0.05, 0.1)
#: Camera at frame f: location START + f * STEP, rotation (X_DEG + f * TILT_DEG, 0, Z_DEG + f * PAN_DEG)
#: (Euler XYZ): it moves right, pans left and tilts up a little every frame.
CAMERA_START = (0.0, -6.0, 2.0)
CAMERA_STEP = (0.08, 0.0, 0.0)
CAMERA_X_DEG, CAMERA_TILT_DEG, CAMERA_Z_DEG, CAMERA_PAN_DEG = 80.0, 0.8, 0.0, 1.5
LENS_MM, SENSOR_MM = 35.0, 36.0


def _at(start: Sequence[float], step: Sequence[float], f: float) -> tuple[float, ...]:
    return tuple(a + f * b for a, b in zip(start, step))


# ------------------------------------------------------------------------------------------------ render

def cycles_scene(bpy, width: int, height: int, frames: int, samples: int):
    """An empty bpy scene set up for the importer: Cycles on the CPU, ``samples`` a pixel without adaptive
    sampling or denoiser, no motion blur (Cycles writes the Vector pass only without it), 24 fps, frames
    1..``frames``, the Combined, Depth, Vector and Object Index passes into 32-bit multilayer EXRs."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = False
    scene.render.use_motion_blur = False
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.render.fps, scene.render.fps_base = 24, 1.0
    scene.frame_start, scene.frame_end = 1, frames
    layer = scene.view_layers[0]
    layer.use_pass_combined = True
    layer.use_pass_z = True
    layer.use_pass_vector = True
    layer.use_pass_object_index = True
    settings = scene.render.image_settings
    if hasattr(settings, "media_type"):  # Blender >= 5.0 picks the media type first
        settings.media_type = "MULTI_LAYER_IMAGE"
    settings.file_format = "OPEN_EXR_MULTILAYER"
    settings.color_depth = "32"
    settings.exr_codec = "ZIP"
    return scene


def render(out: Path, frames: int, width: int, height: int, samples: int, motion: float = 1.0) -> None:
    """Build the scene in bpy, render frames 1..frames, write cameras.json and truth.json.

    ``motion`` scales every per-frame step (cube, camera move, pan, tilt).
    """
    import bpy  # noqa: PLC0415 (only in Blender's Python)
    from bpy_extras.object_utils import world_to_camera_view  # noqa: PLC0415
    from mathutils import Vector  # noqa: PLC0415

    scene = cycles_scene(bpy, width, height, frames, samples)

    world = bpy.data.worlds.new("World")
    world.color = (0.4, 0.5, 0.7)
    scene.world = world
    bpy.ops.mesh.primitive_plane_add(size=24.0, location=(0.0, 4.0, 0.0))
    plane = bpy.context.active_object
    plane.pass_index = 0
    bpy.ops.mesh.primitive_cube_add(size=CUBE_SIZE, location=CUBE_START)
    cube = bpy.context.active_object
    cube.pass_index = 1
    bpy.ops.object.light_add(type="SUN", rotation=(0.6, 0.2, 0.4))
    camera = add_camera(bpy, scene)
    # Keys at every integer frame from 0 (the previous frame of frame 1) to frames + 1 (the next of the
    # last): the Vector pass evaluates the scene at frame - 1 and frame + 1, whatever the interpolation.
    for f in range(0, frames + 2):
        t = f * motion
        cube.location = _at(CUBE_START, CUBE_STEP, t)
        cube.keyframe_insert("location", frame=f)
        camera.location = _at(CAMERA_START, CAMERA_STEP, t)
        camera.rotation_euler = (math.radians(CAMERA_X_DEG + t * CAMERA_TILT_DEG), 0.0,
                                 math.radians(CAMERA_Z_DEG + t * CAMERA_PAN_DEG))
        camera.keyframe_insert("location", frame=f)
        camera.keyframe_insert("rotation_euler", frame=f)

    def pixel(point: Vector) -> list[float]:
        """Blender's projection of a world point: (x right, y down) pixels, centres at +0.5."""
        ndc = world_to_camera_view(scene, camera, point)  # x, y in [0, 1] from the bottom-left corner
        return [ndc.x * width, (1.0 - ndc.y) * height]

    render_dir = out / "render"
    render_dir.mkdir(parents=True, exist_ok=True)
    cameras, truth = {"fps": 24.0, "frames": []}, {"cube_pass_index": 1, "world_from_cube": {}, "points": {}}
    for f in range(0, frames + 2):
        scene.frame_set(f)
        truth["world_from_cube"][str(f)] = [list(r) for r in cube.matrix_world]
    # Surface points of the cube's visible faces (-y face, +z face) and of the ground, in object space.
    half = CUBE_SIZE / 2
    cube_points = [Vector((x * half, -half, z * half)) for x in (-0.5, 0.0, 0.5) for z in (-0.5, 0.0, 0.5)]
    cube_points += [Vector((x * half, y * half, half)) for x in (-0.4, 0.4) for y in (-0.4, 0.4)]
    ground_points = [Vector((x, y, 0.0)) for x in (-2.0, 0.0, 2.5) for y in (-3.5, -1.5)]
    for f in range(1, frames + 1):
        cameras["frames"].append(render_frame(bpy, scene, camera, render_dir, f))
        now_cube = cube.matrix_world.copy()
        now = [pixel(now_cube @ p) for p in cube_points] + [pixel(p) for p in ground_points]
        scene.frame_set(f - 1)
        before_cube = cube.matrix_world.copy()
        before = [pixel(before_cube @ p) for p in cube_points] + [pixel(p) for p in ground_points]
        kinds = ["cube"] * len(cube_points) + ["ground"] * len(ground_points)
        truth["points"][str(f)] = [{"kind": k, "now": a, "previous": b} for k, a, b in zip(kinds, now, before)]
    (out / "cameras.json").write_text(json.dumps(cameras, indent=1))
    (out / "truth.json").write_text(json.dumps(truth, indent=1))
    print(f"rendered {frames} frames of {width}x{height} into {out}")


# ------------------------------------------------------------------------------------------------ check

def check(out: Path, tolerance: float, layer: str = "ViewLayer") -> int:
    """Import OUT and compare its motion vectors with the truth; returns the exit status (0: all within)."""
    report = compare(out, layer)
    for line in report["lines"]:
        print(line)
    worst = max(report["rigid_max"], report["points_max"], report["flow_max"])
    ok = worst <= tolerance and report["background_not_nan"] == 0
    print(f"{'OK' if ok else 'FAIL'}: largest error {worst:.3f} px (tolerance {tolerance} px), "
          f"{report['background_not_nan']} background pixels not NaN")
    return 0 if ok else 1


def compare(out: Path, layer: str = "ViewLayer") -> dict:
    """Import ``out`` (a ``render`` output) and measure its motion vectors against the truth.

    Returns ``rigid_max`` / ``rigid_mean`` (px, over the single-surface pixels of every frame),
    ``flow_max`` (px, the imported ``flow`` against the exact vectors to the next frame, same pixels),
    ``points_max`` (px, Blender-projected sample points), ``background_not_nan`` (count), ``raw_background``
    (the raw Vector pass values Cycles wrote where depth is 1e10) and ``lines`` (a readable report).
    """
    import numpy as np  # noqa: PLC0415

    from engine.core.frames import rigid_inverse  # noqa: PLC0415
    from engine.geometry.motion import rigid_motion_vectors  # noqa: PLC0415
    from engine.io.exr import read_exr  # noqa: PLC0415
    from engine.io.importers import frames_from_blender  # noqa: PLC0415

    out = Path(out)
    truth = json.loads((out / "truth.json").read_text())
    meta = json.loads((out / "cameras.json").read_text())
    imported = list(frames_from_blender(out / "cameras.json", layer=layer).frames)
    by_number = {entry["frame"]: frame for entry, frame in zip(meta["frames"], imported)}
    cube = int(truth["cube_pass_index"])
    lines, rigid_errors, flow_errors, point_errors, not_nan, raw_background = [], [], [], [], 0, []
    for entry in meta["frames"]:
        number, frame = entry["frame"], by_number[entry["frame"]]
        ch = read_exr(out / entry["file"], all_parts=True)
        index_pass = next(f"{layer}.{p}.X" for p in ("Object Index", "IndexOB") if f"{layer}.{p}.X" in ch)
        ids = np.rint(ch[index_pass]).astype(np.int64)  # "Object Index" in Blender 5, "IndexOB" before
        mv = frame.motion_vectors
        background = ~np.isfinite(frame.depth)
        raw_background.append(np.stack([ch[f"{layer}.Vector.{c}"][background] for c in "XYZW"], axis=-1))
        not_nan += int(np.count_nonzero(~np.isnan(mv[background])))
        # 1. exact rigid vectors from depth + cameras + the cube's motion, the previous camera being the
        # previous imported frame's (or, for the first frame, none: skip the rigid comparison there).
        key = np.where(background, -1, ids)
        pad = np.pad(key, 1, mode="edge")
        inner = ~background
        for dy in range(3):
            for dx in range(3):
                inner &= pad[dy:dy + key.shape[0], dx:dx + key.shape[1]] == key
        previous = by_number.get(number - 1)
        if previous is not None:
            moves = {cube: np.asarray(truth["world_from_cube"][str(number - 1)])
                     @ rigid_inverse(np.asarray(truth["world_from_cube"][str(number)]))}
            exact = rigid_motion_vectors(frame.depth, frame.camera, previous.camera, ids, moves)
            err = np.linalg.norm(mv[inner] - exact[inner], axis=-1)
            rigid_errors.append(err)
            moving = inner & (ids == cube)
            lines.append(f"frame {number}: {int(inner.sum())} single-surface pixels, error vs exact rigid vectors "
                         f"mean {err.mean():.3f} max {err.max():.3f} px; mean vector cube "
                         f"{np.round(mv[moving].mean(axis=0), 2).tolist()} (exact "
                         f"{np.round(exact[moving].mean(axis=0), 2).tolist()}), ground "
                         f"{np.round(mv[inner & (ids == 0)].mean(axis=0), 2).tolist()} (exact "
                         f"{np.round(exact[inner & (ids == 0)].mean(axis=0), 2).tolist()})")
        following = by_number.get(number + 1)
        if following is not None:  # the flow (ZW) against the exact vectors to the next frame
            ahead = {cube: np.asarray(truth["world_from_cube"][str(number + 1)])
                     @ rigid_inverse(np.asarray(truth["world_from_cube"][str(number)]))}
            forward = rigid_motion_vectors(frame.depth, frame.camera, following.camera, ids, ahead)
            flow_errors.append(np.linalg.norm(frame.flow[inner] - forward[inner], axis=-1))
            lines.append(f"frame {number}: flow error vs exact vectors to the next frame mean "
                         f"{flow_errors[-1].mean():.3f} max {flow_errors[-1].max():.3f} px")
        # 2. Blender's own projections of sample points (no project camera code involved).
        h, w = frame.depth.shape
        for p in truth["points"][str(number)]:
            (u, v), (pu, pv) = p["now"], p["previous"]
            x, y = int(math.floor(u)), int(math.floor(v))
            if not (1 <= x < w - 1 and 1 <= y < h - 1):
                continue
            want_id = cube if p["kind"] == "cube" else 0
            window = ids[y - 1:y + 2, x - 1:x + 2]
            if background[y - 1:y + 2, x - 1:x + 2].any() or (window != want_id).any():
                continue  # the point is hidden or on an edge: the pixel's vector is a blend
            # the vector at the pixel centre, corrected to the point's sub-pixel position with the local gradient
            here = mv[y, x]
            gx = (mv[y, x + 1] - mv[y, x - 1]) / 2
            gy = (mv[y + 1, x] - mv[y - 1, x]) / 2
            at_point = here + gx * (u - x - 0.5) + gy * (v - y - 0.5)
            want = np.array([pu - u, pv - v])
            point_errors.append(float(np.linalg.norm(at_point - want)))
            lines.append(f"frame {number}: {p['kind']} point at ({u:.2f}, {v:.2f}) was at ({pu:.2f}, {pv:.2f}): "
                         f"Blender says {np.round(want, 3).tolist()}, imported {np.round(at_point, 3).tolist()}")
    raw = np.concatenate(raw_background) if raw_background else np.zeros((0, 4))
    lines.append(f"background: {len(raw)} pixels with depth 1e10, {int(np.all(raw == 0, axis=1).sum())} of them with "
                 f"a zero vector (no sample hit a surface); raw Vector pass there: "
                 f"min {raw.min(axis=0).tolist() if len(raw) else []} "
                 f"max {raw.max(axis=0).tolist() if len(raw) else []}")
    rigid = np.concatenate(rigid_errors) if rigid_errors else np.zeros(0)
    flow = np.concatenate(flow_errors) if flow_errors else np.zeros(0)
    return {"flow_max": float(flow.max()) if flow.size else 0.0,"rigid_max": float(rigid.max()) if rigid.size else 0.0,
            "rigid_mean": float(rigid.mean()) if rigid.size else 0.0,
            "rigid_count": int(rigid.size),
            "points_max": max(point_errors, default=0.0), "points_count": len(point_errors),
            "background_not_nan": not_nan, "background_count": int(len(raw)), "raw_background": raw,
            "lines": lines}


def add_camera(bpy, scene):
    """The scene's camera: a LENS_MM lens on a SENSOR_MM-wide sensor (fit: auto), linked and active."""
    data = bpy.data.cameras.new("Camera")
    data.lens, data.sensor_width, data.sensor_fit = LENS_MM, SENSOR_MM, "AUTO"
    camera = bpy.data.objects.new("Camera", data)
    scene.collection.objects.link(camera)
    scene.camera = camera
    return camera


def render_frame(bpy, scene, camera, render_dir: Path, f: int) -> dict:
    """Render frame ``f`` of ``scene`` into ``render_dir/NNNN.exr``; returns its entry of the importer's camera
    JSON (``camera``'s pose and lens at that frame)."""
    scene.frame_set(f)
    name = f"{f:04d}.exr"
    scene.render.filepath = str(render_dir / name)
    bpy.ops.render.render(write_still=True)
    return {"frame": f, "file": f"{render_dir.name}/{name}", "camera_to_world": [list(r) for r in camera.matrix_world],
            "lens_mm": camera.data.lens, "sensor_width_mm": camera.data.sensor_width}


def render_parser(sub, *, frames: Optional[int], width: int, height: int, samples: int = 16, name: str = "render",
                  help: str = "render the scene (run with bpy's Python)") -> argparse.ArgumentParser:
    """The ``NAME OUT`` sub-command of a Blender tool with its size, length (``frames`` None: no ``--frames``) and
    sample-count options."""
    r = sub.add_parser(name, help=help)
    r.add_argument("out", type=Path)
    if frames is not None:
        r.add_argument("--frames", type=int, default=frames)
    r.add_argument("--width", type=int, default=width)
    r.add_argument("--height", type=int, default=height)
    r.add_argument("--samples", type=int, default=samples, help="path-traced samples a pixel (no denoiser)")
    return r


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    r = render_parser(sub, frames=3, width=64, height=48)
    r.add_argument("--motion", type=float, default=1.0, help="scale of every per-frame step")
    c = sub.add_parser("check", help="import the render and compare (run with the project's Python)")
    c.add_argument("out", type=Path)
    c.add_argument("--tolerance", type=float, default=0.5)
    args = parser.parse_args(argv)
    if args.command == "render":
        render(args.out, args.frames, args.width, args.height, args.samples, args.motion)
        return 0
    return check(args.out, args.tolerance)


if __name__ == "__main__":
    sys.exit(main())
