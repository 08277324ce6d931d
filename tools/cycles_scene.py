"""Path-traced validation data: Cycles renders of fast, spinning objects behind thin poles, a yawing camera and
Monte Carlo noise, imported as an rgbd-seq with the exact object motion; the same moving scenes seen by a row of static
cameras, imported as an rgbd-rig (the dynamic fields' training data); and static forward-facing captures of the
same scenes in LLFF's layout.

A check the rasterizer of ``engine.scenegen`` cannot give: global illumination, soft shadows, anti-aliased
edges and a path tracer's noise (``--samples``, no denoiser), with Cycles' own Depth, Vector and Object Index
passes. Two steps, two interpreters (bpy is NOT a project dependency; install it in a throwaway venv)::

    python3.11 -m venv /tmp/bpyenv && /tmp/bpyenv/bin/pip install bpy==5.0.1
    /tmp/bpyenv/bin/python tools/cycles_scene.py render /tmp/cyc/s1 --seed 1        # Blender side
    .venv/bin/python -m tools.cycles_scene import /tmp/cyc/s1 out/cycles/s1          # project side
    /tmp/bpyenv/bin/python tools/cycles_scene.py rig /tmp/cyc/r31 --seed 31          # 5 static cameras
    .venv/bin/python -m tools.cycles_scene import-rig /tmp/cyc/r31 out/cycles/r31    # an rgbd-rig

``render OUT`` builds the scene of ``--seed`` (Blender world, z up): a textured ground and back wall, a row of
thin static poles between the camera and the objects, ``--objects`` textured primitives (object index 1, 2,
...) on smooth paths (each axis a sinusoid) whose peak screen speed is ``--speed`` px per frame at the given
width and which spin 5-15 degrees a frame about a random axis, and a camera that yaws back and forth (peak
``--yaw`` degrees a frame) while it slides sideways. Keys at every integer frame 0 .. frames + 1 (the Vector
pass evaluates the scene at frame - 1 and frame + 1). It renders frames 1 .. frames into multilayer EXRs
``OUT/render/NNNN.exr`` and writes ``OUT/cameras.json`` (the importer's camera JSON) and ``OUT/objects.json``
(every object's ``matrix_world`` at every keyed frame and its object index).

``rig OUT`` renders the same moving scene (``render``'s builder, objects and paths for ``--seed``) from
``--num-cameras`` STATIC cameras on a forward-facing row, as ``interleave render-rig --num-cameras N`` captures a
generated scene: ``--baseline`` world units between neighbours (0.4: render-rig's 0.2 of the distance to the
target over 4 gaps), centred where ``render``'s camera path starts, parallel optical axes pitched as its camera.
Every camera renders frames 1 .. frames into ``OUT/cam<k>/render/NNNN.exr`` with its own ``cameras.json``;
``OUT/objects.json`` is ``render``'s and ``OUT/cameras.json`` names the cameras and ``--test-cameras``.
``import-rig OUT RIG`` writes the rgbd-rig ``RIG`` the dynamic trainer reads: each camera imported as ``import``
imports a sequence, and ``rig.json`` with render-rig's split (test cameras between train cameras, never at an
end of the row: cam2 of 5). The fixture ``tests/io/data/cycles_rig`` was made with::

    /tmp/bpyenv/bin/python tools/cycles_scene.py rig tests/io/data/cycles_rig --seed 1 --num-cameras 3 \
        --frames 2 --width 48 --height 27 --samples 4 --speed 3

``capture OUT`` renders the same scene frozen at frame 0 (nothing moves) from ``--views`` cameras on a
forward-facing grid (``--baseline`` world units apart, parallel axes), and ``llff OUT ROOT --factor N`` writes
those views as an LLFF capture as one ships (``images_N/`` and ``poses_bounds.npy``, no ``images/``): a
photo-like capture for the radiance fields and for ``interleave demo --field``.

``import OUT SEQ`` reads a ``render`` output with :func:`engine.io.importers.frames_from_blender` (colour,
planar depth, cameras, the renderer's motion vectors), adds the Object Index pass as ``object_id`` and
``moving`` (the pixels of the moving objects), and writes the rgbd-seq ``SEQ`` with the objects' per-frame
transforms, so ``interleave eval`` and the benchmarks score it like a generated sequence (``oracle``, moving
pixels, end-point error).
"""
from __future__ import annotations

