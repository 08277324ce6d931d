"""Importers: small files written in each exact layout (Blender multilayer EXR, MPI-Sintel, DeCOMPnet/VEED)."""
from __future__ import annotations

import json
import struct
from pathlib import Path

import cv2
import numpy as np
import OpenEXR
import pytest

from engine.core.colorspace import srgb_to_linear
from engine.core.errors import InputError
from engine.core.frames import rigid_inverse
from engine.io.importers import (SINTEL_TAG, frames_from_blender, frames_from_sintel, frames_from_veed, import_any,
                                 read_cam, read_dpt, read_png_linear, read_transformation_csv)
from engine.io.rgbd import read_sequence
from tests.synthetic import rigid, rotation

H, W = 16, 24



def project(k: np.ndarray, world_to_camera: np.ndarray, point: np.ndarray) -> np.ndarray:
    """OpenCV projection of a world point to (u, v) pixel coordinates (centres at +0.5)."""
    p = world_to_camera @ np.append(point, 1.0)
    return (k @ (p[:3] / p[2]))[:2]


# ---------------------------------------------------------------------------------------------- Blender

LENS_MM, SENSOR_MM = 50.0, 36.0
FOCAL = LENS_MM / SENSOR_MM * max(W, H)
BLENDER_DEPTH = 4.0


def blender_camera_to_world(i: int) -> np.ndarray:
    """A Blender camera (x right, y up, looking down -z) somewhere in a z-up world."""
    return rigid([1.0, 0.3, -0.2], 1.2 + 0.05 * i, [1.0 + 0.1 * i, -5.0, 2.0])


#: Cycles' Vector pass of the synthetic renders, (X, Y, Z, W) in Blender's y-up pixels: XY = p_prev - p,
#: ZW = p - p_next. The surface was 2.5 px left of and 1.5 px BELOW (y up: Y = -1.5) its current position
#: in the previous frame, and will be 3 px right of and 2 px below it (ZW = -(3, -2)) in the next.
BLENDER_VECTOR = (-2.5, -1.5, -3.0, 2.0)
#: What the importer must make of it (x right, y down): current -> previous, and flow to the next frame.
BLENDER_MOTION, BLENDER_FLOW = (-2.5, 1.5), (3.0, 2.0)


def write_blender_render(path: Path, vector: bool = True, layer: str = "ViewLayer", depth: bool = True) -> None:
    """A Blender-style multilayer EXR (single part, as Blender 4 writes it): half colour, float depth with
    1e10 background, Vector pass."""
    rng = np.random.default_rng(0)
    z = np.full((H, W), BLENDER_DEPTH, np.float32)
    z[:4, :] = 1e10  # background (no surface), as Cycles writes it
    channels = {f"{layer}.Combined.{c}": rng.uniform(0, 2, (H, W)).astype(np.float16) for c in "RGBA"}
    if depth:
        channels[f"{layer}.Depth.Z"] = z
    if vector:
        # Cycles writes 0 where no sample hit a surface (the background rows): the importer must not trust it.
        for c, value in zip("XYZW", BLENDER_VECTOR):
            channels[f"{layer}.Vector.{c}"] = np.full((H, W), value, np.float32)
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, channels).write(str(path))


def write_blender_scene(root: Path, numbers: tuple[int, ...] = (5, 6, 7), camera: dict | None = None) -> Path:
    (root / "render").mkdir(parents=True)
    frames = []
    for i, n in enumerate(numbers):
        write_blender_render(root / "render" / f"{n:04d}.exr")
        frames.append({"frame": n, "file": f"render/{n:04d}.exr",
                       "camera_to_world": blender_camera_to_world(i).tolist(),
                       **(camera or {"lens_mm": LENS_MM, "sensor_width_mm": SENSOR_MM})})
    (root / "cameras.json").write_text(json.dumps({"fps": 24.0, "frames": frames}))
    return root / "cameras.json"


