"""Tests of engine/runtime/session.py: the game-engine integration API.

Per engine, the engine's own pipeline (view and projection matrices, clip -> NDC -> window pixel with row 0
at the top, window depth; the reference math of tests/conventions/test_conventions.py) places a known point; the
session, fed the same matrices and depth buffer, must put it on the same pixel: exactly for the converted
camera, and within a tenth of a pixel end to end (submit a textured wall, predict another view, read back
which source pixel landed there). Then the hard cases of issue 7: camera cuts, time going backwards and
frames out of order, resolution changes, NaN / negative values, reversed-Z zeros, two threads, zero-copy.
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import pytest

from engine.conventions import UNITY_FLIP, UNREAL_FLIP, encode_depth_buffer
from engine.core.errors import InputError
from engine.core.frames import rigid_inverse
from engine.predict.registry import METHODS
from engine.runtime.session import NotReadyError, Session, SessionConfig
from tests.conventions.test_conventions import (UE_VIEW_SWAP, clip_to_window, gl_frustum, gl_look_at, gl_perspective,
                                                homogeneous, reversed_zero_to_one, rot_x, rot_y, rot_z,
                                                ue_reversed_z_perspective, ue_transform_fmatrix)

W, H = 64, 48
PIXEL_A = (30.5, 22.5)  # the centre of pixel (column 30, row 22) in the submitted view
EXACT_TOL = 1e-6        # pixels, converted camera against the engine's pipeline
END_TO_END_TOL = 0.1    # pixels, through submit -> forward splat -> hole fill -> predict


# --------------------------------------------------------------------------------------------
# One rig per engine: two cameras in the engine's own form and the engine's projection math
# --------------------------------------------------------------------------------------------

@dataclass
class Rig:
    """Two cameras A (submitted) and B (predicted) of one engine, and that engine's pipeline."""

    config: dict
    view_a: np.ndarray
    proj_a: object
    view_b: np.ndarray
    proj_b: object
    project: Callable          # (view, proj, world point) -> (u, v, window depth), engine math
    unproject: Callable        # (view, proj, u, v, depth in engine units) -> world point, engine math
    to_output: Callable        # engine world point -> Interleave's output world (metres)
    depth: float               # planar depth of the wall in A, engine units
    extra: dict = field(default_factory=dict)


def ndc(u, v):
    return 2.0 * u / W - 1.0, 1.0 - 2.0 * v / H


def gl_family_rig(config, view_a, view_b, proj, depth_proj, clip_range, depth):
    """OpenGL, Unity (worldToCameraMatrix) and Godot (view matrix): column vectors, clip = P @ V @ x."""

    def project(view, p, point):
        u, v, _ = clip_to_window(p @ view @ np.append(point, 1.0), W, H, clip_range="minus_one_to_one")
        _, _, d = clip_to_window(depth_proj @ view @ np.append(point, 1.0), W, H, clip_range=clip_range)
        return u, v, d

    def unproject(view, p, u, v, z):
        nx, ny = ndc(u, v)
        clip = np.array([nx * z, ny * z, -p[2, 2] * z + p[2, 3], z])
        return (np.linalg.inv(p @ view) @ clip)[:3]

    return Rig(config, view_a, proj, view_b, proj, project, unproject, lambda x: x, depth)


def opengl_rig():
    up = (0.1, 1.0, 0.0)
    view_a = gl_look_at((2.0, 1.5, 6.0), (0.3, 0.2, -1.0), up)
    view_b = gl_look_at((2.4, 1.3, 6.2), (0.35, 0.2, -1.0), up)
    proj = gl_frustum(-0.06, 0.1, -0.04, 0.05, 0.1, 100.0)  # off-centre, non-square pixels at 64x48
    config = dict(engine="opengl", depth_convention="opengl", near=0.1, far=100.0)
    return gl_family_rig(config, view_a, view_b, proj, proj, "minus_one_to_one", 4.0)


def unity_view(position, euler):
    ex, ey, ez = euler
    local_to_world = homogeneous(rot_y(ey) @ rot_x(ex) @ rot_z(ez), position)  # Unity: z, then x, then y
    return np.diag([1.0, 1.0, -1.0, 1.0]) @ np.linalg.inv(local_to_world)   # camera.worldToCameraMatrix


def unity_rig():
    proj = gl_perspective(60.0, W / H, 0.3, 1000.0)  # camera.projectionMatrix
    config = dict(engine="unity", depth_convention="reversed", near=0.3, far=1000.0)
    rig = gl_family_rig(config, unity_view([1.0, 2.0, -3.0], (10.0, 30.0, 5.0)),
                        unity_view([1.5, 2.1, -3.1], (11.0, 30.0, 5.0)), proj, reversed_zero_to_one(proj),
                        "zero_to_one", 5.0)
    rig.to_output = lambda x: (UNITY_FLIP @ np.append(x, 1.0))[:3]
    return rig


def godot_view(origin, euler):
    ex, ey, ez = euler
    camera_to_world = homogeneous(rot_y(ey) @ rot_x(ex) @ rot_z(ez), origin)  # Basis.from_euler, YXZ order
    return np.linalg.inv(camera_to_world)  # get_camera_transform().affine_inverse()


def godot_rig():
    proj = gl_perspective(75.0, W / H, 0.05, 4000.0)  # get_camera_projection(), KEEP_HEIGHT
    config = dict(engine="godot", depth_convention="reversed", near=0.05, far=4000.0)  # Godot 4.3+
    return gl_family_rig(config, godot_view([3.0, 1.7, 4.0], (-15.0, 40.0, 8.0)),
                         godot_view([2.8, 1.75, 4.1], (-14.0, 42.0, 8.0)), proj, reversed_zero_to_one(proj),
                         "zero_to_one", 4.0)


def unreal_rig():
    near_cm, hfov = 10.0, 90.0
    proj = ue_reversed_z_perspective(math.radians(hfov) / 2, W, H, near_cm)  # row vectors, as Unreal stores it
    cams = {"a": (np.array([120.0, -340.0, 175.0]), (-12.0, 35.0, 7.0)),
            "b": (np.array([97.0, -307.0, 170.0]), (-11.0, 37.0, 7.0))}

    transforms = {name: ue_transform_fmatrix(*c) for name, c in cams.items()}  # the cameras' FMatrix

    def view_matrix(transform):  # FViewMatrices: Translation(-loc) * FInverseRotationMatrix * axis swap
        return np.linalg.inv(transform) @ UE_VIEW_SWAP

    def project(view, p, point):
        clip = np.append(point, 1.0) @ view_matrix(view) @ p
        return clip_to_window(clip, W, H, clip_range="zero_to_one")

    def unproject(view, p, u, v, w):
        nx, ny = ndc(u, v)
        clip = np.array([nx * w, ny * w, near_cm, w])
        return (clip @ np.linalg.inv(view_matrix(view) @ p))[:3]

    config = dict(engine="unreal", depth_convention="reversed_infinite", near=near_cm, far=math.inf)
    rig = Rig(config, transforms["a"], proj, transforms["b"], proj, project, unproject,
              lambda x: (UNREAL_FLIP @ np.append(0.01 * x, 1.0))[:3], 400.0)
    rig.extra = dict(cams=cams, hfov=hfov)
    return rig


