"""Bad input thrown at the public entry points; prints every case that did not end in one InputError.

Usage: python docs/results/2026-11-27-bad-input-fuzz.py SEQUENCE_DIR FIELD_EXPORT_DIR RIG_DIR
(an rgbd-seq, an exported static field, an rgbd-rig; copies are damaged under a temporary folder).
"""
import copy
import json
import os
import shutil
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

from engine.core.errors import InputError
from engine.fields.render import load_field, render_field
from engine.io.rgbd import read_rig, read_sequence
from engine.runtime.session import NotReadyError, Session, SessionConfig, engine_camera

warnings.simplefilter("ignore")
sequence_dir, field_dir, rig_dir = (Path(p) for p in sys.argv[1:4])
work = Path(tempfile.mkdtemp())
found = []
tried = [0]


def expect_input_error(group, name, fn):
    tried[0] += 1
    try:
        fn()
    except (InputError, NotReadyError):
        return
    except Exception as exc:  # noqa: BLE001
        found.append((group, name, type(exc).__name__, str(exc)[:120]))
        return
    found.append((group, name, "accepted", ""))


def damaged_copy(src: Path, damage) -> Path:
    dst = work / src.name
    shutil.rmtree(dst, ignore_errors=True)
    shutil.copytree(src, dst)
    damage(dst)
    return dst


def with_json(name, change):
    def damage(root):
        meta = json.loads((root / name).read_text())
        change(meta)
        (root / name).write_text(json.dumps(meta))
    return damage


# Session: colours, depths, poses, projections and times (every method, colour encoding in and out)
H, W = 24, 32
K = np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]])
bad_colors = [np.zeros((H, W, 2), np.float32), np.full((H, W, 3), np.nan, np.float32), "x", None,
              np.zeros((H + 1, W, 3), np.float32), np.zeros((H, W, 3), object), np.zeros((0, W, 3), np.float32)]
bad_depths = [np.full((H, W), -1.0, np.float32), np.full((H, W), np.nan, np.float32), "x", None,
              np.ones((W, H), np.float32)]
bad_matrices = ["p", None, {"a": 1}, [[1.0, 2.0], [3.0]], b"xx", np.full((4, 4), np.nan), np.zeros((4, 4))]
for method in ("reproject", "flow2d", "mvec", "decomp", "auto"):
    for space in ("linear", "srgb", "srgb8"):
        session = Session(SessionConfig(engine="opencv", width=W, height=H, method=method, color_in=space,
                                        color_out="srgb8" if space == "srgb8" else "linear"), backend="cpu")
        color = np.zeros((H, W, 3), np.uint8) if space == "srgb8" else np.full((H, W, 3), 0.5, np.float32)
        depth = np.full((H, W), 3.0, np.float32)
        group = f"Session {method} {space}"
        for c in bad_colors:
            expect_input_error(group, f"submit colour {type(c).__name__}", lambda: session.submit(c, depth, np.eye(4), K, 0.0))
        for d in bad_depths:
            expect_input_error(group, f"submit depth {type(d).__name__}", lambda: session.submit(color, d, np.eye(4), K, 0.0))
        for m in bad_matrices:
            expect_input_error(group, f"submit view {m!r:.20}", lambda: session.submit(color, depth, m, K, 0.0))
            expect_input_error(group, f"submit projection {m!r:.20}", lambda: session.submit(color, depth, np.eye(4), m, 0.0))
        vectors = np.zeros((H, W, 2), np.float32)
        session.submit(color, depth, np.eye(4), K, 10.0, motion_vectors=vectors)
        session.submit(color, depth, np.eye(4), K, 10.1, motion_vectors=vectors)
        # times far from the rendered frames: refused where motion is extrapolated (flow2d, decomp); reproject,
        # and mvec with zero vectors (nothing moves), have no motion to extrapolate and answer any time
        far = [-1e300, 1e300, 10.1 + 6.41] if method in ("flow2d", "decomp") else []
        for t in [np.nan, np.inf, "t", None] + far:
            expect_input_error(group, f"predict time {t!r}", lambda: session.predict(np.eye(4), K, t))
for engine in ("opengl", "unity", "godot", "unreal"):
    config = SessionConfig(engine=engine, width=W, height=H)
    for m in bad_matrices:
        expect_input_error(f"engine_camera {engine}", f"view {m!r:.20}", lambda: engine_camera(config, m, 90.0 if engine == "unreal" else np.eye(4)))
        expect_input_error(f"engine_camera {engine}", f"projection {m!r:.20}", lambda: engine_camera(config, np.eye(4), m))

