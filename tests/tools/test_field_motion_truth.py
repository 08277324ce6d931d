"""``tools.field_motion_truth`` on the programmed translating field of ``tools.programmed_field``, whose motion is
known in closed form (``tests/fields/test_field_motion.py``): a capture whose true object flow is that motion
and one whose objects stand still."""
from __future__ import annotations

import json

import numpy as np
import pytest

from engine.core.frames import Frame
from engine.core.errors import InputError
from engine.fields.dynamic import load_dynamic_field, normalize_time, render_dynamic_field
from engine.fields.render import camera_rays_np, contract_np
from engine.geometry.motion import rigid_motion_vectors
from engine.io.rgbd import write_sequence
from tests.fields.test_field_motion import camera, depth_with_sky
from tools.field_motion_truth import check, flow_units, main
from tools.programmed_field import flow_x, write_export

SIZE, TIMES = 24, [0.0, 0.25, 0.5, 0.75, 1.0]


def capture(path, export, *, still: bool = False, object_flow: bool = True, rendered: bool = False):
    """A static camera's frames of the plane of ``depth_with_sky`` (``rendered``: of the field's own rendered
    depth) at TIMES: object id 1 inside the field's cube, the true object flow to the next frame the field's
    translation (zero with ``still``)."""
    assets = load_dynamic_field(export)
    cam = camera(10.0)
    origin, dirs = camera_rays_np(cam.intrinsics, cam.world_to_camera, SIZE, SIZE)
    frames = []
    for n, t in enumerate(TIMES):
        depth = (render_dynamic_field(assets, cam.intrinsics, cam.world_to_camera, SIZE, SIZE, t)["depth"]
                 if rendered else depth_with_sky())
        finite = np.isfinite(depth).reshape(-1)
        points = (origin + np.where(finite, depth.reshape(-1), 0.0)[:, None] * dirs).astype(np.float32)
        inside = (finite & (np.abs(contract_np(assets.scene, points, 0.0)) <= 1.0).all(-1)).reshape(SIZE, SIZE)
        flow = np.zeros((SIZE, SIZE, 2), np.float32)
        if n + 1 < len(TIMES) and not still:
            tau, tau_next = (normalize_time(s, assets.time_range) for s in (t, TIMES[n + 1]))
            motion = np.eye(4)  # c -> c + flow(tau) - flow(tau_next): the box half-size is 1
            motion[0, 3] = flow_x(assets.max_flow, 0.0, tau) - flow_x(assets.max_flow, 0.0, tau_next)
            flow = np.nan_to_num(rigid_motion_vectors(depth, cam, cam, inside.astype(np.int32), {1: motion}))
        frames.append(Frame(index=n, time=t, color=np.full((SIZE, SIZE, 3), 0.5, np.float32), depth=depth,
                            camera=cam, object_id=inside.astype(np.int32), object_flow=flow if object_flow else None))
    write_sequence(path, frames, fps=4.0)
    return path


def test_the_fields_own_motion_scores_zero_error_and_still_objects_score_its_motion(tmp_path):
    export = write_export(tmp_path / "export")
    moving = check(export, capture(tmp_path / "moving", export))
    still = check(export, capture(tmp_path / "still", export, still=True))
    assert moving["pairs"] == still["pairs"] == 4 and 0.1 < moving["object pixel share"] < 0.9
    truth = moving["objects: true motion, px"]
    assert truth > 0.5  # the case moves the objects by a visible amount
    assert moving["objects: EPE of the field's motion, px"] < 0.01 * truth
    assert moving["objects: EPE of zero motion, px"] == truth
    assert moving["objects: share where the field halves zero motion's error"] > 0.95
    # the field moves what the still capture says stands still: its error is its motion, zero motion's is 0
    assert still["objects: EPE of the field's motion, px"] == pytest.approx(truth, rel=0.01)
    assert still["objects: share where the field halves zero motion's error"] == 0.0
    for figures in (moving, still):  # outside the cube the field moves nothing
        assert figures["background: EPE of the field's motion, px"] == 0.0
        assert figures["background: share the field moves > 0.25 px"] == 0.0
    # the field's rendered depth: on a capture of the field's own box the two depths give the same figures
    box = capture(tmp_path / "box", export, rendered=True)
    truth_depth, field_depth = check(export, box), check(export, box, "field")
    assert truth_depth["object pixel share"] > 0.05 and truth_depth["objects: true motion, px"] > 0.5
    assert field_depth["objects: EPE of the field's motion, px"] < 0.02 * truth_depth["objects: true motion, px"]
    assert field_depth == pytest.approx(truth_depth, abs=0.02)
    with pytest.raises(InputError, match="depth"):
        check(export, box, "rendered")
    out = tmp_path / "truth.json"
    assert main([str(export), str(tmp_path / "moving"), "--json", str(out)]) == 0
    assert json.loads(out.read_text())["objects: EPE of the field's motion, px"] == moving[
        "objects: EPE of the field's motion, px"]


def test_a_capture_without_object_flow_or_outside_the_trained_times_is_one_line_and_exit_2(tmp_path, capsys):
    export = write_export(tmp_path / "export")
    capture(tmp_path / "bare", export, object_flow=False)
    assert main([str(export), str(tmp_path / "bare")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "frame 0" in err and "object_flow" in err
    late = tmp_path / "late"
    capture(late, export)
    meta = json.loads((late / "sequence.json").read_text())
    for frame in meta["frames"]:
        frame["time"] += 10.0
    (late / "sequence.json").write_text(json.dumps(meta))
    assert main([str(export), str(late)]) == 2
    assert "trained times" in capsys.readouterr().err
    assert main([str(tmp_path / "nothing"), str(late)]) == 2


def test_flow_units_counts_the_hidden_units_no_input_switches_on(tmp_path):
    """The programmed flow MLP drives hidden unit 0 with a positive feature and zeroes the other 15 (ReLU input 0
    everywhere: never active); a bias that pushes unit 0 below zero for every input kills it too."""
    export = write_export(tmp_path / "export")
    assets = load_dynamic_field(export)
    assert flow_units(assets) == (16, 15)
    assert check(export, capture(tmp_path / "moving", export))["flow MLP: hidden units never active"] == 15
    w, b = assets.flow_layers[0]
    b[0] = -1e3
    assert flow_units(assets) == (16, 16)
    b[0], b[1] = 0.0, 1e-3  # unit 1 switched on by its bias alone, at every sample
    assert flow_units(assets, samples=16) == (16, 14)