def opencv_rig():
    k = np.array([[50.0, 0.0, 31.0], [0.0, 52.0, 25.0], [0.0, 0.0, 1.0]])
    view_a = homogeneous(rot_x(5.0) @ rot_y(-8.0), [0.1, -0.2, 0.3])
    view_b = homogeneous(rot_x(6.0) @ rot_y(-6.5), [0.25, -0.15, 0.35])

    def project(view, kk, point):
        cam = view[:3, :3] @ point + view[:3, 3]
        uvw = kk @ cam
        return uvw[0] / uvw[2], uvw[1] / uvw[2], cam[2]

    def unproject(view, kk, u, v, z):
        cam = z * np.linalg.solve(kk, [u, v, 1.0])
        return view[:3, :3].T @ (cam - view[:3, 3])

    return Rig(dict(engine="opencv", depth_convention="linear"), view_a, k, view_b, k, project, unproject,
               lambda x: x, 3.0)


RIGS = {"opengl": opengl_rig, "unity": unity_rig, "godot": godot_rig, "unreal": unreal_rig, "opencv": opencv_rig}
#: The point's pixel in view B and its depth-buffer value in view A, as printed in docs/server.md.
DOC_EXAMPLES = {"opengl": ((28.3918, 21.6331), 0.975976), "unity": ((26.3040, 22.4539), 0.059718),
                "godot": ((33.0929, 23.9003), 0.012488), "unreal": ((26.1950, 23.2205), 0.025),
                "opencv": ((34.1170, 22.5879), 3.0)}


def known_point(rig):
    """The wall point seen at PIXEL_A's centre in view A, its window depth there and its pixel in view B."""
    point = rig.unproject(rig.view_a, rig.proj_a, *PIXEL_A, rig.depth)
    u_a, v_a, d_a = rig.project(rig.view_a, rig.proj_a, point)
    assert (u_a, v_a) == pytest.approx(PIXEL_A, abs=1e-9)  # the engine math round-trips
    u_b, v_b, _ = rig.project(rig.view_b, rig.proj_b, point)
    return point, d_a, (u_b, v_b)


def ramp_image():
    """Colour that encodes the pixel-centre coordinates: R = (u + 0.5) / W, G = (v + 0.5) / H."""
    u = (np.arange(W, dtype=np.float32) + 0.5) / W
    v = (np.arange(H, dtype=np.float32) + 0.5) / H
    return np.stack([np.broadcast_to(u, (H, W)), np.broadcast_to(v[:, None], (H, W)),
                     np.full((H, W), 0.5, np.float32)], axis=-1)


def bilinear(image, x, y):
    """Sample an (H, W, C) image at continuous coordinates (x, y), pixel centres at +0.5."""
    x0, y0 = math.floor(x - 0.5), math.floor(y - 0.5)
    fx, fy = x - 0.5 - x0, y - 0.5 - y0
    patch = image[y0:y0 + 2, x0:x0 + 2].astype(np.float64)
    return ((1 - fy) * ((1 - fx) * patch[0, 0] + fx * patch[0, 1]) + fy * ((1 - fx) * patch[1, 0] + fx * patch[1, 1]))


@pytest.mark.parametrize("engine", list(RIGS))
def test_known_point_lands_on_the_engines_pixel(engine):
    rig = RIGS[engine]()
    point, d_a, (u_b, v_b) = known_point(rig)
    (doc_u, doc_v), doc_d = DOC_EXAMPLES[engine]
    assert (u_b, v_b, d_a) == pytest.approx((doc_u, doc_v, doc_d), abs=1e-4, rel=1e-5)
    session = Session(SessionConfig(width=W, height=H, method="reproject", **rig.config))

    # The converted camera projects the point exactly where the engine does.
    for view, proj, expected in ((rig.view_a, rig.proj_a, PIXEL_A), (rig.view_b, rig.proj_b, (u_b, v_b))):
        camera = session.camera(view, proj)
        cam = camera.world_to_camera[:3, :3] @ rig.to_output(point) + camera.world_to_camera[:3, 3]
        uvw = camera.intrinsics @ cam
        assert uvw[:2] / uvw[2] == pytest.approx(expected, abs=EXACT_TOL)

    # End to end: a wall at the point's depth (the same window depth everywhere in A), textured with a
    # coordinate ramp; in the prediction for B the point's pixel shows the colour of A's pixel PIXEL_A.
    buffer = np.full((H, W), d_a, dtype=np.float32)
    session.submit(ramp_image(), buffer, rig.view_a, rig.proj_a, 0.0)
    out = session.predict(rig.view_b, rig.proj_b, 1.0 / 60.0)
    assert out.method == "reproject" and out.fallback is None
    assert math.hypot(u_b - PIXEL_A[0], v_b - PIXEL_A[1]) > 2.0  # the views differ by more than two pixels
    r, g, _ = bilinear(out.color, u_b, v_b)
    assert (r * W, g * H) == pytest.approx(PIXEL_A, abs=END_TO_END_TOL)


def test_unreal_pose_and_fov_forms_agree():
    rig = unreal_rig()
    (location, rotator), hfov = rig.extra["cams"]["a"], rig.extra["hfov"]
    session = Session(SessionConfig(width=W, height=H, **rig.config))
    reference = session.camera(rig.view_a, rig.proj_a)
    for view, proj in ((np.concatenate([location, rotator]), hfov), (rig.view_a, hfov)):
        camera = session.camera(view, proj)
        np.testing.assert_allclose(camera.world_to_camera, reference.world_to_camera, atol=1e-12)
        np.testing.assert_allclose(camera.intrinsics, reference.intrinsics, atol=1e-9)
    off_centre = rig.proj_a.copy()
    off_centre[2, 0] = 0.1
    with pytest.raises(InputError, match="off-centre"):
        session.camera(rig.view_a, off_centre)


# --------------------------------------------------------------------------------------------
# A small OpenCV scene for the hard cases
# --------------------------------------------------------------------------------------------

K = np.array([[50.0, 0.0, W / 2], [0.0, 50.0, H / 2], [0.0, 0.0, 1.0]])


def pose(x=0.0, y=0.0, z=0.0, yaw_deg=0.0):
    """world_to_camera of a camera at (x, y, z) turned by yaw about the y axis (OpenCV axes)."""
    rotation = rot_y(yaw_deg)
    return homogeneous(rotation, -rotation @ np.array([x, y, z]))


def frame_arrays(seed=0, depth=3.0, size=(H, W)):
    rng = np.random.default_rng(seed)
    color = rng.uniform(0.05, 0.95, size + (3,)).astype(np.float32)
    return color, np.full(size, depth, np.float32)


def make_session(**overrides):
    return Session(SessionConfig(**{"engine": "opencv", "width": W, "height": H, **overrides}))


def test_camera_cut_on_submit_resets_history_and_never_smears():
    session = make_session(method="flow2d")
    color0, depth = frame_arrays(0)
    color1, _ = frame_arrays(1)
    assert session.submit(color0, depth, pose(), K, 0.0).reset is None
    small = session.submit(color1, depth, pose(x=0.05), K, 1 / 30)
    assert small.reset is None and small.history == 2
    assert session.predict(pose(x=0.06), K, 1 / 20).fallback is None

    jump = session.submit(color0, depth, pose(x=100.0), K, 2 / 30)  # teleport: 100 m against a 3 m scene
    assert jump.reset == "camera_cut" and jump.history == 1
    out = session.predict(pose(x=100.01), K, 2 / 30 + 1 / 60)
    assert out.method == "reproject" and out.fallback == "history" and out.frame == jump.frame
    turn = session.submit(color1, depth, pose(x=100.0, yaw_deg=90.0), K, 3 / 30)
    assert turn.reset == "camera_cut"
    assert session.stats["resets"]["camera_cut"] == 2