def test_blender_conventions(tmp_path: Path) -> None:
    imported = frames_from_blender(write_blender_scene(tmp_path))
    assert (imported.fps, imported.count) == (24.0, 3)
    frames = list(imported.frames)
    assert [f.index for f in frames] == [0, 1, 2] and frames[2].time == 2 / 24
    frame = frames[1]
    np.testing.assert_allclose(frame.camera.intrinsics, [[FOCAL, 0, W / 2], [0, FOCAL, H / 2], [0, 0, 1]])
    # Depth: planar z kept as is; Blender's 1e10 background becomes +inf.
    assert np.isposinf(frame.depth[:4]).all() and (frame.depth[4:] == BLENDER_DEPTH).all()
    # Pose: a world point in front of the Blender camera projects to the same pixel before and after.
    camera_to_world = blender_camera_to_world(1)
    in_blender_camera = np.array([0.7, -0.4, -BLENDER_DEPTH])  # right, below centre, in front (-z)
    point = (camera_to_world @ np.append(in_blender_camera, 1.0))[:3]
    x, y, z = (rigid_inverse(camera_to_world) @ np.append(point, 1.0))[:3]
    blender_pixel = np.array([W / 2 + FOCAL * x / -z, H / 2 - FOCAL * y / -z])  # row from the top
    np.testing.assert_allclose(project(frame.camera.intrinsics, frame.camera.world_to_camera, point), blender_pixel)
    assert (frame.camera.world_to_camera @ np.append(point, 1.0))[2] == pytest.approx(BLENDER_DEPTH)
    # Flow: to the next frame, x right, y down.
    np.testing.assert_array_equal(frame.flow[..., 0], 3.0)
    np.testing.assert_array_equal(frame.flow[..., 1], 2.0)
    assert frame.color.dtype == np.float32 and frame.color.shape == (H, W, 3)


def test_blender_motion_vectors_sign_flip_and_background(tmp_path: Path) -> None:
    """Vector XY (p_prev - p, y up) -> motion_vectors (X, -Y), y down, pixels; NaN on background.

    A wrong x sign gives +2.5 instead of -2.5; forgetting the y flip gives -1.5 instead of +1.5; taking ZW
    (the next-frame half) instead of XY gives (3, 2) or (-3, -2): each fails the equality below.
    """
    frames = list(frames_from_blender(write_blender_scene(tmp_path)).frames)
    for frame in frames:
        mv = frame.motion_vectors
        assert mv is not None and mv.shape == (H, W, 2) and mv.dtype == np.float32
        assert np.isnan(mv[:4]).all()  # depth 1e10: Cycles wrote no (or a partial) vector there
        np.testing.assert_array_equal(mv[4:, :, 0], BLENDER_MOTION[0])
        np.testing.assert_array_equal(mv[4:, :, 1], BLENDER_MOTION[1])
        np.testing.assert_array_equal(frame.flow[4:], np.broadcast_to(BLENDER_FLOW, (H - 4, W, 2)))
    # background_depth=None keeps the 1e10 depth, and the vectors there are still NaN
    kept = next(frames_from_blender(tmp_path / "cameras.json", background_depth=None).frames)
    assert (kept.depth[:4] == 1e10).all() and np.isnan(kept.motion_vectors[:4]).all()


@pytest.mark.parametrize("camera, focal", [
    ({"focal_px": 40.0}, 40.0),
    ({"intrinsics": [[41.0, 0, 12.5], [0, 42.0, 7.5], [0, 0, 1]]}, 41.0),
])
def test_blender_intrinsics_variants(tmp_path: Path, camera: dict, focal: float) -> None:
    frame = next(frames_from_blender(write_blender_scene(tmp_path, camera=camera)).frames)
    assert frame.camera.intrinsics[0, 0] == focal


def test_blender_incomplete_camera_is_rejected_at_open(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="missing key 'sensor_width_mm'") as exc:
        frames_from_blender(write_blender_scene(tmp_path, camera={"lens_mm": 50.0}))
    assert exc.value.field == "sensor_width_mm" and exc.value.frame == 0 and "cameras.json" in str(exc.value)


