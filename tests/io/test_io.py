"""rgbd-seq / rgbd-rig reading and writing: exact round trips, sRGB decoding, one test per validation rule."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest

from engine.core.colorspace import linear_to_srgb, srgb_to_linear
from engine.core.errors import InputError
from engine.core.frames import Camera, Frame, SceneObject
from engine.io.exr import read_exr, read_exr_info, write_exr
from engine.io.rgbd import read_rig, read_sequence, write_rig, write_sequence
from tests.synthetic import rigid, rotation, two_layer_sequence

H, W, N = 16, 24, 4
BAD_POSITION, BAD_INDEX = 1, 2  # the frame the bad-input tests break: position 1 has index 2



def make_frames(n: int = N, seed: int = 0, times: np.ndarray | None = None) -> list[Frame]:
    """n frames of W x H with every optional channel, sky (+inf) pixels, indices 0, 2, 4, ..."""
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(n):
        depth = rng.uniform(0.5, 20.0, (H, W)).astype(np.float32)
        depth[:3, :5] = np.inf
        k = np.array([[30.0 + i, 0.0, W / 2], [0.0, 31.5, H / 2 + 0.25], [0.0, 0.0, 1.0]])
        frames.append(Frame(
            index=2 * i, time=float(i / 24 if times is None else times[i]),
            color=rng.uniform(0.0, 4.0, (H, W, 3)).astype(np.float32), depth=depth,
            camera=Camera(k, rigid([0.2, 1.0, 0.1], 0.1 * i + 0.3, [0.1 * i, -0.2, 1.5])),
            object_id=rng.integers(0, 3, (H, W)).astype(np.int32), moving=rng.random((H, W)) > 0.5,
            flow=rng.normal(0.0, 3.0, (H, W, 2)).astype(np.float32),
            object_flow=rng.normal(0.0, 1.0, (H, W, 2)).astype(np.float32)))
    return frames


def make_objects(n: int = N) -> list[SceneObject]:
    return [SceneObject(id=1, name="cube", moving=True,
                        world_from_object=np.stack([rigid([0, 0, 1], 0.2 * i, [i, 0, 3]) for i in range(n)])),
            SceneObject(id=7, name="floor", moving=False, world_from_object=np.tile(np.eye(4), (n, 1, 1)))]


@pytest.fixture
def seq_dir(tmp_path: Path) -> Path:
    return write_sequence(tmp_path / "seq", make_frames(), fps=24.0, objects=make_objects())


def edit_json(seq_dir: Path, edit: Callable[[dict[str, Any]], None]) -> None:
    path = seq_dir / "sequence.json"
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))


def edit_exr(seq_dir: Path, edit: Callable[[dict[str, np.ndarray]], None], position: int = BAD_POSITION) -> None:
    path = seq_dir / "frames" / f"{2 * position:06d}.exr"
    channels = read_exr(path)
    edit(channels)
    write_exr(path, channels)


def assert_names(exc: InputError, *, file: str, field: str | None, frame: int | None) -> None:
    """The message locates the problem: file, frame and field."""
    message = str(exc)
    assert file in message, message
    if field is not None:
        assert exc.field == field and f"field '{field}'" in message, message
    if frame is not None:
        assert exc.frame == frame and f"frame {frame}" in message, message


def assert_frames_equal(a: Frame, b: Frame) -> None:
    assert (a.index, a.time) == (b.index, b.time)
    for name in ("color", "depth", "flow", "object_flow", "object_id", "moving"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    np.testing.assert_array_equal(a.camera.intrinsics, b.camera.intrinsics)
    np.testing.assert_array_equal(a.camera.world_to_camera, b.camera.world_to_camera)


# ---------------------------------------------------------------------------------------------- round trips

def test_round_trip_is_exact(seq_dir: Path) -> None:
    seq = read_sequence(seq_dir)
    frames = make_frames()
    assert (seq.width, seq.height, seq.fps, seq.color_space, len(seq)) == (W, H, 24.0, "linear-srgb", N)
    np.testing.assert_array_equal(seq.indices, [0, 2, 4, 6])
    np.testing.assert_array_equal(seq.times, [f.time for f in frames])
    for original, loaded in zip(frames, seq):
        assert_frames_equal(original, loaded)
        assert loaded.color.dtype == loaded.depth.dtype == loaded.flow.dtype == np.float32
        assert loaded.object_id.dtype == np.int32 and loaded.moving.dtype == bool
        assert np.isposinf(loaded.depth[:3, :5]).all()
    for original, loaded in zip(make_objects(), seq.objects):
        assert (original.id, original.name, original.moving) == (loaded.id, loaded.name, loaded.moving)
        np.testing.assert_array_equal(original.world_from_object, loaded.world_from_object)
    assert_frames_equal(seq[-1], frames[-1])


def test_channels_are_float_and_color_half_on_request(tmp_path: Path) -> None:
    frames = make_frames(2)
    write_sequence(tmp_path / "s", frames, fps=30.0, half_color=True)
    import OpenEXR
    stored = OpenEXR.File(str(tmp_path / "s/frames/000000.exr"), separate_channels=True).channels()
    types = {name: channel.pixels.dtype for name, channel in stored.items()}
    assert types["R"] == np.float16 and types["Z"] == types["flow.X"] == types["object_id"] == np.float32
    loaded = read_sequence(tmp_path / "s")[0]
    np.testing.assert_array_equal(loaded.color, frames[0].color.astype(np.float16).astype(np.float32))
    np.testing.assert_array_equal(loaded.depth, frames[0].depth)


def test_write_streams_a_generator_and_copies_a_sequence(seq_dir: Path, tmp_path: Path) -> None:
    copy = write_sequence(tmp_path / "copy", read_sequence(seq_dir), fps=24.0, progress=False)
    for a, b in zip(read_sequence(seq_dir), read_sequence(copy)):
        assert_frames_equal(a, b)
    minimal = (Frame(f.index, f.time, f.color, f.depth, f.camera) for f in make_frames(2))
    seq = read_sequence(write_sequence(tmp_path / "minimal", minimal, fps=24.0))
    assert seq[1].flow is None and seq[1].object_id is None and seq.objects == []


def test_has_channel(seq_dir: Path, tmp_path: Path) -> None:
    seq = read_sequence(seq_dir)
    assert set(seq.channels) == {"R", "G", "B", "Z", "object_id", "moving", "flow.X", "flow.Y",
                                 "object_flow.X", "object_flow.Y"}
    assert all(seq.has_channel(n) for n in ("color", "depth", "flow", "object_flow", "object_id", "flow.X"))
    f = make_frames(1)[0]
    bare_frame = Frame(f.index, f.time, f.color, f.depth, f.camera)
    bare = read_sequence(write_sequence(tmp_path / "bare", [bare_frame], fps=1.0))
    assert not any(bare.has_channel(n) for n in ("flow", "object_flow", "object_id", "moving"))


def test_read_accepts_the_json_path_and_rejects_out_of_range_positions(seq_dir: Path) -> None:
    seq = read_sequence(seq_dir / "sequence.json")
    assert seq.path == seq_dir
    with pytest.raises(IndexError):
        seq[N]


def test_frames_load_lazily(seq_dir: Path) -> None:
    edit_exr(seq_dir, lambda ch: ch.__setitem__("Z", np.full((H, W), np.nan, np.float32)))
    seq = read_sequence(seq_dir)  # metadata only: opening succeeds
    seq[0]
    with pytest.raises(InputError):
        seq[BAD_POSITION]


# ---------------------------------------------------------------------------------------------- sRGB

def test_srgb_eotf_known_values() -> None:
    encoded = np.array([0.0, 0.04045, 0.5, 1.0])
    expected = np.array([0.0, 0.04045 / 12.92, ((0.5 + 0.055) / 1.055) ** 2.4, 1.0])
    np.testing.assert_allclose(srgb_to_linear(encoded), expected, rtol=1e-6)
    assert abs(float(srgb_to_linear(0.5)) - 0.2140411) < 1e-6  # not gamma 2.2 (0.2176)
    x = np.linspace(0.0, 1.0, 1001)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-6)


def test_srgb_sequence_is_decoded_to_linear(seq_dir: Path) -> None:
    stored = np.random.default_rng(1).uniform(0.0, 1.0, (H, W, 3)).astype(np.float32)
    edit_json(seq_dir, lambda m: m.__setitem__("color_space", "srgb"))
    edit_exr(seq_dir, lambda ch: ch.update(R=stored[..., 0], G=stored[..., 1], B=stored[..., 2]))
    seq = read_sequence(seq_dir)
    assert seq.color_space == "srgb"
    linear = seq[BAD_POSITION].color
    c = stored.astype(np.float64)
    expected = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    np.testing.assert_allclose(linear, expected, rtol=1e-6, atol=1e-9)


def test_srgb_write_encodes_and_round_trips(tmp_path: Path) -> None:
    frame = make_frames(1)[0]
    frame = frame.with_color(np.clip(frame.color / 4.0, 0.0, 1.0))
    path = write_sequence(tmp_path / "s", [frame], fps=1.0, color_space="srgb")
    np.testing.assert_allclose(read_exr(path / "frames/000000.exr")["G"], linear_to_srgb(frame.color[..., 1]))
    np.testing.assert_allclose(read_sequence(path)[0].color, frame.color, atol=1e-6)


def test_srgb_values_outside_unit_range_are_rejected(seq_dir: Path, tmp_path: Path) -> None:
    edit_json(seq_dir, lambda m: m.__setitem__("color_space", "srgb"))
    with pytest.raises(InputError) as exc:
        read_sequence(seq_dir)[BAD_POSITION]  # the synthetic colour goes up to 4
    assert_names(exc.value, file="frames/000002.exr", field="RGB", frame=BAD_INDEX)
    with pytest.raises(InputError) as exc:
        write_sequence(tmp_path / "hdr", make_frames(1), fps=1.0, color_space="srgb")
    assert_names(exc.value, file="000000.exr", field="RGB", frame=0)


# ---------------------------------------------------------------------------------------------- bad metadata

def set_top(key: str, value: Any) -> Callable[[dict], None]:
    return lambda m: m.__setitem__(key, value)


def set_frame(key: str, value: Any, position: int = BAD_POSITION) -> Callable[[dict], None]:
    return lambda m: m["frames"][position].__setitem__(key, value)


def edit_matrix(key: str, change: Callable[[np.ndarray], np.ndarray]) -> Callable[[dict], None]:
    def edit(m: dict) -> None:
        entry = m["frames"][BAD_POSITION]
        entry[key] = change(np.array(entry[key], dtype=np.float64)).tolist()
    return edit


def scaled(m: np.ndarray) -> np.ndarray:
    m[:3, :3] *= 1.1
    return m


def reflected(m: np.ndarray) -> np.ndarray:
    m[0, :3] *= -1
    return m


def with_value(row: int, col: int, value: float) -> Callable[[np.ndarray], np.ndarray]:
    def change(m: np.ndarray) -> np.ndarray:
        m[row, col] = value
        return m
    return change


def set_object(key: str, value: Any, k: int = 0) -> Callable[[dict], None]:
    return lambda m: m["objects"][k].__setitem__(key, value)


def scale_object(m: dict) -> None:
    transforms = np.array(m["objects"][0]["world_from_object"])
    transforms[2, :3, :3] *= 1.1
    m["objects"][0]["world_from_object"] = transforms.tolist()


BAD_METADATA = [
    # (id, edit, field, frame index named in the message or None)
    ("format", set_top("format", "rgbd-sequence"), "format", None),
    ("version", set_top("version", 3), "version", None),
    ("version-string", set_top("version", "1"), "version", None),
    ("width-zero", set_top("width", 0), "width", None),
    ("width-string", set_top("width", "24"), "width", None),
    ("height-float", set_top("height", 16.0), "height", None),
    ("height-negative", set_top("height", -16), "height", None),
    ("fps-zero", set_top("fps", 0), "fps", None),
    ("fps-negative", set_top("fps", -30.0), "fps", None),
    ("fps-missing", lambda m: m.pop("fps"), "fps", None),
    ("color-space", set_top("color_space", "rec2020"), "color_space", None),
    ("depth-kind", set_top("depth", "ray-distance"), "depth", None),
    ("camera-convention", set_top("camera_convention", "opengl"), "camera_convention", None),
    ("no-frames", set_top("frames", []), "frames", None),
    ("intrinsics-shape", set_frame("intrinsics", [[30, 0, 12], [0, 30, 8]]), "intrinsics", BAD_INDEX),
    ("intrinsics-fx-zero", edit_matrix("intrinsics", with_value(0, 0, 0.0)), "intrinsics", BAD_INDEX),
    ("intrinsics-fy-negative", edit_matrix("intrinsics", with_value(1, 1, -30.0)), "intrinsics", BAD_INDEX),
    ("intrinsics-singular", set_frame("intrinsics", np.zeros((3, 3)).tolist()), "intrinsics", BAD_INDEX),
    ("intrinsics-nan", edit_matrix("intrinsics", with_value(0, 2, np.nan)), "intrinsics", BAD_INDEX),
    ("intrinsics-missing", lambda m: m["frames"][BAD_POSITION].pop("intrinsics"), "intrinsics", BAD_INDEX),
    ("pose-shape", edit_matrix("world_to_camera", lambda m: m[:3]), "world_to_camera", BAD_INDEX),
    ("pose-scale", edit_matrix("world_to_camera", scaled), "world_to_camera", BAD_INDEX),
    ("pose-reflection", edit_matrix("world_to_camera", reflected), "world_to_camera", BAD_INDEX),
    ("pose-nan", edit_matrix("world_to_camera", with_value(0, 3, np.nan)), "world_to_camera", BAD_INDEX),
    ("pose-inf", edit_matrix("world_to_camera", with_value(1, 3, np.inf)), "world_to_camera", BAD_INDEX),
    ("pose-last-row", edit_matrix("world_to_camera", with_value(3, 0, 0.5)), "world_to_camera", BAD_INDEX),
    ("pose-not-numeric", set_frame("world_to_camera", [["a"] * 4] * 4), "world_to_camera", BAD_INDEX),
    ("index-negative", set_frame("index", -1, 2), "index", None),
    ("index-repeated", set_frame("index", BAD_INDEX, 2), "index", BAD_INDEX),
    ("index-not-int", set_frame("index", 2.5), "index", None),
    ("time-decreasing", set_frame("time", -1.0), "time", BAD_INDEX),
    ("time-nan", set_frame("time", np.nan), "time", BAD_INDEX),
    ("time-string", set_frame("time", "0.1"), "time", BAD_INDEX),
    ("file-not-string", set_frame("file", 3), "file", BAD_INDEX),
    ("objects-not-list", set_top("objects", {"id": 1}), "objects", None),
    ("object-id-zero", set_object("id", 0), "objects[0].id", None),
    ("object-id-duplicate", set_object("id", 1, k=1), "objects[id=1].id", None),
    ("object-moving-not-bool", set_object("moving", "yes"), "objects[id=1].moving", None),
    ("object-too-few-transforms", lambda m: m["objects"][0]["world_from_object"].pop(),
     "objects[id=1].world_from_object", None),
    ("object-transform-shape", set_object("world_from_object", np.eye(4).tolist()),
     "objects[id=1].world_from_object", None),
    ("object-transform-ragged", set_object("world_from_object", [[1, 2], [3]]),
     "objects[id=1].world_from_object", None),
    ("object-transform-scaled", scale_object, "objects[id=1].world_from_object", 4),
]


@pytest.mark.parametrize("edit, field, frame", [c[1:] for c in BAD_METADATA], ids=[c[0] for c in BAD_METADATA])
def test_bad_metadata_is_rejected_at_open(seq_dir: Path, edit: Callable, field: str, frame: int | None) -> None:
    edit_json(seq_dir, edit)
    with pytest.raises(InputError) as exc:
        read_sequence(seq_dir)
    assert_names(exc.value, file="sequence.json", field=field, frame=frame)


def test_decreasing_index_names_the_frame(seq_dir: Path) -> None:
    edit_json(seq_dir, set_frame("index", 1, 2))  # indices 0, 2, 1, 6
    with pytest.raises(InputError, match="strictly increasing") as exc:
        read_sequence(seq_dir)
    assert_names(exc.value, file="sequence.json", field="index", frame=1)


def test_missing_frame_file(seq_dir: Path) -> None:
    (seq_dir / "frames" / "000004.exr").unlink()
    with pytest.raises(InputError, match="does not exist") as exc:
        read_sequence(seq_dir)
    assert_names(exc.value, file="frames/000004.exr", field="file", frame=4)


def test_missing_or_invalid_sequence_json(tmp_path: Path, seq_dir: Path) -> None:
    with pytest.raises(InputError) as exc:
        read_sequence(tmp_path / "nowhere")
    assert_names(exc.value, file="nowhere/sequence.json", field=None, frame=None)
    (seq_dir / "sequence.json").write_text("{ not json")
    with pytest.raises(InputError, match="not valid JSON") as exc:
        read_sequence(seq_dir)
    assert_names(exc.value, file="sequence.json", field=None, frame=None)


# ---------------------------------------------------------------------------------------------- bad frame data

def set_channel(name: str, change: Callable[[np.ndarray], None]) -> Callable[[dict], None]:
    def edit(ch: dict) -> None:
        change(ch[name])
    return edit


def put(row: int, col: int, value: float) -> Callable[[np.ndarray], None]:
    def change(a: np.ndarray) -> None:
        a[row, col] = value
    return change


def rename(old: str, new: str) -> Callable[[dict], None]:
    return lambda ch: ch.__setitem__(new, ch.pop(old))


def blender_names(ch: dict) -> None:
    for old, new in (("R", "ViewLayer.Combined.R"), ("G", "ViewLayer.Combined.G"), ("B", "ViewLayer.Combined.B"),
                     ("Z", "ViewLayer.Depth.Z")):
        ch[new] = ch.pop(old)


def crop(ch: dict) -> None:
    for name in ch:
        ch[name] = ch[name][:, :-2]


BAD_FRAMES = [
    # (id, edit of the EXR channels, field, message fragment)
    ("depth-nan", set_channel("Z", put(4, 4, np.nan)), "Z", "NaN"),
    ("depth-neg-inf", set_channel("Z", put(4, 4, -np.inf)), "Z", "-inf"),
    ("depth-zero", set_channel("Z", put(4, 4, 0.0)), "Z", "zero or negative"),
    ("depth-negative", set_channel("Z", put(4, 4, -2.0)), "Z", "zero or negative"),
    ("depth-named-depth", rename("Z", "depth"), "Z", "'depth'"),
    ("blender-channel-names", blender_names, "R", "ViewLayer.Depth.Z"),
    ("wrong-size", crop, "Z", "sequence.json says 24x16"),
    ("lone-flow-x", lambda ch: ch.pop("flow.Y"), "flow.X", "flow.Y"),
    ("lone-object-flow-y", lambda ch: ch.pop("object_flow.X"), "object_flow.Y", "object_flow.X"),
    ("flow-nan", set_channel("flow.Y", put(0, 0, np.nan)), "flow", "non-finite"),
    ("color-nan", set_channel("G", put(1, 1, np.nan)), "RGB", "non-finite"),
    ("color-negative", set_channel("B", put(1, 1, -0.5)), "RGB", "negative"),
    ("object-id-fraction", set_channel("object_id", put(2, 2, 1.5)), "object_id", "integers"),
    ("moving-not-binary", set_channel("moving", put(2, 2, 2.0)), "moving", "0 and 1"),
]


@pytest.mark.parametrize("edit, field, fragment", [c[1:] for c in BAD_FRAMES], ids=[c[0] for c in BAD_FRAMES])
def test_bad_frame_data_is_rejected_on_load(seq_dir: Path, edit: Callable, field: str, fragment: str) -> None:
    edit_exr(seq_dir, edit)
    seq = read_sequence(seq_dir)
    with pytest.raises(InputError) as exc:
        seq[BAD_POSITION]
    assert fragment in str(exc.value)
    assert_names(exc.value, file="frames/000002.exr", field=field, frame=BAD_INDEX)


def test_missing_channel_message_lists_present_channels(seq_dir: Path) -> None:
    edit_exr(seq_dir, rename("Z", "depth"))
    with pytest.raises(InputError) as exc:
        read_sequence(seq_dir)[BAD_POSITION]
    assert "missing required channel(s) ['Z']" in str(exc.value)
    assert "channels present: ['B', 'G', 'R', 'depth'," in str(exc.value)


@pytest.mark.parametrize("damage", ["garbage", "truncated"])
def test_unreadable_exr_names_the_file(seq_dir: Path, damage: str) -> None:
    path = seq_dir / "frames" / "000002.exr"
    data = path.read_bytes()
    path.write_bytes(b"this is not an EXR" if damage == "garbage" else data[: len(data) // 2])
    with pytest.raises(InputError) as exc:
        read_sequence(seq_dir)[BAD_POSITION]
    assert_names(exc.value, file="frames/000002.exr", field=None, frame=None)


@pytest.mark.parametrize("keep", [40, 0.5, 0.9, -1])
def test_a_cut_exr_is_one_quiet_error_saying_so(tmp_path: Path, capfd, keep) -> None:
    """A file cut in its header or in its pixels (the header intact: OpenEXR then keeps no part and prints dozens
    of lines) is an InputError that says it is truncated, not that channels are missing, and nothing else is
    printed."""
    rng = np.random.default_rng(3)
    z = rng.uniform(1, 5, (64, 48)).astype(np.float32)  # random: the compressed pixels are long
    write_exr(tmp_path / "a.exr", {"R": z, "G": z, "B": z, "Z": z}, half={"R", "G", "B"})
    data = (tmp_path / "a.exr").read_bytes()
    cut = keep if isinstance(keep, int) and keep > 0 else int(len(data) * keep) if keep > 0 else len(data) - 16
    (tmp_path / "a.exr").write_bytes(data[:cut])
    capfd.readouterr()
    with pytest.raises(InputError, match="truncated") as exc:
        read_exr(tmp_path / "a.exr")
    assert exc.value.file.endswith("a.exr") and "\n" not in str(exc.value)
    assert capfd.readouterr() == ("", "")


def test_exr_helpers(tmp_path: Path) -> None:
    z = np.arange(12, dtype=np.float32).reshape(3, 4)
    write_exr(tmp_path / "a.exr", {"Z": z, "R": z}, half={"R"})
    info = read_exr_info(tmp_path / "a.exr")
    assert (info.width, info.height, set(info.channels)) == (4, 3, {"Z", "R"})
    channels = read_exr(tmp_path / "a.exr")
    assert channels["R"].dtype == np.float32
    np.testing.assert_array_equal(channels["Z"], z)
    with pytest.raises(InputError, match="does not exist"):
        read_exr(tmp_path / "missing.exr")


# ---------------------------------------------------------------------------------------------- bad writes

def test_write_rejects_invalid_frames(tmp_path: Path) -> None:
    frames = make_frames(3)
    frames[1].depth[0, 0] = np.nan
    with pytest.raises(InputError, match="NaN") as exc:
        write_sequence(tmp_path / "s", frames, fps=24.0)
    assert_names(exc.value, file="frames/000002.exr", field="Z", frame=2)


def test_write_rejects_inconsistent_streams(tmp_path: Path) -> None:
    frames = make_frames(3)
    small = Frame(4, 1.0, frames[2].color[:8], frames[2].depth[:8], frames[2].camera)
    with pytest.raises(InputError, match="the first frame is 24x16") as exc:
        write_sequence(tmp_path / "a", frames[:2] + [small], fps=24.0)
    assert_names(exc.value, file="000004.exr", field="Z", frame=4)
    with pytest.raises(InputError, match="strictly increase") as exc:
        write_sequence(tmp_path / "b", [frames[1], frames[0]], fps=24.0)
    assert_names(exc.value, file="000000.exr", field="index", frame=0)
    frames[1].time = -1.0
    with pytest.raises(InputError) as exc:
        write_sequence(tmp_path / "c", frames, fps=24.0)
    assert_names(exc.value, file="000002.exr", field="time", frame=2)


@pytest.mark.parametrize("kwargs, field", [
    (dict(fps=0.0), "fps"),
    (dict(fps=float("nan")), "fps"),
    (dict(fps=24.0, color_space="aces"), "color_space"),
    (dict(fps=24.0, objects=make_objects(N + 1)), "objects[id=1].world_from_object"),
    (dict(fps=24.0, objects=[SceneObject(0, "x", True, np.tile(np.eye(4), (N, 1, 1)))]), "objects[0].id"),
])
def test_write_rejects_bad_arguments(tmp_path: Path, kwargs: dict, field: str) -> None:
    with pytest.raises(InputError) as exc:
        write_sequence(tmp_path / "s", make_frames(), **kwargs)
    assert exc.value.field == field


def test_write_rejects_an_empty_stream(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no frames"):
        write_sequence(tmp_path / "s", [], fps=24.0)


# ---------------------------------------------------------------------------------------------- rigs

def write_test_rig(root: Path, counts: tuple[int, ...] = (2, 2, 2), shift: float = 0.0) -> Path:
    times = np.arange(max(counts)) / 24
    sequences = {f"cam{c}": make_frames(n, seed=c, times=times + (shift if c == 2 else 0.0))
                 for c, n in enumerate(counts)}
    return write_rig(root, sequences, train=["cam0", "cam1"], test=["cam2"], fps=24.0)


def test_rig_round_trip(tmp_path: Path) -> None:
    rig = read_rig(write_test_rig(tmp_path / "rig"))
    assert list(rig.cameras) == ["cam0", "cam1", "cam2"]
    assert (rig.train_cameras, rig.test_cameras, len(rig)) == (["cam0", "cam1"], ["cam2"], 2)
    np.testing.assert_array_equal(rig.times, [0.0, 1 / 24])
    assert_frames_equal(rig.cameras["cam1"][1], make_frames(2, seed=1)[1])
    assert read_rig(tmp_path / "rig" / "rig.json").path == tmp_path / "rig"


def test_rig_cameras_must_share_frame_count_and_times(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="has 3 frames") as exc:
        write_test_rig(tmp_path / "a", counts=(2, 2, 3))
    assert_names(exc.value, file="cam2/sequence.json", field="frames", frame=None)
    assert not (tmp_path / "a" / "rig.json").exists()
    with pytest.raises(InputError, match="share its time") as exc:
        write_test_rig(tmp_path / "b", shift=0.01)
    assert_names(exc.value, file="cam2/sequence.json", field="time", frame=0)


def test_read_rig_checks_synchronization(tmp_path: Path) -> None:
    root = write_test_rig(tmp_path / "rig")
    edit_json(root / "cam1", lambda m: m["frames"][1].__setitem__("time", 0.5))
    with pytest.raises(InputError) as exc:
        read_rig(root)
    assert_names(exc.value, file="cam1/sequence.json", field="time", frame=2)


@pytest.mark.parametrize("edit, field", [
    (lambda m: m.__setitem__("format", "rgbd-seq"), "format"),
    (lambda m: m.__setitem__("version", 3), "version"),
    (lambda m: m.__setitem__("test_cameras", ["cam9"]), "test_cameras"),
    (lambda m: m.__setitem__("cameras", ["cam0", "cam0"]), "cameras"),
    (lambda m: m.__setitem__("cameras", ["../cam0"]), "cameras"),
    (lambda m: m.__setitem__("cameras", []), "cameras"),
])
def test_bad_rig_json(tmp_path: Path, edit: Callable, field: str) -> None:
    root = write_test_rig(tmp_path / "rig")
    meta = json.loads((root / "rig.json").read_text())
    edit(meta)
    (root / "rig.json").write_text(json.dumps(meta))
    with pytest.raises(InputError) as exc:
        read_rig(root)
    assert_names(exc.value, file="rig.json", field=field, frame=None)


def test_write_rig_rejects_unknown_split(tmp_path: Path) -> None:
    with pytest.raises(InputError) as exc:
        write_rig(tmp_path / "r", {"cam0": make_frames(1)}, train=["cam0"], test=["cam1"], fps=24.0)
    assert exc.value.field == "test_cameras"
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("name", ["../../x.exr", "/etc/passwd", "frames/../../outside.exr", "link/0000.exr"])
def test_frame_files_cannot_leave_the_sequence_folder(tmp_path, name):
    """A frame ``file`` that escapes the folder (``..``, an absolute path, a symbolic link out of it) is refused
    before anything is read, and the error is the same whether the target exists or not (issue 20, D7)."""
    frames, _ = two_layer_sequence(2, width=16, height=12)
    root = write_sequence(tmp_path / "seq", frames, fps=30.0)
    (tmp_path / "x.exr").write_bytes((root / "frames").iterdir().__next__().read_bytes())
    (root / "link").symlink_to(tmp_path)
    meta = json.loads((root / "sequence.json").read_text())
    meta["frames"][1]["file"] = name
    (root / "sequence.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="inside the sequence folder") as info:
        read_sequence(root)
    assert info.value.frame == meta["frames"][1]["index"] and info.value.field == "file"


def test_frame_size_is_checked_from_the_header_before_pixels_are_decoded(tmp_path, monkeypatch):
    """Issue 20, D9: a small EXR whose data window claims a huge image was decoded whole (646 MB) before its
    size was compared with sequence.json."""
    import engine.io.rgbd as rgbd

    frames, _ = two_layer_sequence(2, width=16, height=12)
    root = write_sequence(tmp_path / "seq", frames, fps=30.0)
    big, _ = two_layer_sequence(2, width=32, height=24)
    write_sequence(tmp_path / "big", big, fps=30.0)
    victim = read_sequence(root).files[1]
    victim.write_bytes(read_sequence(tmp_path / "big").files[1].read_bytes())
    monkeypatch.setattr(rgbd, "read_exr", lambda path: pytest.fail("pixels decoded before the size check"))
    with pytest.raises(InputError, match="image is 32x24, sequence.json says 16x12") as info:
        read_sequence(root)[1]
    assert info.value.frame == 1 and info.value.field == "Z"


def test_truncated_exr_and_folders_are_named_plainly(tmp_path):
    """Issue 20, D11: a truncated EXR said "file has 0 parts"; a folder was reported as not existing."""
    frames, _ = two_layer_sequence(2, width=16, height=12)
    root = write_sequence(tmp_path / "seq", frames, fps=30.0)
    file = read_sequence(root).files[0]
    file.write_bytes(file.read_bytes()[:40])
    with pytest.raises(InputError, match="truncated"):
        read_sequence(root)[0]
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="folder without sequence.json"):
        read_sequence(tmp_path / "empty")
    with pytest.raises(InputError, match="is a file"):
        read_sequence(file)
    with pytest.raises(InputError, match="is a folder, not an EXR"):
        read_exr(tmp_path / "empty")