def test_camera_cut_on_predict_repeats_the_newest_frame():
    session = make_session(method="reproject", cut_rotation_deg=30.0)
    color, depth = frame_arrays(3)
    session.submit(color, depth, pose(), K, 0.0)
    for target in (pose(x=5.0), pose(yaw_deg=60.0)):
        out = session.predict(target, K, 1 / 60)
        assert out.method == "repeat" and out.fallback == "camera_cut"
        np.testing.assert_array_equal(out.color, color)  # the newest frame, not a smear
        assert not out.holes.any()
    assert session.predict(pose(yaw_deg=20.0), K, 1 / 60).fallback is None  # under the threshold


def test_time_going_backwards_and_out_of_order_frames_reset_history():
    session = make_session(method="flow2d")
    depth = frame_arrays()[1]
    arrivals = [(0, 0.0), (2, 2 / 30), (1, 1 / 30), (3, 3 / 30)]  # frame 1 arrives late
    results = [session.submit(frame_arrays(i)[0], depth, pose(x=0.01 * i), K, t, frame=i) for i, t in arrivals]
    assert [r.reset for r in results] == [None, None, "time_backwards", None]
    assert [r.history for r in results] == [1, 2, 1, 2]
    out = session.predict(pose(x=0.035), K, 3.5 / 30)
    assert out.fallback is None and np.all(np.isfinite(out.color))
    assert session.submit(frame_arrays(4)[0], depth, pose(), K, 3 / 30).reset == "time_backwards"  # same time
    # A game rewinding to t = 0: the history starts again from the rewound frame.
    rewind = session.submit(frame_arrays(5)[0], depth, pose(), K, 0.0)
    assert rewind.reset == "time_backwards" and rewind.history == 1
    assert session.predict(pose(), K, 1 / 60).fallback == "history"


def test_resolution_change_is_an_error_until_reset_with_the_new_size():
    session = make_session()
    color, depth = frame_arrays()
    session.submit(color, depth, pose(), K, 0.0)
    small_color, small_depth = frame_arrays(size=(24, 32))
    with pytest.raises(InputError, match=r"frame 7.*\(H, W\) = \(48, 64\).*reset\(width"):
        session.submit(small_color, small_depth, pose(), K, 0.1, frame=7)
    assert session.predict(pose(), K, 0.05).color.shape == (H, W, 3)  # history intact

    session.reset(width=32, height=24)
    with pytest.raises(NotReadyError):
        session.predict(pose(), K, 0.1)
    k_small = K * np.array([[0.5], [0.5], [1.0]])
    session.submit(small_color, small_depth, pose(), k_small, 0.2)
    out = session.predict(pose(x=0.01), k_small, 0.25)
    assert out.color.shape == (24, 32, 3) and out.holes.shape == (24, 32)


def test_predict_before_submit_is_not_ready():
    with pytest.raises(NotReadyError, match="before any frame"):
        make_session().predict(pose(), K, 0.0)


@pytest.mark.parametrize("what, change, match", [
    ("nan colour", lambda c, d: c.__setitem__((3, 4, 1), np.nan), r"frame 12, field 'color': has 1 non-finite"),
    ("inf colour", lambda c, d: c.__setitem__((0, 0, 0), np.inf), r"frame 12, field 'color': has 1 non-finite"),
    ("negative colour", lambda c, d: c.__setitem__((0, 0, 0), -0.5), r"frame 12, field 'color': has 1 negative"),
    ("negative depth", lambda c, d: d.__setitem__((5, 5), -1.0), r"frame 12, field 'depth': has 1 zero or negative"),
    ("nan depth", lambda c, d: d.__setitem__((5, 5), np.nan), r"frame 12, field 'depth': has 1 NaN"),
])
def test_bad_values_are_rejected_naming_the_frame(what, change, match):
    session = make_session()
    color, depth = frame_arrays()
    session.submit(color, depth, pose(), K, 0.0)
    bad_color, bad_depth = frame_arrays(1)
    change(bad_color, bad_depth)
    with pytest.raises(InputError, match=match) as info:
        session.submit(bad_color, bad_depth, pose(), K, 0.25, frame=12)
    assert "time 0.25" in str(info.value)
    assert session.stats["submitted"] == 1  # rejected frames leave the history as it was
    np.testing.assert_array_equal(session.predict(pose(), K, 0.3).color.shape, (H, W, 3))


#: Every method a session can run (oracle needs the true object motion), and auto.
SESSION_METHODS = [m for m in METHODS if m != "oracle"] + ["auto"]


def static_history(session, colors, depth):
    """Submit ``colors`` from a static camera at 30 fps (mvec with zero vectors: nothing moves)."""
    vectors = np.zeros((H, W, 2), np.float32) if session.config.method == "mvec" else None
    for i, color in enumerate(colors):
        session.submit(color, depth, pose(), K, i / 30, motion_vectors=vectors)


@pytest.mark.parametrize("method", SESSION_METHODS)
def test_srgb_colour_is_checked_decoded_and_a_refused_frame_leaves_the_history(method):
    """Issue 41, item 3: sRGB-float colour is checked as the engine uses it, decoded to linear float32, where a
    finite 2e16 becomes inf: a 10x10 patch of it is refused in one line naming the field, for every method;
    the history keeps its frames, so the next prediction is the one before, and finite."""
    session = make_session(method=method, color_in="srgb")
    depth = frame_arrays()[1]
    static_history(session, [frame_arrays(i)[0] for i in range(3)], depth)
    before = session.predict(pose(x=0.02), K, 2.5 / 30)
    bad = frame_arrays(3)[0]
    bad[10:20, 20:30] = 2e16
    with pytest.raises(InputError, match=r"frame 7, field 'color': has 300 values that are not finite once decoded "
                                         r"from sRGB \(largest 2e\+16") as info:
        session.submit(bad, depth, pose(), K, 3 / 30, frame=7)
    assert "\n" not in str(info.value) and session.stats["submitted"] == 3
    after = session.predict(pose(x=0.02), K, 2.5 / 30)
    np.testing.assert_array_equal(after.color, before.color)
    assert np.isfinite(after.color).all()


@pytest.mark.parametrize("color_out", ["linear", "srgb"])
@pytest.mark.parametrize("method", SESSION_METHODS)
def test_the_largest_finite_linear_colour_predicts_finite_frames(method, color_out):
    """Linear colour up to float32's largest finite value is used as it comes: every method's predictions of
    a moving bright patch stay finite, in linear and in sRGB (clipped to 1) out."""
    session = make_session(method=method, color_out=color_out)
    depth = frame_arrays()[1]
    colors = [frame_arrays(i)[0] for i in range(3)]
    for i, color in enumerate(colors):
        color[10:20, 10 + 2 * i:20 + 2 * i] = np.finfo(np.float32).max
    static_history(session, colors, depth)
    for time in (2.5 / 30, 3 / 30):
        out = session.predict(pose(x=0.02), K, time)
        assert np.isfinite(out.color).all()
        assert out.color.max() > 1e38 if color_out == "linear" else out.color.max() == 1.0  # sRGB out is clipped
        assert np.isfinite(session._loop.prepared.frames[-1].color).all()