import argparse
import json
import math
import random
import sys
from pathlib import Path
from typing import Optional, Sequence

if __package__ in (None, ""):  # run as a script by bpy's Python: make ``tools`` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tools import blender_vector_check as blender  # noqa: E402

CAMERA_DISTANCE = 8.0  # the objects' paths are centred this far in front of the camera


def _material(bpy, name: str, color, scale: float, noise_scale: float):
    """Principled BSDF whose base colour is a checker of a coloured noise and ``color`` in object coordinates
    (the texture moves with the object)."""
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    bsdf = nodes["Principled BSDF"]
    coords = nodes.new("ShaderNodeTexCoord")
    checker = nodes.new("ShaderNodeTexChecker")
    noise = nodes.new("ShaderNodeTexNoise")
    checker.inputs["Scale"].default_value = scale
    checker.inputs["Color2"].default_value = (*color, 1.0)
    noise.inputs["Scale"].default_value = noise_scale
    links.new(coords.outputs["Object"], checker.inputs["Vector"])
    links.new(coords.outputs["Object"], noise.inputs["Vector"])
    links.new(noise.outputs["Color"], checker.inputs["Color1"])
    links.new(checker.outputs["Color"], bsdf.inputs["Base Color"])
    bsdf.inputs["Roughness"].default_value = 0.6
    return mat


def _content(bpy, scene, rng: random.Random, width: int, objects: int, speed: float) -> list:
    """The scene's world, sun, ground, wall, poles and ``objects`` textured primitives (object index 1, 2, ...),
    drawn from ``rng``; returns each object with its path (centre, amplitudes, rates, phases) and spin (axis,
    radians a frame, starting orientation), whose peak screen speed is ``speed`` px a frame at ``width``."""
    from mathutils import Euler, Vector  # noqa: PLC0415

    world = bpy.data.worlds.new("World")
    world.color = (0.35, 0.42, 0.55)
    scene.world = world
    sun_heading = math.radians(rng.uniform(0, 90))
    bpy.ops.object.light_add(type="SUN", rotation=(math.radians(50), math.radians(10), sun_heading))
    bpy.context.active_object.data.energy = 3.0

    def add(kind: str, pass_index: int, material, **kw):
        getattr(bpy.ops.mesh, f"primitive_{kind}_add")(**kw)
        obj = bpy.context.active_object
        obj.pass_index = pass_index
        obj.data.materials.append(material)
        return obj

    ground = _material(bpy, "ground", (0.25, 0.22, 0.2), 0.6, 3.0)
    add("plane", 0, ground, size=80.0, location=(0.0, CAMERA_DISTANCE, 0.0))
    wall = _material(bpy, "wall", (0.5, 0.45, 0.4), 0.8, 6.0)
    add("plane", 0, wall, size=60.0, location=(0.0, CAMERA_DISTANCE + 9.0, 10.0), rotation=(math.radians(90), 0, 0))
    pole = _material(bpy, "pole", (0.1, 0.1, 0.12), 20.0, 30.0)
    for i in range(7):  # thin static structures the objects pass behind
        add("cylinder", 0, pole, radius=0.035, depth=4.0,
            location=(-4.5 + 1.5 * i + rng.uniform(-0.3, 0.3), CAMERA_DISTANCE - 3.0 + rng.uniform(-0.5, 0.5), 2.0))

    # screen px per world unit at the paths' centre
    px_per_unit = width * blender.LENS_MM / blender.SENSOR_MM / CAMERA_DISTANCE
    kinds = ["cube", "uv_sphere", "torus", "cylinder", "ico_sphere", "cone"]
    movers = []
    for i in range(objects):
        kind = kinds[i % len(kinds)]
        size = rng.uniform(0.5, 1.1)
        color = (rng.uniform(0.1, 0.9), rng.uniform(0.1, 0.9), rng.uniform(0.1, 0.9))
        mat = _material(bpy, f"object{i + 1}", color, rng.uniform(2.0, 5.0), rng.uniform(4.0, 12.0))
        extra = {"major_radius": size, "minor_radius": size * 0.35} if kind == "torus" else (
            {"radius": size} if kind in ("uv_sphere", "ico_sphere", "cylinder", "cone") else {"size": 1.6 * size})
        obj = add(kind, i + 1, mat, **extra)
        peak = rng.uniform(0.5, 1.0) * speed / px_per_unit  # world units a frame at the fastest
        amplitude = [rng.uniform(2.0, 3.5), rng.uniform(0.5, 2.0), rng.uniform(0.2, 0.6)]
        omega = peak / amplitude[0]
        phases = [rng.uniform(0, 2 * math.pi) for _ in range(3)]
        rates = [omega, omega * rng.uniform(0.5, 1.2), omega * rng.uniform(0.8, 1.5)]
        centre = [rng.uniform(-1.5, 1.5), CAMERA_DISTANCE + rng.uniform(-1.5, 1.5), size + 0.3 + amplitude[2]]
        axis = Vector((rng.gauss(0, 1), rng.gauss(0, 1), rng.gauss(0, 1))).normalized()
        spin = math.radians(rng.uniform(5.0, 15.0)) * rng.choice((-1, 1))
        start = Euler((rng.uniform(0, 6.3), rng.uniform(0, 6.3), rng.uniform(0, 6.3))).to_matrix()
        movers.append((obj, centre, amplitude, rates, phases, axis, spin, start))

    return movers


