"""``tools.fast_regions`` (each method's error by object / revealed background) and ``tools.unseen_velocity``
(``mvec``'s motion on points frame n-k did not see)."""
import json

import numpy as np
import pytest

from engine.predict import Mvec
from tests.synthetic import two_layer_sequence, with_vectors
from tools import fast_regions, unseen_velocity


@pytest.fixture(scope="module")
def fast_sequence(tmp_path_factory):
    from engine.scenegen import SceneConfig, generate_sequence

    return generate_sequence(SceneConfig(seed=7005, width=96, height=64, num_frames=7, supersample=1, fps=10.0,
                                         object_speed=2.0), tmp_path_factory.mktemp("fast") / "seq", progress=False)


def test_regions_split_the_target_where_the_object_was_and_whether_frame_n_minus_k_saw_it():
    # a square 15 px a frame to the right, static camera: at frame 3 it has left pixels it covered at frame 2;
    # frame 0 saw the background at those right of its own square, not the ones it covered itself
    frames, _ = two_layer_sequence(5, width=128, height=64, camera_speed=0.0, object_speed=0.4)
    masks = fast_regions.region_masks(frames[0], frames[2], frames[3], near=4)
    assert (sum(m.astype(int) for m in masks.values()) == 1).all()  # disjoint and covering
    np.testing.assert_array_equal(masks["object"], frames[3].moving)
    revealed = frames[2].moving & ~frames[3].moving
    np.testing.assert_array_equal(masks["revealed_seen"] | masks["revealed_hidden"], revealed)
    assert masks["revealed_seen"].any() and masks["revealed_hidden"].any()
    np.testing.assert_array_equal(masks["revealed_hidden"], revealed & frames[0].moving)


def test_fast_regions_add_up_to_the_frame_error_and_true_motion_leaves_static_surfaces_alone(fast_sequence, tmp_path,
                                                                                           capsys):
    fast_regions.main([str(fast_sequence), "--k", "2", "--methods", "reproject,oracle", "--png-dir",
                       str(tmp_path / "png"), "--json", str(tmp_path / "r.json")])
    rows = {r["method"]: r for r in json.loads((tmp_path / "r.json").read_text())["rows"]}
    assert rows["oracle"]["error"]["far"] == pytest.approx(rows["reproject"]["error"]["far"], abs=1e-6)
    assert rows["oracle"]["error"]["object"] < rows["reproject"]["error"]["object"]
    assert rows["reproject"]["hole_share"]["object"] <= 1.0
    assert (tmp_path / "png" / "seq_k2.png").exists()
    assert "| oracle |" in capsys.readouterr().out


def test_previous_depths_find_the_points_frame_n_minus_k_saw_and_the_true_velocity_is_mvecs_there():
    frames, objects = two_layer_sequence(5, width=96, height=64, camera_speed=0.02, object_speed=0.1)
    older, newest = frames[0], with_vectors(frames, objects, 0, 2)
    state = Mvec().prepare([older, newest])
    moving = state.data.moving
    guess, seen, inside = unseen_velocity.previous_depths(newest, older, moving)
    assert seen.all() and inside.all()  # the square moved sideways at a constant depth: every point was seen
    np.testing.assert_allclose(guess, 3.0, rtol=1e-6)
    velocity, depth = unseen_velocity.true_velocity(newest, older, {o.id: o for o in objects}, moving)
    np.testing.assert_allclose(velocity.reshape(-1, 3)[moving], state.data.velocity.reshape(-1, 3)[moving], atol=1e-4)
    np.testing.assert_allclose(depth, 3.0, rtol=1e-6)


def test_a_point_that_entered_the_frame_was_not_seen():
    # the square enters from the left: at frame 0 it lay outside the image
    frames, objects = two_layer_sequence(5, width=96, height=64, camera_speed=0.0,
                                         object_path=lambda i: -3.0 + 1.4 * i)
    older, newest = frames[0], with_vectors(frames, objects, 0, 2)
    moving = Mvec().prepare([older, newest]).data.moving
    assert moving.size
    _, seen, inside = unseen_velocity.previous_depths(newest, older, moving)
    assert not inside.any() and not seen.any()


def test_unseen_velocity_prints_a_row_per_k(fast_sequence, tmp_path, capsys):
    unseen_velocity.main([str(fast_sequence), "--k", "2", "--json", str(tmp_path / "u.json")])
    rows = json.loads((tmp_path / "u.json").read_text())["rows"]
    assert [r["k"] for r in rows] == [2]
    epe = rows[0]["epe"]
    assert epe["true velocity"] <= epe["hold"]  # the true motion of the last interval beats none on this set
    assert 0.0 <= rows[0]["unseen_share"] <= 1.0
    assert "| seq | 2 |" in capsys.readouterr().out


def test_unseen_rules_keep_mvec_where_frame_n_minus_k_saw_everything_and_hold_what_it_did_not():
    from engine.predict import Reproject, Target

    frames, objects = two_layer_sequence(5, width=96, height=64, camera_speed=0.0,
                                         object_path=lambda i: -3.0 + 1.4 * i)
    history = [frames[0], with_vectors(frames, objects, 0, 2)]
    target = Target(frames[3].camera, frames[3].time, frames[3].index)
    shipped = Mvec().predict(history, target).color
    np.testing.assert_array_equal(unseen_velocity.UnseenRule("static").predict(history, target).color, shipped)
    held = Reproject().predict(history, target).color
    for rule in ("hold", "hold-outside", "unseen-regions", "region-median"):  # nothing of the square was seen
        np.testing.assert_array_equal(unseen_velocity.UnseenRule(rule).predict(history, target).color, held)
    seen_frames, objects = two_layer_sequence(5, width=96, height=64, camera_speed=0.02, object_speed=0.1)
    history = [seen_frames[0], with_vectors(seen_frames, objects, 0, 2)]
    target = Target(seen_frames[3].camera, seen_frames[3].time, seen_frames[3].index)
    for rule in unseen_velocity.RULES:  # every point seen: every rule is mvec's
        np.testing.assert_array_equal(unseen_velocity.UnseenRule(rule).predict(history, target).color,
                                      Mvec().predict(history, target).color)
    with pytest.raises(ValueError):
        unseen_velocity.UnseenRule("guess")