def test_a_pose_that_overflows_once_scaled_to_metres_is_refused():
    """Issue 41, item 4: the opencv engine's translation is checked after scaling by meters_per_unit, as the
    other engines' are: 1e10 x 1e300 is inf, refused at submit and predict naming the view; a finite depth
    that the scale makes inf is refused too (it would have become sky)."""
    session = make_session(meters_per_unit=1e300)
    color = frame_arrays()[0]
    sky = np.full((H, W), np.inf, np.float32)
    far = pose()
    far[0, 3] = 1e10
    match = r"field 'view': translation \(1e\+10, 0, 0\) times meters_per_unit 1e\+300 is not finite"
    with pytest.raises(InputError, match=match):
        session.submit(color, sky, far, K, 0.0)
    assert session.stats["submitted"] == 0
    session.submit(color, sky, pose(), K, 0.0)
    with pytest.raises(InputError, match=match):
        session.predict(far, K, 1 / 60)
    near = sky.copy()
    near[0, :2] = 3.0
    with pytest.raises(InputError, match=r"field 'depth': has 2 values that are not finite once scaled by "
                                         r"meters_per_unit 1e\+300"):
        session.submit(color, near, pose(), K, 1 / 30)
    assert session.stats["submitted"] == 1


def test_errors_name_the_session_counter_by_default_and_catch_bad_poses():
    session = make_session()
    color, depth = frame_arrays()
    session.submit(color, depth, pose(), K, 0.0)
    color[0, 0, 0] = np.nan
    with pytest.raises(InputError, match=r"^frame 1, field 'color'"):
        session.submit(color, depth, pose(), K, 0.1)
    with pytest.raises(InputError, match="frame 1, field 'view'.*not rigid"):
        session.submit(frame_arrays()[0], depth, np.diag([2.0, 2.0, 2.0, 1.0]), K, 0.1)
    with pytest.raises(InputError, match="field 'time'"):
        session.submit(frame_arrays()[0], depth, pose(), K, float("nan"))
    with pytest.raises(InputError, match="frame 5, field 'view'.*non-finite"):
        session.predict(np.full((4, 4), np.nan), K, 0.1, frame=5)
    with pytest.raises(InputError, match="UNORM"):
        make_session(depth_convention="reversed", near=0.1, far=100.0).submit(
            frame_arrays()[0], np.zeros((H, W), np.uint16), pose(), K, 0.0)


@pytest.mark.parametrize("engine", ["opencv", "unreal"])
@pytest.mark.parametrize("value", ["p", None, {"a": 1}, [[1.0, 2.0], [3.0]], b"xx"])
def test_non_numeric_poses_are_input_errors(engine, value):
    from engine.runtime.session import engine_camera

    config = SessionConfig(engine=engine, width=W, height=H)
    good_view, good_projection = (np.zeros(6), 90.0) if engine == "unreal" else (pose(), K)
    for view, projection, field in ((value, good_projection, "view"), (good_view, value, "projection")):
        with pytest.raises(InputError) as err:
            engine_camera(config, view, projection)
        assert err.value.field == ("pose" if engine == "unreal" and view is None else field)  # unreal: no pose given


@pytest.mark.parametrize("method", ["flow2d", "mvec"])
def test_a_time_beyond_the_extrapolation_limit_is_refused_not_answered(method):
    """A target MAX_EXTRAPOLATION steps of the rendered frames from the newest (or a time so far that the motion
    would overflow) is an InputError naming the frame and the time; at the limit and for reproject it is served."""
    from engine.predict.base import MAX_EXTRAPOLATION

    session = make_session(method=method)
    depth = frame_arrays()[1]
    vectors = np.full((H, W, 2), 0.5, np.float32) if method == "mvec" else None
    for i in range(3):
        session.submit(frame_arrays(i)[0], depth, pose(x=0.02 * i), K, 0.1 * i, motion_vectors=vectors)
    step = 0.1  # frames 1 -> 2
    assert session.predict(pose(), K, 0.2 + MAX_EXTRAPOLATION * step * 0.999).color.shape == (H, W, 3)
    for time in (0.2 + MAX_EXTRAPOLATION * step * 1.01, 0.2 - MAX_EXTRAPOLATION * step * 1.01, 1e300, -1e300):
        with pytest.raises(InputError, match=r"^frame 7, field 'time':.* steps") as err:
            session.predict(pose(), K, time, frame=7)
        assert "predicted frame at time" in str(err.value)
    plain = make_session(method="reproject")
    plain.submit(*frame_arrays(), pose(), K, 0.0)
    assert plain.predict(pose(), K, 1e300).color.shape == (H, W, 3)  # no motion to extrapolate


def test_reversed_z_zero_is_sky_and_nan_buffer_is_rejected():
    session = make_session(depth_convention="reversed", near=0.1, far=100.0)
    color, planar = frame_arrays(depth=4.0)
    buffer = encode_depth_buffer(planar, 0.1, 100.0, convention="reversed").astype(np.float32)
    buffer[:, : W // 2] = 0.0  # left half: the reversed-Z clear value, i.e. no surface
    session.submit(color, buffer, pose(), K, 0.0)
    out = session.predict(pose(yaw_deg=2.0), K, 1 / 60)
    assert np.all(np.isfinite(out.color)) and out.fallback is None
    sky_only = make_session(depth_convention="reversed_infinite", near=0.1, far=math.inf)
    sky_only.submit(color, np.zeros((H, W), np.float32), pose(), K, 0.0)  # all sky: rotation-only warp
    assert np.all(np.isfinite(sky_only.predict(pose(x=1.0, yaw_deg=3.0), K, 1 / 60).color))
    buffer[1, 1] = np.nan
    with pytest.raises(InputError, match=r"frame 1, field 'depth': has 1 NaN"):
        session.submit(color, buffer, pose(), K, 0.1)


def test_two_threads_submit_and_predict_concurrently():
    session = make_session(method="reproject")
    color, depth = frame_arrays()
    session.submit(color, depth, pose(), K, 0.0)
    errors, seen = [], []

    def submitter():
        try:
            for i in range(1, 41):
                session.submit(frame_arrays(i)[0], depth, pose(x=0.01 * i), K, i / 30)
        except Exception as exc:  # noqa: BLE001
            errors.append(exc)

    def predictor():
        try:
            for i in range(80):
                out = session.predict(pose(x=0.005 * i), K, i / 60)
                assert out.color.shape == (H, W, 3) and np.all(np.isfinite(out.color))
                seen.append(out.frame)
        except Exception as exc:  # noqa: BLE001
            errors.append(exc)

    threads = [threading.Thread(target=submitter), threading.Thread(target=predictor)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not errors
    assert seen == sorted(seen)  # a predict never sees an older frame than the one before it
    assert session.stats["submitted"] == 41 and session.stats["predicted"] == 80


@pytest.mark.parametrize("method", ["reproject", "flow2d"])
def test_the_gl_backend_predicts_what_the_cpu_backend_predicts_from_two_threads(method):
    from engine.geometry.backends import gl as glb

    if not glb.available():
        pytest.skip("no EGL context with compute shaders")
    sessions = {b: Session(SessionConfig(width=W, height=H, method=method), backend=b) for b in ("cpu", "gl")}
    color, depth = frame_arrays()
    outs, errors = {}, []

    def run(backend):  # the GL work of a session on any thread runs on the context's own thread
        try:
            session = sessions[backend]
            for i in range(3):
                session.submit(frame_arrays(i)[0], depth, pose(x=0.02 * i), K, i / 30)
            outs[backend] = session.predict(pose(x=0.05), K, 2.5 / 30)
        except Exception as exc:  # noqa: BLE001
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(b,)) for b in sessions]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not errors and outs["gl"].method == method
    close = np.abs(outs["gl"].color - outs["cpu"].color) <= 1e-3 * np.maximum(1.0, np.abs(outs["cpu"].color))
    assert close.all(axis=-1).mean() >= 0.995
    with pytest.raises(InputError):
        Session(SessionConfig(width=W, height=H), backend="metal")


