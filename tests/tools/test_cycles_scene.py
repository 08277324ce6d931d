"""``tools.cycles_scene import`` on a real Cycles render (a committed 64x36, 3-frame fixture made with bpy 5.0.1):
the imported sequence's object ids, moving masks and per-frame object transforms agree with Cycles' own
Vector pass, so ``oracle`` and the moving-pixel scores mean on it what they mean on generated sequences."""
from pathlib import Path

import numpy as np
import pytest

from engine.core.frames import rigid_inverse
from engine.geometry.motion import rigid_motion_vectors
from engine.io.rgbd import read_sequence
from engine.predict.base import true_object_flow
from tools.cycles_scene import import_sequence

FIXTURE = Path(__file__).resolve().parents[1] / "io" / "data" / "cycles_scene"


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    return read_sequence(import_sequence(FIXTURE, tmp_path_factory.mktemp("cycles") / "seq"))


def _single_surface(ids: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood is one object (Cycles anti-aliases the Vector pass, not Depth or Index)."""
    key = np.where(np.isfinite(depth), ids, -1)
    pad = np.pad(key, 1, mode="edge")
    inner = np.isfinite(depth)
    for dy in range(3):
        for dx in range(3):
            inner &= pad[dy:dy + key.shape[0], dx:dx + key.shape[1]] == key
    return inner


def test_ids_masks_and_transforms_are_imported(sequence):
    assert len(sequence) == 3 and sequence[0].color.shape == (36, 64, 3)
    ids = {o.id for o in sequence.objects}
    assert ids == {1, 2} and all(o.moving and o.world_from_object.shape == (3, 4, 4) for o in sequence.objects)
    for i in range(3):
        frame = sequence[i]
        assert frame.object_id is not None and set(np.unique(frame.object_id)) <= {0, 1, 2}
        np.testing.assert_array_equal(frame.moving, np.isin(frame.object_id, [1, 2]))
    assert any(sequence[i].moving.any() for i in range(3))


def test_object_transforms_reproduce_the_cycles_vector_pass(sequence):
    """Exact rigid vectors from the imported depth, cameras, ids and object transforms against Cycles' Vector
    pass (imported as motion_vectors), on single-surface pixels of the moving objects and the background."""
    objects = {o.id: o for o in sequence.objects}
    checked = 0
    for n in (1, 2):
        frame, previous = sequence[n], sequence[n - 1]
        motions = {oid: o.world_from_object[n - 1] @ rigid_inverse(o.world_from_object[n])
                   for oid, o in objects.items()}
        exact = rigid_motion_vectors(frame.depth, frame.camera, previous.camera, frame.object_id, motions)
        inner = _single_surface(frame.object_id, frame.depth)
        error = np.linalg.norm(frame.motion_vectors[inner] - exact[inner], axis=-1)
        assert np.median(error) < 0.05 and np.percentile(error, 95) < 0.5, (n, np.median(error), error.max())
        moving = inner & frame.moving
        # the oracle's object flow: zero on the static scene, the objects' own motion on theirs
        truth = true_object_flow(frame, objects, n - 1)[..., :2]
        assert not truth[~frame.moving].any() and np.linalg.norm(truth[moving], axis=-1).min() > 0.0
        checked += int(moving.sum())
    assert checked > 50  # the objects do move across pixels the check covers