def render(out: Path, seed: int, frames: int, width: int, height: int, samples: int, objects: int, speed: float,
           yaw: float) -> None:
    """Build the scene of ``seed`` in bpy, render frames 1..frames, write cameras.json and objects.json."""
    import bpy  # noqa: PLC0415 (only in Blender's Python)

    rng = random.Random(seed)
    scene = blender.cycles_scene(bpy, width, height, frames, samples)
    scene.cycles.seed = seed

    movers = _content(bpy, scene, rng, width, objects, speed)

    camera = blender.add_camera(bpy, scene)
    yaw_rate = rng.uniform(0.07, 0.12)  # rad of the yaw oscillation per frame
    yaw_amplitude = math.radians(yaw) / yaw_rate  # peak yaw rate ``yaw`` degrees a frame
    yaw_phase = rng.uniform(0, 2 * math.pi)
    for f in range(0, frames + 2):
        camera.location = (0.6 * math.sin(0.05 * f), 0.0, 1.7)
        camera.rotation_euler = (math.radians(84.0), 0.0, yaw_amplitude * math.sin(yaw_rate * f + yaw_phase))
        camera.keyframe_insert("location", frame=f)
        camera.keyframe_insert("rotation_euler", frame=f)
    record = _key_objects(scene, movers, seed, frames)

    render_dir = out / "render"
    render_dir.mkdir(parents=True, exist_ok=True)
    cameras = {"fps": 24.0, "frames": []}
    for f in range(1, frames + 1):
        cameras["frames"].append(blender.render_frame(bpy, scene, camera, render_dir, f))
    (out / "cameras.json").write_text(json.dumps(cameras, indent=1))
    (out / "objects.json").write_text(json.dumps(record, indent=1))
    print(f"rendered {frames} frames of {width}x{height} into {out}")


def rig(out: Path, seed: int, cameras: int, test_cameras: int, frames: int, width: int, height: int, samples: int,
        objects: int, speed: float, baseline: float) -> None:
    """Render the moving scene of ``seed`` (``render``'s objects and paths) from ``cameras`` STATIC cameras on a
    forward-facing row: ``baseline`` world units between neighbours, centred where ``render``'s camera starts
    (x = 0, 1.7 m up), parallel optical axes pitched as ``render``'s camera (camera k further right than k - 1). Writes
    OUT/cam<k>/render/NNNN.exr and OUT/cam<k>/cameras.json (frames 1 .. frames), OUT/objects.json (as
    ``render``) and OUT/cameras.json: ``{"cameras": [...], "test_cameras": N, "baseline": B}``."""
    import bpy  # noqa: PLC0415 (only in Blender's Python)

    rng = random.Random(seed)
    scene = blender.cycles_scene(bpy, width, height, frames, samples)
    scene.cycles.seed = seed
    movers = _content(bpy, scene, rng, width, objects, speed)
    record = _key_objects(scene, movers, seed, frames)
    camera = blender.add_camera(bpy, scene)  # not keyed: it stays where it is put, at every frame
    camera.rotation_euler = (math.radians(84.0), 0.0, 0.0)
    names = [f"cam{k}" for k in range(cameras)]
    for k, name in enumerate(names):  # left to right as seen from the rig
        camera.location = ((k - (cameras - 1) / 2) * baseline, 0.0, 1.7)
        render_dir = out / name / "render"
        render_dir.mkdir(parents=True, exist_ok=True)
        entries = {"fps": 24.0, "frames": [blender.render_frame(bpy, scene, camera, render_dir, f)
                                           for f in range(1, frames + 1)]}
        (out / name / "cameras.json").write_text(json.dumps(entries, indent=1))
    (out / "objects.json").write_text(json.dumps(record, indent=1))
    (out / "cameras.json").write_text(json.dumps({"cameras": names, "test_cameras": test_cameras,
                                                  "baseline": baseline}, indent=1))
    print(f"rendered {frames} frames of {width}x{height} from {cameras} cameras into {out}")