@pytest.mark.parametrize("method", ["reproject", "mvec", "flow2d"])
def test_srgb8_out_on_the_gl_backend_is_encoded_on_the_gpu_as_the_cpu_encodes(method, monkeypatch):
    """color_out="srgb8" on gl: the predicted frame comes back as codes from the GPU (the host encodes
    nothing), equal to encode8 of the same session's linear prediction; rows flipped; a camera cut
    (``repeat``, no GL pass) is encoded on the host."""
    from engine.geometry.backends import gl as glb
    from engine.geometry.encoding import encode8
    from engine.runtime import session as session_module

    if not glb.available():
        pytest.skip("no EGL context with compute shaders")
    host_encodes = []
    monkeypatch.setattr(session_module, "_encode_color", lambda c, s: host_encodes.append(s) or encode8(c))
    depth = frame_arrays()[1]
    outs = {}
    for space in ("linear", "srgb8"):
        session = Session(SessionConfig(width=W, height=H, method=method, color_out=space, flip_rows=True),
                          backend="gl")
        for i in range(3):
            vectors = np.zeros((H, W, 2), np.float32) if method == "mvec" else None
            session.submit(frame_arrays(i)[0] * 1.2, depth, pose(x=0.02 * i), K, i / 30, motion_vectors=vectors)
        outs[space] = session.predict(pose(x=0.05), K, 2.5 / 30)
        assert not host_encodes
        outs[space, "cut"] = session.predict(pose(x=0.05, yaw_deg=90.0), K, 2.5 / 30)
    assert host_encodes == ["srgb8"]  # the camera cut's
    assert outs["srgb8"].color.dtype == np.uint8 and outs["srgb8"].color.shape == (H, W, 3)
    np.testing.assert_array_equal(outs["srgb8"].color, encode8(outs["linear"].color))
    np.testing.assert_array_equal(outs["srgb8"].holes, outs["linear"].holes)
    assert outs["srgb8", "cut"].fallback == "camera_cut" and outs["srgb8", "cut"].color.dtype == np.uint8
    np.testing.assert_array_equal(outs["srgb8", "cut"].color, encode8(outs["linear", "cut"].color))


@pytest.mark.parametrize("method", ["reproject", "mvec", "flow2d"])
def test_srgb8_in_on_the_gl_backend_uploads_the_codes_and_predicts_as_from_floats(method, monkeypatch):
    """color_in="srgb8" on gl: every frame crosses the bus as its codes (RGBA, rows flipped: as given) and is
    decoded on the GPU; predictions equal, bit for bit, those of a session given decode8 of the codes as
    linear floats. With copy=True the caller may overwrite its buffer at once."""
    from engine.geometry.backends import gl as glb
    from engine.geometry.encoding import decode8

    if not glb.available():
        pytest.skip("no EGL context with compute shaders")
    uploads = {"codes": 0, "floats": 0}
    upload, upload_codes = glb.GlFrameWarper.upload, glb.GlFrameWarper.upload_codes

    def count(kind, fn):
        def wrapped(*args, **kwargs):
            uploads[kind] += 1
            return fn(*args, **kwargs)
        return wrapped
    monkeypatch.setattr(glb.GlFrameWarper, "upload", count("floats", upload))
    monkeypatch.setattr(glb.GlFrameWarper, "upload_codes", count("codes", upload_codes))
    rng = np.random.default_rng(21)
    frames = [rng.integers(0, 256, (H, W, 4), dtype=np.uint8) for _ in range(3)]
    depth = frame_arrays()[1]
    sessions = {name: Session(SessionConfig(width=W, height=H, method=method, color_in=space, flip_rows=True),
                              backend="gl") for name, space in (("srgb8", "srgb8"), ("linear", "linear"),
                                                                ("copied", "srgb8"))}
    outs = {}
    for space, session in sessions.items():
        buffer = np.empty_like(frames[0])
        for i, codes in enumerate(frames):
            vectors = np.zeros((H, W, 2), np.float32) if method == "mvec" else None
            given = decode8(codes[..., :3]) if space == "linear" else codes
            if space == "copied":  # one buffer the caller reuses, overwritten right after each submit
                buffer[:] = codes
                session.submit(buffer, depth, pose(x=0.02 * i), K, i / 30, motion_vectors=vectors, copy=True)
                buffer[:] = 0
            else:
                session.submit(given, depth, pose(x=0.02 * i), K, i / 30, motion_vectors=vectors)
        outs[space] = session.predict(pose(x=0.05), K, 2.5 / 30)
    np.testing.assert_array_equal(outs["srgb8"].color, outs["linear"].color)
    np.testing.assert_array_equal(outs["srgb8"].holes, outs["linear"].holes)
    np.testing.assert_array_equal(outs["copied"].color, outs["linear"].color)
    assert uploads["floats"] >= 1 and uploads["codes"] == 2 * uploads["floats"]  # floats: the linear session's


def test_zero_copy_where_layouts_match():
    color, depth = frame_arrays()
    session = make_session()
    session.submit(color, depth, pose(), K, 0.0)
    newest = session._loop.prepared.frames[-1]
    assert np.shares_memory(newest.color, color) and np.shares_memory(newest.depth, depth)
    session.submit(color, depth, pose(), K, 0.1, copy=True)
    newest = session._loop.prepared.frames[-1]
    assert not np.shares_memory(newest.color, color) and not np.shares_memory(newest.depth, depth)
    rgba = np.concatenate([color, np.ones((H, W, 1), np.float32)], axis=-1)
    flipped = make_session(flip_rows=True)
    flipped.submit(rgba, depth, pose(), K, 0.0)  # a 4-channel, bottom-up buffer is still only viewed
    assert np.shares_memory(flipped._loop.prepared.frames[-1].color, rgba)
    out = session.predict(pose(), K, 0.2)
    assert not np.shares_memory(out.color, color)


def test_colour_spaces_and_flipped_rows():
    rng = np.random.default_rng(4)
    srgb8 = rng.integers(0, 256, (H, W, 4), dtype=np.uint8)
    depth = frame_arrays()[1]
    session = make_session(method="repeat", color_in="srgb8", color_out="srgb8")
    session.submit(srgb8, depth, pose(), K, 0.0)
    out = session.predict(pose(), K, 0.1)
    assert out.color.dtype == np.uint8
    np.testing.assert_array_equal(out.color, srgb8[..., :3])  # 8-bit sRGB survives the linear round trip

    color = frame_arrays(5)[0]
    depth = np.broadcast_to(np.linspace(2.0, 6.0, H, dtype=np.float32)[:, None], (H, W))
    plain, flipped = make_session(), make_session(flip_rows=True)
    plain.submit(color, depth, pose(), K, 0.0)
    flipped.submit(color[::-1], depth[::-1], pose(), K, 0.0)  # a bottom-up readback of the same frame
    target = pose(y=0.05, yaw_deg=1.0)
    a, b = plain.predict(target, K, 0.1), flipped.predict(target, K, 0.1)
    np.testing.assert_array_equal(b.color, a.color[::-1])
    np.testing.assert_array_equal(b.holes, a.holes[::-1])


@pytest.mark.parametrize("kwargs, match", [
    (dict(engine="cryengine"), "engine"),
    (dict(method="oracle"), "ground-truth"),
    (dict(far=0.05), "far"),
    (dict(depth_convention="reversed_infinite", far=100.0), "far"),
    (dict(color_in="hdr"), "color_in"),
    (dict(width=0), "width"),
    (dict(cut_rotation_deg=0.0), "cut_rotation_deg"),
])
def test_bad_configs(kwargs, match):
    with pytest.raises(InputError, match=match):
        SessionConfig(**kwargs)