def test_blender_without_vector_pass_has_no_flow(tmp_path: Path) -> None:
    cameras = write_blender_scene(tmp_path, numbers=(1,))
    write_blender_render(tmp_path / "render" / "0001.exr", vector=False)
    frame = next(frames_from_blender(cameras).frames)
    assert frame.flow is None and frame.motion_vectors is None
    seq = read_sequence(import_any(tmp_path, tmp_path / "seq", "blender"))
    assert not seq.has_channel("motion_vectors") and seq.version == 1


def test_blender_vectors_dropped_after_a_gap(tmp_path: Path) -> None:
    """Frame 8's vectors point to Blender frame 7, which is not in the sequence: dropped, with a warning."""
    with pytest.warns(UserWarning, match=r"0008.exr \(frame 8\): no motion vectors.*frame 7"):
        frames = list(frames_from_blender(write_blender_scene(tmp_path, numbers=(5, 6, 8))).frames)
    assert [f.motion_vectors is not None for f in frames] == [True, True, False]
    assert all(f.flow is not None for f in frames)
    (tmp_path / "render" / "0005.exr").unlink()  # a skipped first render: frame 6's vectors point to 5
    with pytest.warns(UserWarning) as record:
        frames = list(frames_from_blender(tmp_path / "cameras.json", skip_missing=True).frames)
    assert [(f.index, f.motion_vectors is not None) for f in frames] == [(1, False), (3, False)]
    messages = [str(w.message) for w in record]
    assert len(messages) == 3 and "0005.exr is missing" in messages[0]
    assert "0006.exr (frame 6): no motion vectors" in messages[1] and "0008.exr (frame 8)" in messages[2]


