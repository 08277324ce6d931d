"""``interleave eval`` with the renderer's motion vectors: frame n's vectors to the previous RENDERED frame."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from engine.core.errors import InputError
from engine.core.frames import rigid_inverse
from engine.eval.protocol import evaluate_sequence, history_motion_vectors, rendered_history
from engine.geometry.motion import rigid_motion_vectors
from engine.io.rgbd import read_sequence, write_sequence
from tests.synthetic import two_layer_sequence


def _sequence(tmp_path: Path, name="seq", vectors=True, objects=True):
    frames, objs = two_layer_sequence(9, width=64, height=48, camera_speed=0.03, object_speed=0.08)
    out = []
    for i, f in enumerate(frames):  # what an engine rendering every frame writes: vectors to frame i - 1
        j = max(i - 1, 0)
        motions = {o.id: o.world_from_object[j] @ rigid_inverse(o.world_from_object[i]) for o in objs}
        mv = rigid_motion_vectors(f.depth, f.camera, frames[j].camera, f.object_id, motions) if vectors else None
        out.append(dataclasses.replace(f, motion_vectors=mv))
    return read_sequence(write_sequence(tmp_path / name, out, fps=30.0, objects=objs if objects else None))


def test_vectors_to_frame_n_minus_k_are_recomputed_exactly_or_chained(tmp_path: Path) -> None:
    seq = _sequence(tmp_path)
    exact = history_motion_vectors(seq, 2, 6)
    chained = history_motion_vectors(_sequence(tmp_path, "plain", objects=False), 2, 6)
    known = np.isfinite(chained[..., 0])
    assert known.mean() > 0.7
    # exact wherever the intermediate frames see the point; where the square covered it there, it takes the
    # square's vector (an occlusion that chaining cannot see: why objects, where present, are used instead)
    close = np.all(np.abs(chained - exact) < 0.05, axis=-1)
    assert close[known].mean() > 0.95
    np.testing.assert_array_equal(history_motion_vectors(seq, 5, 6), seq[6].motion_vectors)  # k = 1: as stored


def test_mvec_is_scored_beside_the_others_and_auto_picks_it(tmp_path: Path) -> None:
    seq = _sequence(tmp_path)
    results = {r.method: r for r in evaluate_sequence(seq, ["reproject", "mvec", "auto", "oracle"], 2,
                                                        with_flip=False)}
    assert results["mvec"].psnr > results["reproject"].psnr + 1.0
    assert abs(results["mvec"].psnr - results["oracle"].psnr) < 0.3
    assert results["auto"].psnr == results["mvec"].psnr
    assert results["mvec"].epe_moving < 0.05


def test_mvec_on_a_sequence_without_vectors_or_objects_names_it(tmp_path: Path) -> None:
    seq = _sequence(tmp_path, vectors=False, objects=False)
    with pytest.raises(InputError) as err:
        evaluate_sequence(seq, ["mvec"], 2, with_flip=False)
    assert err.value.field.startswith("motion") and "seq" in str(err.value)
    assert evaluate_sequence(seq, ["auto"], 2, with_flip=False, max_groups=1)[0].method == "auto"  # flow2d here


def test_rendered_history_gives_frame_n_minus_2k_with_or_without_vectors(tmp_path: Path) -> None:
    seq = _sequence(tmp_path, vectors=False, objects=False)
    assert [f.index for f in rendered_history(seq, 4, 6, with_vectors=False, three=True)] == [2, 4, 6]
    assert [f.index for f in rendered_history(seq, 4, 6, with_vectors=False, three=False)] == [4, 6]
    assert [f.index for f in rendered_history(seq, 1, 3, with_vectors=False, three=True)] == [1, 3]  # no frame -1
    with_vectors = rendered_history(_sequence(tmp_path, "v"), 4, 6, with_vectors=True, three=True)
    assert [f.index for f in with_vectors] == [2, 4, 6] and with_vectors[1].motion_vectors is not None