def test_unknown_method_is_an_input_error():
    with pytest.raises(InputError, match="unknown method"):
        Session(SessionConfig(method="warp9"))


def test_rigid_inverse_helper_matches_numpy():  # the Godot rig relies on it being an exact inverse
    view = godot_view([3.0, 1.7, 4.0], (-15.0, 40.0, 8.0))
    np.testing.assert_allclose(rigid_inverse(view), np.linalg.inv(view), atol=1e-12)


def test_near_and_far_must_be_planes_of_the_projection():
    """Issue 20, D10: a SessionConfig near/far that disagreed with the projection decoded every depth
    wrongly without a word (21.9 -> 15.3 dB). Now the submit names the field."""
    from engine.conventions import encode_depth_buffer, projection_from_intrinsics

    k = np.array([[40.0, 0.0, 16.0], [0.0, 40.0, 12.0], [0.0, 0.0, 1.0]])
    projection = projection_from_intrinsics(k, 32, 24, 0.1, 100.0)
    depth = encode_depth_buffer(np.full((24, 32), 5.0), 0.1, 100.0, convention="opengl").astype(np.float32)
    color = np.full((24, 32, 3), 0.5, np.float32)
    view = np.eye(4)
    good = Session(SessionConfig(engine="opengl", width=32, height=24, depth_convention="opengl", near=0.1, far=100.0))
    good.submit(color, depth, view, projection, 0.0)
    for near, far, field in ((0.3, 100.0, "near"), (0.1, 1000.0, "far")):
        session = Session(SessionConfig(engine="opengl", width=32, height=24, depth_convention="opengl",
                                        near=near, far=far))
        with pytest.raises(InputError, match="not a plane of the projection") as info:
            session.submit(color, depth, view, projection, 0.0)
        assert info.value.field == field and info.value.frame == 0
    linear = Session(SessionConfig(engine="opengl", width=32, height=24, near=0.3))  # linear depth: unused
    linear.submit(color, np.full((24, 32), 5.0, np.float32), view, projection, 0.0)


# --------------------------------------------------------------------------------------------
# Motion vectors: each engine's convention, NaN and masks, lower resolution, object-only vectors,
# bad input, camera cuts, "auto"
# --------------------------------------------------------------------------------------------

def true_vectors(points):
    """The true motion of the test: at full-resolution pixel coordinates ``points`` (..., 2) = (x, y), the
    vector in full-resolution pixels (x right, y down) to where the surface point was in the previous frame."""
    x, y = points[..., 0], points[..., 1]
    return np.stack([1.5 + 0.02 * x - 0.01 * y, -0.75 + 0.015 * y + 0.005 * x], axis=-1)


def sample_centres(h, w):
    """Full-resolution (x, y) of the centres of an (h, w) vector buffer's samples: ((j + 0.5) W / w, ...)."""
    x, y = np.meshgrid((np.arange(w) + 0.5) * W / w, (np.arange(h) + 0.5) * H / h)
    return np.stack([x, y], axis=-1)


# Each engine's buffer for the same motion, from the engine's own formulas on the two positions of each
# sample (cur: where the point is now, prev: where it was; full-resolution pixels, row 0 at the top).
def unity_uv(p):  # Unity screen UV: v = 0 at the bottom
    return np.stack([p[..., 0] / W, 1.0 - p[..., 1] / H], axis=-1)


def unreal_screen_pos(p):  # Unreal ScreenPos: NDC, y up
    return np.stack([2.0 * p[..., 0] / W - 1.0, 1.0 - 2.0 * p[..., 1] / H], axis=-1)


def godot_uv(p):  # Godot 4: RenderingDevice clip space (y down) times 0.5
    return 0.5 * np.stack([2.0 * p[..., 0] / W - 1.0, 2.0 * p[..., 1] / H - 1.0], axis=-1)


def buffer_pixels(p, h, w):  # pixels of an (h, w) buffer spanning the viewport
    return p * np.array([w / W, h / H])


CONVENTIONS = {
    # name: (rig, SessionConfig motion fields, encoder (cur, prev, h, w) -> the engine's buffer)
    "unity": ("unity", {}, lambda cur, prev, h, w: unity_uv(cur) - unity_uv(prev)),        # current - previous UV
    "unreal": ("unreal", {}, lambda cur, prev, h, w: unreal_screen_pos(cur) - unreal_screen_pos(prev)),
    "godot": ("godot", {}, lambda cur, prev, h, w: godot_uv(prev) - godot_uv(cur)),          # prev_uv - uv
    "opencv": ("opencv", {}, lambda cur, prev, h, w: buffer_pixels(prev - cur, h, w)),
    # an OpenGL renderer's own buffer: NDC (y up), current -> previous; OpenGL has no default, so it is set
    "opengl": ("opengl", dict(motion_units="ndc", motion_y_up=True, motion_direction="previous"),
               lambda cur, prev, h, w: unreal_screen_pos(prev) - unreal_screen_pos(cur)),
    # FSR 2/3: a UV-space buffer handed to FSR with motionVectorScale = render size (pixels, y down, to previous)
    "fsr_uv_buffer": ("godot", dict(motion_units="pixels", motion_direction="previous", motion_y_up=False),
                      lambda cur, prev, h, w: (prev - cur) / np.array([W, H])),
    # DLSS (Streamline): a pixel-space buffer with mvecScale = (1 / w, 1 / h) into the [-1, 1] (uv) range
    "dlss_pixel_buffer": ("unreal", dict(motion_units="uv", motion_direction="previous", motion_y_up=False),
                          lambda cur, prev, h, w: buffer_pixels(prev - cur, h, w)),
}
SCALES = {"fsr_uv_buffer": lambda h, w: (float(w), float(h)), "dlss_pixel_buffer": lambda h, w: (1.0 / w, 1.0 / h)}


def submit_pair(session, rig, vectors, **kwargs):
    """Submit the rig's view A twice (a static camera), the second time with ``vectors``; returns the frame
    that entered the history."""
    _, d_a, _ = known_point(rig)
    buffer = np.full((H, W), d_a, dtype=np.float32)
    color = ramp_image()
    flip = session.config.flip_rows
    rows = (lambda a: a[::-1]) if flip else (lambda a: a)
    session.submit(rows(color), rows(buffer), rig.view_a, rig.proj_a, 0.0)
    vectors = None if vectors is None else rows(vectors)
    mask = kwargs.pop("motion_valid", None)
    result = session.submit(rows(color), rows(buffer), rig.view_a, rig.proj_a, 1.0 / 60.0, motion_vectors=vectors,
                            motion_valid=None if mask is None else rows(mask), **kwargs)
    assert result.reset is None and result.history == 1  # reproject keeps one frame: the second
    return session._loop.prepared.frames[-1]


@pytest.mark.parametrize("size", [(H, W), (24, 32), (18, 40)], ids=["full", "half", "uneven"])
@pytest.mark.parametrize("name", list(CONVENTIONS))
def test_each_engines_motion_vectors_give_the_same_pixel_vectors(name, size):
    """The same true motion, written as each engine (or upscaler integration) writes its buffer, at full and
    at lower resolution, enters the history as the same full-resolution pixel vectors."""
    rig_name, motion, encode = CONVENTIONS[name]
    rig = RIGS[rig_name]()
    h, w = size
    cur = sample_centres(h, w)
    engine_buffer = encode(cur, cur + true_vectors(cur), h, w).astype(np.float32)
    if name in SCALES:
        motion = dict(motion, motion_scale=SCALES[name](h, w))
    session = Session(SessionConfig(width=W, height=H, method="reproject", **rig.config, **motion))
    frame = submit_pair(session, rig, engine_buffer)
    assert frame.motion_vectors.shape == (h, w, 2) and frame.motion_vectors.dtype == np.float32
    np.testing.assert_allclose(frame.motion_vectors, true_vectors(cur), atol=2e-4)