def _key_objects(scene, movers: list, seed: int, frames: int) -> dict:
    """Key every ``_content`` object at the integer frames 0 .. frames + 1 (the Vector pass evaluates the scene
    at frame - 1 and frame + 1); returns objects.json's record (each object's ``matrix_world`` at those frames)."""
    for f in range(0, frames + 2):
        for mover in movers:
            obj = mover[0]
            obj.matrix_world = _pose(mover, f)
            obj.keyframe_insert("location", frame=f)
            obj.keyframe_insert("rotation_euler", frame=f)
    record = {"seed": seed, "objects": {}}
    for f in range(0, frames + 2):
        scene.frame_set(f)
        for obj, *_ in movers:
            entry = record["objects"].setdefault(obj.name, {"pass_index": obj.pass_index, "world_from_object": {}})
            entry["world_from_object"][str(f)] = [list(r) for r in obj.matrix_world]
    return record


def _pose(mover, f: int):
    """World-from-object matrix of a ``_content`` object at frame ``f``."""
    from mathutils import Matrix, Vector  # noqa: PLC0415

    obj, centre, amplitude, rates, phases, axis, spin, start = mover
    location = Vector([c + a * math.sin(r * f + p) for c, a, r, p in zip(centre, amplitude, rates, phases)])
    return Matrix.Translation(location) @ (Matrix.Rotation(spin * f, 3, axis) @ start).to_4x4()