def test_blender_multipart_exr_with_a_repeated_channel_is_rejected(tmp_path: Path) -> None:
    cameras = write_blender_scene(tmp_path, numbers=(1,))
    z = np.full((H, W), 2.0, np.float32)
    parts = [OpenEXR.Part({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                          {"ViewLayer.Depth.Z": z}, name) for name in ("ViewLayer.Depth", "ViewLayer.Depth2")]
    OpenEXR.File(parts).write(str(tmp_path / "render" / "0001.exr"))
    with pytest.raises(InputError, match="'ViewLayer.Depth.Z' is in two parts") as exc:
        next(frames_from_blender(cameras).frames)
    assert "0001.exr" in str(exc.value)


BLENDER_FIXTURE = Path(__file__).parent / "data" / "blender_vectors"


def test_blender_vectors_of_a_real_cycles_render() -> None:
    """A real Cycles render (Blender 5.0.1, 32x24, two frames; made by tools/blender_vector_check.py, see
    its docstring): a cube translating and a ground plane, seen by a camera that moves, pans and tilts.

    Blender 5 writes one EXR part per pass (read here). The imported motion vectors match the exact
    current -> previous vectors (rigid motion from depth, cameras, the Object Index pass and the cube's
    recorded transforms) and Blender's own projections of surface points (``world_to_camera_view``)
    within 0.05 px (measured 0.008 px); the sky is NaN. With the y flip missing, the ground's y components
    (-0.5 to -1.3 px: it was higher up the image in the previous frame) would have the wrong sign (errors
    up to 2.6 px); with the x sign wrong, the cube's x (about -2.1 px) would be off by about 4.2 px.
    """
    from tools.blender_vector_check import compare

    report = compare(BLENDER_FIXTURE)
    assert report["rigid_count"] > 300 and report["points_count"] >= 10 and report["background_count"] > 500
    assert report["rigid_max"] < 0.05 and report["points_max"] < 0.05 and report["flow_max"] < 0.05
    assert report["background_not_nan"] == 0
    raw = report["raw_background"]  # what Cycles wrote where its depth says "no surface"
    assert (raw == 0).all(axis=1).mean() > 0.8 and (raw != 0).any()  # mostly 0, some partial edge pixels
    frames = list(frames_from_blender(BLENDER_FIXTURE / "cameras.json").frames)
    ground = frames[1].motion_vectors[-4:]  # bottom rows: ground, which was up-left of where it is now
    assert (ground[..., 0] < -0.3).all() and (ground[..., 1] < -0.5).all()


def test_blender_missing_pass_lists_channels(tmp_path: Path) -> None:
    cameras = write_blender_scene(tmp_path, numbers=(1,))
    write_blender_render(tmp_path / "render" / "0001.exr", depth=False)
    with pytest.raises(InputError) as exc:
        next(frames_from_blender(cameras).frames)
    assert exc.value.field == "ViewLayer.Depth.Z" and "0001.exr" in str(exc.value)
    assert "ViewLayer.Combined.R" in str(exc.value)
    with pytest.raises(InputError, match="ViewLayer.Combined.R"):
        next(frames_from_blender(cameras, layer="RenderLayer").frames)


def test_blender_missing_render(tmp_path: Path) -> None:
    cameras = write_blender_scene(tmp_path)
    (tmp_path / "render" / "0006.exr").unlink()
    with pytest.raises(InputError, match="missing") as exc:
        frames_from_blender(cameras)
    assert "0006.exr" in str(exc.value) and exc.value.frame == 1
    with pytest.warns(UserWarning, match="0006.exr"):
        imported = frames_from_blender(cameras, skip_missing=True)
    with pytest.warns(UserWarning, match="0007.exr .*no motion vectors"):  # they would point to the missing 0006
        assert [f.index for f in imported.frames] == [0, 2]


def test_blender_scaled_camera_is_rejected(tmp_path: Path) -> None:
    cameras = write_blender_scene(tmp_path)
    meta = json.loads(cameras.read_text())
    meta["frames"][1]["camera_to_world"] = (np.diag([1.1, 1.1, 1.1, 1.0]) @ blender_camera_to_world(1)).tolist()
    cameras.write_text(json.dumps(meta))
    with pytest.raises(InputError, match="not rigid") as exc:
        frames_from_blender(cameras)
    assert exc.value.field == "camera_to_world" and exc.value.frame == 1 and "cameras.json" in str(exc.value)


def test_import_any_blender_writes_a_valid_sequence(tmp_path: Path) -> None:
    write_blender_scene(tmp_path / "blender")
    seq = read_sequence(import_any(tmp_path / "blender", tmp_path / "seq", "blender"))
    assert (len(seq), seq.width, seq.height, seq.fps) == (3, W, H, 24.0)
    assert seq.has_channel("flow") and not seq.has_channel("object_flow")
    assert seq.has_channel("motion_vectors") and seq.version == 2 and seq.motion_camera == "included"
    expected = next(frames_from_blender(tmp_path / "blender" / "cameras.json").frames)
    np.testing.assert_array_equal(seq[0].depth, expected.depth)
    np.testing.assert_array_equal(seq[0].color, expected.color)
    np.testing.assert_array_equal(seq[0].motion_vectors, expected.motion_vectors)  # NaN in the same places


# ---------------------------------------------------------------------------------------------- MPI-Sintel

SINTEL_K = np.array([[20.0, 0.0, (W - 1) / 2], [0.0, 20.0, (H - 1) / 2], [0.0, 0.0, 1.0]])


def sintel_extrinsic(i: int) -> np.ndarray:
    return rigid([0.1, 1.0, 0.0], 0.1 * i, [0.2 * i, 0.0, -1.0])[:3]


def write_dpt(path: Path, depth: np.ndarray, tag: float = SINTEL_TAG) -> None:
    h, w = depth.shape
    path.write_bytes(struct.pack("<f", tag) + struct.pack("<ii", w, h) + depth.astype("<f4").tobytes())


def write_cam(path: Path, k: np.ndarray, extrinsic: np.ndarray, tag: float = SINTEL_TAG) -> None:
    path.write_bytes(struct.pack("<f", tag) + k.astype("<f8").tobytes() + extrinsic.astype("<f8").tobytes())


def sintel_depth(i: int) -> np.ndarray:
    return (np.arange(H * W, dtype=np.float32).reshape(H, W) / 10 + 1 + i)


def write_sintel(root: Path, scene: str = "alley_1", n: int = 3) -> Path:
    for folder in ("final", "depth", "camdata_left"):
        (root / folder / scene).mkdir(parents=True)
    for i in range(n):
        name = f"frame_{i + 1:04d}"
        bgr = np.zeros((H, W, 3), np.uint8)
        bgr[..., 0], bgr[..., 1], bgr[..., 2] = 10 * i, 128, 255  # B, G, R
        cv2.imwrite(str(root / "final" / scene / f"{name}.png"), bgr)
        write_dpt(root / "depth" / scene / f"{name}.dpt", sintel_depth(i))
        write_cam(root / "camdata_left" / scene / f"{name}.cam", SINTEL_K, sintel_extrinsic(i))
    return root


def test_sintel_values(tmp_path: Path) -> None:
    imported = frames_from_sintel(write_sintel(tmp_path), "alley_1")
    assert (imported.fps, imported.count) == (24.0, 3)
    frames = list(imported.frames)
    assert [f.index for f in frames] == [0, 1, 2] and frames[1].time == 1 / 24
    frame = frames[2]
    np.testing.assert_array_equal(frame.depth, sintel_depth(2))
    np.testing.assert_allclose(frame.camera.intrinsics, [[20, 0, W / 2], [0, 20, H / 2], [0, 0, 1]])
    np.testing.assert_array_equal(frame.camera.world_to_camera[:3], sintel_extrinsic(2))
    np.testing.assert_array_equal(frame.camera.world_to_camera[3], [0, 0, 0, 1])
    np.testing.assert_allclose(frame.color[0, 0], srgb_to_linear(np.array([255, 128, 20]) / 255), rtol=1e-6)
    unshifted = next(frames_from_sintel(tmp_path, "alley_1", principal_point_offset=0.0).frames)
    np.testing.assert_array_equal(unshifted.camera.intrinsics, SINTEL_K)


def test_sintel_readers(tmp_path: Path) -> None:
    write_dpt(tmp_path / "a.dpt", sintel_depth(0))
    np.testing.assert_array_equal(read_dpt(tmp_path / "a.dpt"), sintel_depth(0))
    write_cam(tmp_path / "a.cam", SINTEL_K, sintel_extrinsic(1))
    k, world_to_camera = read_cam(tmp_path / "a.cam")
    np.testing.assert_array_equal(k, SINTEL_K)
    np.testing.assert_array_equal(world_to_camera[:3], sintel_extrinsic(1))


@pytest.mark.parametrize("kind", ["dpt", "cam"])
@pytest.mark.parametrize("damage, message", [("truncated", "truncated"), ("tag", "bad tag")])
def test_sintel_damaged_files(tmp_path: Path, kind: str, damage: str, message: str) -> None:
    root = write_sintel(tmp_path)
    path = root / ("depth" if kind == "dpt" else "camdata_left") / "alley_1" / f"frame_0002.{kind}"
    if damage == "truncated":
        path.write_bytes(path.read_bytes()[:-10])
    elif kind == "dpt":
        write_dpt(path, sintel_depth(1), tag=1.0)
    else:
        write_cam(path, SINTEL_K, sintel_extrinsic(1), tag=1.0)
    frames = frames_from_sintel(root, "alley_1").frames
    next(frames)
    with pytest.raises(InputError, match=message) as exc:
        next(frames)
    assert f"frame_0002.{kind}" in str(exc.value)


def test_sintel_gap_in_numbering(tmp_path: Path) -> None:
    root = write_sintel(tmp_path)
    (root / "final" / "alley_1" / "frame_0002.png").unlink()
    with pytest.raises(InputError, match="number 2 is missing") as exc:
        frames_from_sintel(root, "alley_1")
    assert exc.value.frame == 1 and "final/alley_1" in str(exc.value)
    with pytest.warns(UserWarning, match="frame_0001.png and frame_0003.png"):
        imported = frames_from_sintel(root, "alley_1", skip_missing=True)
    assert [f.index for f in imported.frames] == [0, 2]


@pytest.mark.parametrize("folder, kind, field", [("depth", "dpt", "depth"), ("camdata_left", "cam", "camera")])
def test_sintel_missing_companion_file(tmp_path: Path, folder: str, kind: str, field: str) -> None:
    root = write_sintel(tmp_path)
    (root / folder / "alley_1" / f"frame_0003.{kind}").unlink()
    with pytest.raises(InputError, match="missing for image frame_0003.png") as exc:
        frames_from_sintel(root, "alley_1")
    assert exc.value.field == field and exc.value.frame == 2 and f"frame_0003.{kind}" in str(exc.value)
    with pytest.warns(UserWarning, match=f"frame_0003.{kind}"):
        assert frames_from_sintel(root, "alley_1", skip_missing=True).count == 2


def test_sintel_any_png_folder_and_import_any(tmp_path: Path) -> None:
    root = write_sintel(tmp_path / "sintel")
    (root / "final" / "alley_1").rename(root / "mine")
    frames = list(frames_from_sintel(root, "alley_1", image_dir=root / "mine").frames)
    assert len(frames) == 3
    (root / "mine").rename(root / "final" / "alley_1")
    seq = read_sequence(import_any(root, tmp_path / "seq", "sintel", scene="alley_1"))
    np.testing.assert_array_equal(seq[1].depth, frames[1].depth)
    np.testing.assert_array_equal(seq[1].color, frames[1].color)


# ---------------------------------------------------------------------------------------------- DeCOMPnet / VEED

VW, VH = 96, 54  # 1920x1080 / 20


def veed_pose(i: int) -> np.ndarray:
    return rigid([0.0, 1.0, 0.2], 0.05 * i, [0.0, 0.1 * i, 2.0])


def veed_depth(i: int) -> np.ndarray:
    return np.linspace(1.0, 50.0, VH * VW, dtype=np.float32).reshape(VH, VW) + i


def write_veed(root: Path, n: int = 3, rows: int | None = None, channel: str = "B") -> Path:
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    for i in range(n):
        cv2.imwrite(str(root / "rgb" / f"{i:04d}.png"), np.full((VH, VW, 3), 60 + i, np.uint8))
        junk = np.zeros((VH, VW), np.float32)
        channels = {"R": junk, "G": junk, channel: veed_depth(i)}
        OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                     channels).write(str(root / "depth" / f"{i:04d}.exr"))
    lines = [",".join(repr(v) for v in veed_pose(i).ravel().tolist()) for i in range(n if rows is None else rows)]
    (root / "TransformationMatrices.csv").write_text("\n".join(lines) + "\n")
    return root