def test_bottom_up_vectors_with_flip_rows_and_rgba_float16_buffers():
    """A bottom-up readback (Unity Texture2D) of the same buffer, with flip_rows, and an RGBA half-float
    texture whose RG hold the vectors, give the same vectors; y_up describes the picture, not the rows."""
    rig = unity_rig()
    cur = sample_centres(24, 32)
    uv = (unity_uv(cur) - unity_uv(cur + true_vectors(cur))).astype(np.float32)
    rgba = np.concatenate([uv, np.full(uv.shape[:2] + (2,), 7.0, np.float32)], axis=-1).astype(np.float16)
    flipped = Session(SessionConfig(width=W, height=H, method="reproject", flip_rows=True, **rig.config))
    frame = submit_pair(flipped, rig, rgba)  # submit_pair flips every buffer's rows: a bottom-up readback
    np.testing.assert_allclose(frame.motion_vectors, true_vectors(cur), atol=5e-2)  # float16 precision
    plain = Session(SessionConfig(width=W, height=H, method="reproject", **rig.config))
    np.testing.assert_array_equal(submit_pair(plain, rig, rgba).motion_vectors, frame.motion_vectors)


def test_nan_and_the_valid_mask_mark_pixels_without_a_vector():
    rig = opencv_rig()
    cur = sample_centres(H, W)
    buffer = (true_vectors(cur)).astype(np.float32)
    buffer[3, 4] = np.nan
    valid = np.ones((H, W), bool)
    valid[5, 6] = False
    for mask in (valid, valid.astype(np.uint8)):  # a bool mask, or 0 / 1 as a texture holds it
        session = Session(SessionConfig(width=W, height=H, **rig.config))
        vectors = submit_pair(session, rig, buffer, motion_valid=mask).motion_vectors
        missing = np.isnan(vectors).any(axis=-1)
        assert np.argwhere(missing).tolist() == [[3, 4], [5, 6]] and np.isnan(vectors[missing]).all()
        np.testing.assert_allclose(vectors[~missing], true_vectors(cur)[~missing], atol=1e-4)


CAMERA_STEP = 0.06  # m along x between frames A and B: at 3 m and fx = 50, static points move 1 px


@pytest.mark.parametrize("size", [(H, W), (24, 32)], ids=["full", "half"])
def test_object_only_vectors_get_the_cameras_motion_added(size):
    """Object-motion-only vectors (Streamline cameraMotionIncluded = false): the session adds the camera's
    motion. Camera B is 6 cm right of A in front of a wall 3 m away (fx = 50): a static point was 1 px
    further right in A, so the total vector is the object's plus (+1, 0)."""
    h, w = size
    session = make_session(method="reproject", motion_includes_camera=False)
    color, depth = frame_arrays(0)
    objects = np.zeros((h, w, 2), np.float32)
    objects[4:9, 5:12] = (0.5, -0.25)  # a moving object; the rest is static
    objects[1, 1] = np.nan
    session.submit(color, depth, pose(), K, 0.0)
    session.submit(frame_arrays(1)[0], depth, pose(x=CAMERA_STEP), K, 1 / 30, motion_vectors=objects)
    vectors = session._loop.prepared.frames[-1].motion_vectors
    expected = objects * np.array([W / w, H / h]) + np.array([1.0, 0.0])  # "pixels" are the buffer's
    np.testing.assert_allclose(vectors, expected, atol=1e-5)  # NaN stays NaN (assert_allclose: same places)


def test_object_only_vectors_at_low_resolution_sample_the_camera_at_their_own_centres():
    """A camera turning in front of the sky: the camera's motion differs across the picture; at (24, 32) the
    added vectors are those of each sample's own centre (rotation only: q = K R K^-1 p)."""
    h, w = 24, 32
    session = make_session(method="reproject", motion_includes_camera=False)
    color = frame_arrays(0)[0]
    sky = np.full((H, W), np.inf, np.float32)
    session.submit(color, sky, pose(), K, 0.0)
    session.submit(color, sky, pose(yaw_deg=3.0), K, 1 / 30, motion_vectors=np.zeros((h, w, 2), np.float32))
    vectors = session._loop.prepared.frames[-1].motion_vectors
    p = sample_centres(h, w)
    rays = np.concatenate([p, np.ones(p.shape[:2] + (1,))], axis=-1) @ np.linalg.inv(K).T
    b_to_a = pose()[:3, :3] @ pose(yaw_deg=3.0)[:3, :3].T  # camera B axes -> camera A axes
    q = rays @ (K @ b_to_a).T
    np.testing.assert_allclose(vectors, q[..., :2] / q[..., 2:] - p, atol=1e-4)


@pytest.mark.parametrize("ratio", [2, 3, 4])
def test_object_only_vectors_at_low_resolution_take_the_depth_at_their_own_points(ratio):
    """Issue 41, item 7: sample (i, j) of an (h, w) buffer is the point ((j + 0.5) W / w, (i + 0.5) H / h), a
    pixel corner at even ratios; the camera motion added to it is that of the surface there. On a tilted plane
    (inverse depth affine in the image: interpolating it between the nearest pixels is exact) the added
    vectors are the exact camera motion at each sample point."""
    h, w = H // ratio, W // ratio
    session = make_session(method="reproject", motion_includes_camera=False)
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)

    def plane(x, y):  # planar depth of a tilted wall: 1.5 m at the left edge, 6 m at the right
        return 1.0 / (1 / 1.5 + (1 / 6 - 1 / 1.5) * x / W + 0.002 * y)

    color = frame_arrays(0)[0]
    session.submit(color, plane(u, v).astype(np.float32), pose(), K, 0.0)
    session.submit(color, plane(u, v).astype(np.float32), pose(x=CAMERA_STEP), K, 1 / 30,
                   motion_vectors=np.zeros((h, w, 2), np.float32))
    vectors = session._loop.prepared.frames[-1].motion_vectors
    p = sample_centres(h, w)
    now, before = session.camera(pose(x=CAMERA_STEP), K), session.camera(pose(), K)
    rays = np.concatenate([p, np.ones(p.shape[:2] + (1,))], axis=-1) @ np.linalg.inv(K).T
    points = rays * plane(p[..., 0], p[..., 1])[..., None]  # camera B's points at the samples
    b_to_a = before.world_to_camera @ now.camera_to_world
    q = (points @ b_to_a[:3, :3].T + b_to_a[:3, 3]) @ K.T
    np.testing.assert_allclose(vectors, q[..., :2] / q[..., 2:] - p, atol=1e-4)


def test_missing_vectors_can_mean_static_geometry():
    """Unreal leaves static geometry out of its velocity buffer (the clear value): with motion_missing=
    "camera" (Unreal's default) those pixels, marked in motion_valid, get the camera's motion."""
    session = make_session(method="reproject", motion_missing="camera")
    color, depth = frame_arrays(0)
    written = np.zeros((H, W), bool)
    written[10:20, 10:30] = True
    moving = np.where(written[..., None], np.float32(2.5), np.float32(-99.0)) * np.array([1, 0], np.float32)
    session.submit(color, depth, pose(), K, 0.0)
    session.submit(color, depth, pose(x=CAMERA_STEP), K, 1 / 30, motion_vectors=moving, motion_valid=written)
    vectors = session._loop.prepared.frames[-1].motion_vectors
    np.testing.assert_allclose(vectors[written], np.tile([2.5, 0.0], (written.sum(), 1)))
    np.testing.assert_allclose(vectors[~written], np.tile([1.0, 0.0], ((~written).sum(), 1)), atol=1e-5)
    assert SessionConfig(engine="unreal").motion_conventions().missing == "camera"