def capture(out: Path, seed: int, views: int, width: int, height: int, samples: int, objects: int,
            baseline: float) -> None:
    """Render the scene of ``seed``, frozen at frame 0, from ``views`` forward-facing cameras on a grid
    (``baseline`` world units between neighbours, parallel optical axes, as a hand-held LLFF capture);
    writes OUT/render/NNNN.exr and OUT/cameras.json (one entry a view)."""
    import bpy  # noqa: PLC0415 (only in Blender's Python)

    rng = random.Random(seed)
    scene = blender.cycles_scene(bpy, width, height, views, samples)
    scene.cycles.seed = seed
    for mover in _content(bpy, scene, rng, width, objects, 0.0):
        mover[0].matrix_world = _pose(mover, 0)
    camera = blender.add_camera(bpy, scene)
    camera.rotation_euler = (math.radians(84.0), 0.0, 0.0)
    columns = math.ceil(math.sqrt(views * 4 / 3))
    render_dir = out / "render"
    render_dir.mkdir(parents=True, exist_ok=True)
    cameras = {"fps": 24.0, "frames": []}
    for i in range(views):
        row, column = divmod(i, columns)
        camera.location = ((column - (columns - 1) / 2) * baseline + rng.uniform(-0.2, 0.2) * baseline, 0.0,
                           1.7 + (row - (views // columns - 1) / 2) * baseline)
        cameras["frames"].append(blender.render_frame(bpy, scene, camera, render_dir, i + 1))
    (out / "cameras.json").write_text(json.dumps(cameras, indent=1))
    print(f"rendered {views} views of {width}x{height} into {out}")


def write_capture(out: Path, root: Path, factor: int, layer: str = "ViewLayer") -> Path:
    """A ``capture`` output as an LLFF capture ``root`` (``images_<factor>/`` and ``poses_bounds.npy``; the
    bounds are each view's 0.5th and 99.5th depth percentiles, widened by 10 %)."""
    import numpy as np  # noqa: PLC0415

    from engine.io.importers import frames_from_blender  # noqa: PLC0415
    from engine.io.llff import write_llff  # noqa: PLC0415

    frames = list(frames_from_blender(Path(out) / "cameras.json", layer=layer).frames)
    bounds = []
    for frame in frames:
        finite = frame.depth[np.isfinite(frame.depth)]
        bounds.append([0.9 * np.percentile(finite, 0.5), 1.1 * np.percentile(finite, 99.5)])
    return write_llff(root, np.stack([f.color for f in frames]), [f.camera for f in frames], np.array(bounds),
                      factors=(factor,))


def import_sequence(out: Path, seq: Path, layer: str = "ViewLayer") -> Path:
    """Import a ``render`` output as the rgbd-seq ``seq`` with object ids, moving masks and the objects'
    per-frame transforms (frame index i of the sequence is Blender frame i + 1)."""
    from engine.io.meta import load_json  # noqa: PLC0415
    from engine.io.rgbd import write_sequence  # noqa: PLC0415

    out = Path(out)
    fps, objects, frames = _camera_frames(out / "cameras.json", load_json(out / "objects.json"), layer)
    return write_sequence(seq, frames, fps=fps, objects=objects)


def import_rig(out: Path, root: Path, layer: str = "ViewLayer") -> Path:
    """Import a ``rig`` output as the rgbd-rig ``root``: one rgbd-seq per camera (as ``import``), and rig.json
    with the test cameras chosen as ``interleave render-rig`` chooses them for one row (between train
    cameras, never at an end of the row, spread evenly)."""
    from engine.core.errors import InputError  # noqa: PLC0415
    from engine.io.meta import json_int, load_json, require  # noqa: PLC0415
    from engine.io.rgbd import write_rig  # noqa: PLC0415
    from engine.scenegen.rig import RigConfig, camera_split  # noqa: PLC0415 (render-rig's own rule, not a copy)

    out = Path(out)
    path = out / "cameras.json"
    meta = load_json(path)
    names = require(meta, "cameras", path)
    if not isinstance(names, list) or not names or not all(isinstance(n, str) and n for n in names):
        raise InputError(f"must be a non-empty list of camera folder names, got {names!r}", file=path,
                         field="cameras")
    test_cameras = json_int(require(meta, "test_cameras", path), path, "test_cameras", minimum=0)
    try:
        config = RigConfig(num_cameras=len(names), test_cameras=test_cameras)
    except InputError as exc:  # the same rule as render-rig's, named at the file that asked for it
        raise InputError(exc.problem, file=path, field=exc.field) from None
    record = load_json(out / "objects.json")
    train, test = camera_split(config)
    imported = {name: _camera_frames(out / name / "cameras.json", record, layer) for name in names}
    fps, objects, _ = imported[names[0]]
    return write_rig(root, {name: frames for name, (_, _, frames) in imported.items()},
                     [names[k] for k in train], [names[k] for k in test], fps=fps, objects=objects)


def _camera_frames(cameras_json: Path, record: dict, layer: str):
    """One camera's render: ``(fps, objects, frames)``, the frames (a generator) read with
    :func:`engine.io.importers.frames_from_blender` plus ``object_id``, ``moving`` and ``object_flow`` from
    the Object Index pass and the objects' transforms in ``record`` (objects.json)."""
    import dataclasses  # noqa: PLC0415

    import numpy as np  # noqa: PLC0415

    from engine.core.frames import SceneObject  # noqa: PLC0415
    from engine.io.exr import read_exr  # noqa: PLC0415
    from engine.io.importers import frames_from_blender  # noqa: PLC0415
    from engine.io.meta import load_json  # noqa: PLC0415
    from engine.predict.base import true_object_flow  # noqa: PLC0415

    meta = load_json(cameras_json)
    imported = frames_from_blender(cameras_json, layer=layer)
    numbers = [entry["frame"] for entry in meta["frames"]]
    objects, ahead = [], {}  # ahead: id -> the object keyed one frame further (the last frame's next)
    for name, entry in record["objects"].items():
        keyed = [np.asarray(entry["world_from_object"][str(n)], dtype=np.float64) for n in numbers + [numbers[-1] + 1]]
        objects.append(SceneObject(int(entry["pass_index"]), name, True, np.stack(keyed[:-1])))
        ahead[objects[-1].id] = SceneObject(objects[-1].id, name, True, np.stack(keyed))
    moving_ids = np.array([o.id for o in objects])

    def frames():
        for i, (entry, frame) in enumerate(zip(meta["frames"], imported.frames)):
            channels = read_exr(cameras_json.parent / entry["file"], all_parts=True)
            index = next(f"{layer}.{p}.X" for p in ("Object Index", "IndexOB") if f"{layer}.{p}.X" in channels)
            ids = np.rint(channels[index]).astype(np.int32)
            ids[~np.isfinite(frame.depth)] = 0
            frame = dataclasses.replace(frame, index=i, object_id=ids, moving=np.isin(ids, moving_ids))
            # screen motion to the next frame from object motion alone (the generator's object_flow)
            object_flow = true_object_flow(frame, ahead, i + 1)[..., :2]
            yield dataclasses.replace(frame, object_flow=np.ascontiguousarray(object_flow, dtype=np.float32))

    return imported.fps, objects, frames()


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    r = _scene_options(blender.render_parser(sub, frames=16, width=640, height=360))
    r.add_argument("--speed", type=float, default=24.0, help="peak screen speed of an object, px a frame")
    r.add_argument("--yaw", type=float, default=2.5, help="peak camera yaw, degrees a frame")
    g = _scene_options(blender.render_parser(
        sub, name="rig", help="render the moving scene from a row of static cameras (run with bpy's Python)",
        frames=24, width=160, height=90, samples=32))
    g.add_argument("--num-cameras", type=int, default=5)
    g.add_argument("--test-cameras", type=int, default=1, help="held out, between train cameras (as render-rig)")
    g.add_argument("--speed", type=float, default=4.0, help="peak screen speed of an object, px a frame at --width")
    g.add_argument("--baseline", type=float, default=0.4, help="world units between neighbouring cameras")
    c = _scene_options(blender.render_parser(
        sub, name="capture", help="render a static forward-facing capture (run with bpy's Python)",
        frames=None, width=1008, height=756))
    c.add_argument("--views", type=int, default=20)
    c.add_argument("--baseline", type=float, default=0.25, help="world units between neighbouring cameras")
    w = sub.add_parser("llff", help="write a capture as an LLFF capture (run with the project's Python)")
    w.add_argument("out", type=Path)
    w.add_argument("root", type=Path)
    w.add_argument("--factor", type=int, default=2, help="write images_<factor>/ (area-averaged)")
    i = sub.add_parser("import", help="import a render as an rgbd-seq (run with the project's Python)")
    i.add_argument("out", type=Path)
    i.add_argument("seq", type=Path)
    j = sub.add_parser("import-rig", help="import a rig render as an rgbd-rig (run with the project's Python)")
    j.add_argument("out", type=Path)
    j.add_argument("rig", type=Path)
    args = parser.parse_args(argv)
    if args.command == "render":
        render(args.out, args.seed, args.frames, args.width, args.height, args.samples, args.objects, args.speed,
               args.yaw)
        return 0
    if args.command == "rig":
        rig(args.out, args.seed, args.num_cameras, args.test_cameras, args.frames, args.width, args.height,
            args.samples, args.objects, args.speed, args.baseline)
        return 0
    if args.command == "import-rig":
        return _report(import_rig, args.out, args.rig)
    if args.command == "capture":
        capture(args.out, args.seed, args.views, args.width, args.height, args.samples, args.objects, args.baseline)
        return 0
    if args.command == "llff":
        return _report(write_capture, args.out, args.root, args.factor)
    return _report(import_sequence, args.out, args.seq)


def _scene_options(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The scene's options every rendering sub-command shares: the seed and the number of moving objects."""
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--objects", type=int, default=4)
    return parser


def _report(write, *args) -> int:
    """Run an import on the project's side: 0 and the path it wrote, or 2 and bad input's one-line error."""
    from engine.core.errors import InputError  # noqa: PLC0415

    try:
        print(f"wrote {write(*args)}")
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