def test_veed_values(tmp_path: Path) -> None:
    imported = frames_from_veed(write_veed(tmp_path / "seq00"))
    assert imported.count == 3
    frames = list(imported.frames)
    frame = frames[1]
    np.testing.assert_allclose(frame.camera.intrinsics, [[105.0, 0, 48.0], [0, 105.0, 27.0], [0, 0, 1]])
    np.testing.assert_array_equal(frame.camera.world_to_camera, veed_pose(1))
    np.testing.assert_array_equal(frame.depth, veed_depth(1))
    np.testing.assert_allclose(frame.color, srgb_to_linear(np.full((VH, VW, 3), 61 / 255)), rtol=1e-6)
    assert [f.time for f in frames] == [0.0, 1 / 30, 2 / 30]


def test_veed_depth_channel_option(tmp_path: Path) -> None:
    root = write_veed(tmp_path / "seq", channel="Z")
    with pytest.raises(InputError, match=r"no channel 'B'; channels present: \['G', 'R', 'Z'\]") as exc:
        next(frames_from_veed(root).frames)
    assert exc.value.field == "B" and "depth/0000.exr" in str(exc.value)
    np.testing.assert_array_equal(next(frames_from_veed(root, depth_channel="Z").frames).depth, veed_depth(0))


def test_veed_intrinsics_override(tmp_path: Path) -> None:
    k = np.array([[200.0, 0, 40], [0, 210.0, 30], [0, 0, 1]])
    frame = next(frames_from_veed(write_veed(tmp_path / "seq"), intrinsics=k).frames)
    np.testing.assert_array_equal(frame.camera.intrinsics, k)
    with pytest.raises(InputError, match="focal lengths must be positive") as exc:
        frames_from_veed(tmp_path / "seq", intrinsics=np.diag([0.0, 1.0, 1.0]))
    assert exc.value.field == "intrinsics"