def _bad(vectors=None, valid=None):
    return dict(motion_vectors=np.zeros((H, W, 2), np.float32) if vectors is None else vectors, motion_valid=valid)


def _with(index, value, shape=(H, W, 2)):
    v = np.zeros(shape, np.float32)
    v[index] = value
    return v


@pytest.mark.parametrize("what, kwargs, config, match", [
    ("inf", _bad(_with((2, 3, 0), np.inf)), {}, r"field 'motion_vectors': has 1 infinite values"),
    ("2-D", _bad(np.zeros((H, W), np.float32)), {}, r"field 'motion_vectors': must have shape \(h, w, 2\)"),
    ("1 channel", _bad(np.zeros((H, W, 1), np.float32)), {}, r"field 'motion_vectors': must have shape"),
    ("5 channels", _bad(np.zeros((H, W, 5), np.float32)), {}, r"field 'motion_vectors': must have shape"),
    ("integers", _bad(np.zeros((H, W, 2), np.uint16)), {}, r"field 'motion_vectors': must be a float array"),
    ("larger", _bad(np.zeros((H + 2, W, 2), np.float32)), {}, r"field 'motion_vectors': are 64x50: must be at most"),
    ("absurd", _bad(_with((0, 0, 1), 1e6)), {}, r"field 'motion_vectors': has a component of 1e\+06 px"),
    ("uv as pixels", _bad(_with((0, 0, 0), 200.0)), dict(motion_units="uv"),
     r"field 'motion_vectors': has a component of 1\.28e\+04 px once converted, over 64 frame diagonals"),
    ("mask shape", _bad(valid=np.ones((H, W - 1), bool)), {}, r"field 'motion_valid': must have the vectors' shape"),
    ("mask values", _bad(valid=np.full((H, W), 2, np.uint8)), {}, r"field 'motion_valid': must be a bool mask"),
    ("mask alone", dict(motion_valid=np.ones((H, W), bool)), {}, r"field 'motion_valid': is given without"),
    ("no convention", _bad(), dict(engine="opengl"), r"field 'motion_units': engine 'opengl' has no motion-vector"),
])
def test_bad_motion_vectors_are_one_line_errors_naming_frame_and_field(what, kwargs, config, match):
    if config.get("engine") == "opengl":
        session = Session(SessionConfig(engine="opengl", width=W, height=H))
        view, projection = np.eye(4), gl_perspective(60.0, W / H, 0.1, 100.0)
    else:
        session, view, projection = make_session(**config), pose(), K
    color, depth = frame_arrays()
    session.submit(color, depth, view, projection, 0.0)
    with pytest.raises(InputError, match=r"^frame 12, " + match) as info:
        session.submit(frame_arrays(1)[0], depth, view, projection, 0.25, frame=12, **kwargs)
    assert "\n" not in str(info.value) and "time 0.25" in str(info.value)
    assert session.stats["submitted"] == 1  # the history is as it was


@pytest.mark.parametrize("kwargs, match", [
    (dict(motion_units="furlongs"), "motion_units"), (dict(motion_direction="sideways"), "motion_direction"),
    (dict(motion_missing="zero"), "motion_missing"), (dict(motion_scale=(1.0, 0.0)), "motion_scale"),
    (dict(motion_scale=(float("nan"), 1.0)), "motion_scale"), (dict(motion_y_up=2), "motion_y_up"),
])
def test_bad_motion_configs(kwargs, match):
    with pytest.raises(InputError, match=match):
        SessionConfig(**kwargs)


def test_a_camera_cut_with_motion_vectors_resets_and_drops_them_no_smearing():
    """Vectors point into the previous submitted frame: after a cut (or time going backwards) that frame
    is gone from the history, so the new frame enters it without vectors and nothing is smeared across."""
    session = make_session(method="flow2d")
    color0, depth = frame_arrays(0)
    color1, _ = frame_arrays(1)
    step = np.tile(np.array([1.0, 0.0], np.float32), (H, W, 1))
    assert session.submit(color0, depth, pose(), K, 0.0, motion_vectors=step).history == 1
    assert session._loop.prepared.frames[-1].motion_vectors is None  # the first frame: nothing to point into
    session.submit(color1, depth, pose(x=CAMERA_STEP), K, 1 / 30, motion_vectors=step)
    np.testing.assert_array_equal(session._loop.prepared.frames[-1].motion_vectors, step)

    jump = session.submit(color0, depth, pose(x=100.0), K, 2 / 30, motion_vectors=step)
    assert jump.reset == "camera_cut" and jump.history == 1
    newest = session._loop.prepared.frames[-1]
    assert newest.motion_vectors is None and newest.index == jump.frame
    out = session.predict(pose(x=100.0), K, 2 / 30 + 1 / 60)
    assert out.method == "reproject" and out.fallback == "history"
    np.testing.assert_allclose(out.color, color0, atol=1e-6)  # the new frame only: nothing of before
    back = session.submit(color1, depth, pose(x=100.0), K, 0.0, motion_vectors=step)
    assert back.reset == "time_backwards" and session._loop.prepared.frames[-1].motion_vectors is None
    session.reset()
    session.submit(color1, depth, pose(x=100.0), K, 1.0, motion_vectors=step)
    assert session._loop.prepared.frames[-1].motion_vectors is None
    assert session.stats["motion_vectors"] == {"kept": 1, "dropped": 4}


def test_auto_picks_mvec_with_vectors_and_flow2d_without_per_submit():
    session = make_session(method="auto")
    depth = frame_arrays()[1]
    step = np.tile(np.array([1.0, 0.0], np.float32), (24, 32, 1))  # the camera's motion, at half resolution
    methods = []
    for i, with_vectors in enumerate([False, True, False, True, True]):
        session.submit(frame_arrays(i)[0], depth, pose(x=CAMERA_STEP * i), K, i / 30,
                       motion_vectors=step if with_vectors else None)
        out = session.predict(pose(x=CAMERA_STEP * (i + 0.5)), K, (i + 0.5) / 30)
        assert np.all(np.isfinite(out.color))
        methods.append(out.method if out.fallback is None else out.fallback)
    assert methods == ["history", "mvec", "flow2d", "mvec", "mvec"]
    with pytest.raises(InputError, match="'auto' takes no options"):
        SessionConfig(method="auto[x=1]")


def test_mvec_without_vectors_is_an_error_naming_the_callers_frame():
    session = make_session(method="mvec")
    color, depth = frame_arrays()
    step = np.tile(np.array([1.0, 0.0], np.float32), (H, W, 1))
    session.submit(color, depth, pose(), K, 0.0, motion_vectors=step)
    session.submit(color, depth, pose(x=CAMERA_STEP), K, 1 / 30, motion_vectors=step)
    with pytest.raises(InputError, match=r"^frame 41, field 'motion_vectors': .*needs.*time 0\.1") as info:
        session.submit(color, depth, pose(x=2 * CAMERA_STEP), K, 0.1, frame=41)
    assert "\n" not in str(info.value) and session.stats["submitted"] == 2
    assert session.predict(pose(x=2 * CAMERA_STEP), K, 0.09).method == "mvec"  # the history is intact