# rgbd-seq: sequence.json values and damaged EXR files
meta = json.loads((sequence_dir / "sequence.json").read_text())
first_exr = sorted((sequence_dir / "frames").iterdir())[3].name
for name, damage in {
        "width string": with_json("sequence.json", lambda m: m.__setitem__("width", "640")),
        "fps 0": with_json("sequence.json", lambda m: m.__setitem__("fps", 0)),
        "frames empty": with_json("sequence.json", lambda m: m.__setitem__("frames", [])),
        "file outside": with_json("sequence.json", lambda m: m["frames"][0].__setitem__("file", "../../etc/passwd")),
        "intrinsics ragged": with_json("sequence.json", lambda m: m["frames"][0].__setitem__("intrinsics", [[1], [2, 3]])),
        "pose NaN": with_json("sequence.json", lambda m: m["frames"][0].__setitem__("world_to_camera", [[float("nan")] * 4] * 4)),
        "times backwards": with_json("sequence.json", lambda m: m["frames"][1].__setitem__("time", -5.0)),
        "objects string": with_json("sequence.json", lambda m: m.__setitem__("objects", "x")),
        "JSON garbage": lambda root: (root / "sequence.json").write_text("{"),
        "EXR cut in its header": lambda root: (root / "frames" / first_exr).write_bytes((root / "frames" / first_exr).read_bytes()[:40]),
        "EXR cut in its pixels": lambda root: (root / "frames" / first_exr).write_bytes((root / "frames" / first_exr).read_bytes()[:1000]),
        "EXR random bytes": lambda root: (root / "frames" / first_exr).write_bytes(os.urandom(5000)),
        "EXR missing": lambda root: (root / "frames" / first_exr).unlink()}.items():
    root = damaged_copy(sequence_dir, damage)
    expect_input_error("rgbd-seq", name, lambda: [read_sequence(root)[i] for i in range(len(read_sequence(root)))])

# exported fields: field.json values, field.npz arrays
K_small = np.array([[100.0, 0, 16], [0, 100, 12], [0, 0, 1]])
T = np.eye(4)
T[2, 3] = 4.0
arrays = dict(np.load(field_dir / "field.npz"))


def with_arrays(change):
    def damage(root):
        data = {k: v.copy() for k, v in arrays.items()}
        change(data)
        np.savez(root / "field.npz", **data)
    return damage


for name, damage in {
        "scene kind": with_json("field.json", lambda m: m["scene"].__setitem__("kind", "x")),
        "near string": with_json("field.json", lambda m: m["scene"].__setitem__("near", "a")),
        "far below near": with_json("field.json", lambda m: m["scene"].__setitem__("far", 0.5)),
        "box NaN": with_json("field.json", lambda m: m["scene"].__setitem__("box_min", [float("nan")] * 3)),
        "samples 0": with_json("field.json", lambda m: m["render"].__setitem__("num_samples", 0)),
        "samples 1e9": with_json("field.json", lambda m: m["render"].__setitem__("num_samples", 10 ** 9)),
        "spacing": with_json("field.json", lambda m: m["render"].__setitem__("spacing", "x")),
        "no planes": with_json("field.json", lambda m: m["field"].__setitem__("planes", [])),
        "plane axes": with_json("field.json", lambda m: m["field"].__setitem__("plane_axes", [[0, 0], [0, 2], [1, 2]])),
        "direction degree 9": with_json("field.json", lambda m: m["field"].__setitem__("direction_degree", 9)),
        "background of 2": with_json("field.json", lambda m: m.__setitem__("background", [1, 1])),
        "JSON list": lambda root: (root / "field.json").write_text("[]"),
        "npz garbage": lambda root: (root / "field.npz").write_bytes(b"garbage"),
        "NaN weight": with_arrays(lambda d: d["density_w0"].__setitem__((0, 0), np.nan)),
        "weight shape": with_arrays(lambda d: d.__setitem__("density_w0", np.zeros((3, 3), np.float32)))}.items():
    root = damaged_copy(field_dir, damage)
    expect_input_error("field", name, lambda: render_field(load_field(root), K_small, T, 32, 24))

# rgbd-rig: rig.json values
for name, damage in {
        "cameras string": with_json("rig.json", lambda m: m.__setitem__("cameras", "x")),
        "camera outside": with_json("rig.json", lambda m: m["cameras"].__setitem__(0, "../../etc")),
        "camera twice": with_json("rig.json", lambda m: m["cameras"].__setitem__(1, m["cameras"][0])),
        "unknown train camera": with_json("rig.json", lambda m: m.__setitem__("train_cameras", ["nope"])),
        "sequence missing": lambda root: shutil.rmtree(root / json.loads((root / "rig.json").read_text())["cameras"][1])}.items():
    root = damaged_copy(rig_dir, damage)
    expect_input_error("rgbd-rig", name, lambda: [s[0] for s in read_rig(root).cameras.values()])

for row in found:
    print(row)
print(f"{len(found)} of {tried[0]} cases did not end in one InputError")
shutil.rmtree(work, ignore_errors=True)