@pytest.mark.parametrize("rows, row, message", [(2, 3, "row 3 is missing"), (4, 4, "row 4 has no frame")])
def test_veed_csv_row_count_must_match(tmp_path: Path, rows: int, row: int, message: str) -> None:
    root = write_veed(tmp_path / "seq", rows=rows)
    with pytest.raises(InputError, match=message) as exc:
        frames_from_veed(root)
    assert f"has {rows} rows" in str(exc.value) and "need 3" in str(exc.value)
    assert exc.value.field == f"row {row}" and "TransformationMatrices.csv" in str(exc.value)


@pytest.mark.parametrize("line, message", [
    ("1,2,3", "has 3 numbers, expected 16"),
    ("a" + ",0" * 15, "not numeric"),
    (",".join(repr(v) for v in np.diag([1.1, 1.1, 1.1, 1.0]).ravel().tolist()), "not rigid"),
])
def test_veed_bad_csv_row(tmp_path: Path, line: str, message: str) -> None:
    root = write_veed(tmp_path / "seq")
    csv_path = root / "TransformationMatrices.csv"
    lines = csv_path.read_text().splitlines()
    lines[1] = line
    csv_path.write_text("\n".join(lines))
    with pytest.raises(InputError, match=message) as exc:
        read_transformation_csv(csv_path)
    assert exc.value.field == "row 2" and "TransformationMatrices.csv" in str(exc.value)


