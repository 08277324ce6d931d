"""rgbd-seq version 2: the renderer's motion vectors (``motion.X/Y``) written, read and checked."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from engine.core.errors import InputError
from engine.geometry.motion import camera_motion_vectors
from engine.io.exr import read_exr, write_exr
from engine.io.rgbd import read_sequence, write_sequence
from tests.io.test_io import assert_names, make_frames, make_objects


def _with_vectors(frames, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for f in frames:
        v = rng.normal(0.0, 4.0, f.depth.shape + (2,)).astype(np.float32)
        v[0, :4] = np.nan  # no vector there
        out.append(dataclasses.replace(f, motion_vectors=v))
    return out


def test_vectors_round_trip_as_version_2_and_plain_sequences_stay_version_1(tmp_path: Path) -> None:
    frames = _with_vectors(make_frames())
    seq = read_sequence(write_sequence(tmp_path / "mv", frames, fps=24.0, objects=make_objects()))
    meta = json.loads((tmp_path / "mv" / "sequence.json").read_text())
    assert (meta["version"], meta["motion_vectors"]) == (2, {"camera": "included"})
    assert seq.has_channel("motion_vectors") and seq.has_channel("motion.X")
    for mine, back in zip(frames, seq):
        np.testing.assert_array_equal(mine.motion_vectors, back.motion_vectors)  # NaN where NaN
    write_sequence(tmp_path / "plain", make_frames(), fps=24.0)
    assert json.loads((tmp_path / "plain" / "sequence.json").read_text())["version"] == 1
    assert read_sequence(tmp_path / "plain")[0].motion_vectors is None


def test_object_only_vectors_get_the_camera_motion_added_on_load(tmp_path: Path) -> None:
    frames = _with_vectors(make_frames())
    folder = write_sequence(tmp_path / "mv", frames, fps=24.0)
    meta = json.loads((folder / "sequence.json").read_text())
    meta["motion_vectors"] = {"camera": "excluded"}
    (folder / "sequence.json").write_text(json.dumps(meta))
    seq = read_sequence(folder)
    assert seq.motion_camera == "excluded" and seq[0].motion_vectors is None  # no previous frame to point to
    frame = seq[2]
    expected = frames[2].motion_vectors + camera_motion_vectors(frames[2].depth, frames[2].camera, frames[1].camera)
    np.testing.assert_allclose(frame.motion_vectors, expected, rtol=1e-6, atol=1e-5)


@pytest.mark.parametrize("edit, problem", [
    (lambda ch: ch.pop("motion.Y"), "without"),
    (lambda ch: ch["motion.X"].__setitem__((2, 3), np.inf), "infinite"),
    (lambda ch: ch["motion.X"].__setitem__((2, 3), 1e9), "diagonals"),
])
def test_bad_vectors_name_the_file_frame_and_field(tmp_path: Path, edit, problem: str) -> None:
    folder = write_sequence(tmp_path / "mv", _with_vectors(make_frames()), fps=24.0)
    path = folder / "frames" / "000002.exr"
    channels = read_exr(path)
    edit(channels)
    write_exr(path, channels)
    with pytest.raises(InputError) as err:
        read_sequence(folder)[1]
    assert problem in str(err.value)
    assert_names(err.value, file="000002.exr", field=err.value.field, frame=2)
    assert err.value.field.startswith("motion")


def test_bad_motion_entry_and_low_resolution_vectors_are_refused(tmp_path: Path) -> None:
    folder = write_sequence(tmp_path / "mv", _with_vectors(make_frames()), fps=24.0)
    meta = json.loads((folder / "sequence.json").read_text())
    meta["motion_vectors"] = {"camera": "sometimes"}
    (folder / "sequence.json").write_text(json.dumps(meta))
    with pytest.raises(InputError) as err:
        read_sequence(folder)
    assert err.value.field == "motion_vectors.camera"
    small = [dataclasses.replace(f, motion_vectors=np.zeros((4, 6, 2), np.float32)) for f in make_frames()]
    with pytest.raises(InputError) as err:
        write_sequence(tmp_path / "small", small, fps=24.0)
    assert err.value.field == "motion_vectors" and err.value.frame == 0