def test_veed_missing_depth_and_gap(tmp_path: Path) -> None:
    root = write_veed(tmp_path / "seq")
    (root / "depth" / "0001.exr").unlink()
    with pytest.raises(InputError, match="depth file .*0001.exr is missing for image 0001.png") as exc:
        frames_from_veed(root)
    assert exc.value.frame == 1
    with pytest.warns(UserWarning, match="0001.exr"):
        imported = frames_from_veed(root, skip_missing=True)
    frames = list(imported.frames)
    assert [f.index for f in frames] == [0, 2]
    np.testing.assert_array_equal(frames[1].camera.world_to_camera, veed_pose(2))  # CSV row 2 for frame 0002
    (root / "rgb" / "0001.png").unlink()
    with pytest.raises(InputError, match="number 1 is missing"):
        frames_from_veed(root)


def test_import_any_veed_and_unknown_layout(tmp_path: Path) -> None:
    root = write_veed(tmp_path / "seq00")
    seq = read_sequence(import_any(root, tmp_path / "out", "veed", fps=25.0))
    assert (len(seq), seq.width, seq.height, seq.fps) == (3, VW, VH, 25.0)
    np.testing.assert_array_equal(seq[2].depth, veed_depth(2))
    np.testing.assert_array_equal(seq.cameras[2].world_to_camera, veed_pose(2))
    with pytest.raises(InputError, match="unknown layout 'colmap'") as exc:
        import_any(root, tmp_path / "x", "colmap")
    assert exc.value.field == "layout"


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_png_decoding_by_table_equals_decoding_each_pixel(tmp_path: Path, dtype) -> None:
    """``read_png_linear`` looks each code up in a table: the float32 that decoding every pixel gives, to the bit."""
    top = np.iinfo(dtype).max
    rng = np.random.default_rng(3)
    image = rng.integers(0, top + 1, size=(7, 9, 3), dtype=dtype)
    image[0, 0], image[0, 1] = 0, top
    cv2.imwrite(str(tmp_path / "c.png"), image)
    got = read_png_linear(tmp_path / "c.png")
    assert got.dtype == np.float32 and got.shape == (7, 9, 3)
    assert np.array_equal(got, srgb_to_linear(image[..., ::-1].astype(np.float32) / top))
    gray = image[..., 0]
    cv2.imwrite(str(tmp_path / "g.png"), gray)
    assert np.array_equal(read_png_linear(tmp_path / "g.png"), np.repeat(
        srgb_to_linear(gray.astype(np.float32) / top)[..., None], 3, axis=-1))
