"""Tests of engine/conventions/cameras.py: every converter against the engine's own projection math.

Each engine test writes the engine-side pipeline out explicitly (view matrix, projection matrix,
clip -> NDC -> window pixel with row 0 at the top, window depth), then checks that the converted
OpenCV (K, world_to_camera) lands the same scene point on the same pixel (1e-6 px) and that the
decoded depth buffer gives its planar depth. The worked examples in docs/conventions.md are the
fixed scenes of these tests; ``DOC_*`` constants hold the numbers printed there.
"""
from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from engine.conventions import (UNITY_FLIP, UNREAL_FLIP, decode_depth_buffer, decode_from_projection,
                                encode_depth_buffer, from_godot, from_opengl, from_unity, from_unreal,
                                intrinsics_from_fov, intrinsics_from_projection, motion_vectors_to_flow,
                                planar_to_radial, projection_from_intrinsics, radial_to_planar)
from engine.core.errors import InputError
from engine.core.frames import rigid_inverse

PIXEL_TOL = 1e-6
DEPTH_RTOL = 1e-6
FAST = settings(max_examples=60, deadline=None)


# --------------------------------------------------------------------------------------------
# Reference math, written the way each engine does it
# --------------------------------------------------------------------------------------------

def rot_x(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def homogeneous(rotation, translation):
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rotation, translation
    return m


def gl_look_at(eye, target, up):
    """gluLookAt: world -> eye (x right, y up, looking down -z)."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    f = (target - eye) / np.linalg.norm(target - eye)
    s = np.cross(f, up)
    s /= np.linalg.norm(s)
    u = np.cross(s, f)
    rotation = np.stack([s, u, -f])
    return homogeneous(rotation, -rotation @ eye)


def gl_frustum(left, right, bottom, top, near, far):
    """glFrustum: OpenGL clip z in [-1, 1]."""
    return np.array([
        [2 * near / (right - left), 0, (right + left) / (right - left), 0],
        [0, 2 * near / (top - bottom), (top + bottom) / (top - bottom), 0],
        [0, 0, -(far + near) / (far - near), -2 * far * near / (far - near)],
        [0, 0, -1, 0],
    ])


def gl_perspective(fovy_deg, aspect, near, far):
    """gluPerspective / Unity Matrix4x4.Perspective / Godot Projection.set_perspective (clip z in [-1, 1])."""
    cot = 1.0 / math.tan(math.radians(fovy_deg) / 2)
    return np.array([
        [cot / aspect, 0, 0, 0],
        [0, cot, 0, 0],
        [0, 0, -(far + near) / (far - near), -2 * far * near / (far - near)],
        [0, 0, -1, 0],
    ])


def reversed_zero_to_one(gl_projection):
    """Unity GL.GetGPUProjectionMatrix on D3D / Godot 4.3 depth correction: z' = (w - z) / 2."""
    p = gl_projection.copy()
    p[2] = 0.5 * gl_projection[3] - 0.5 * gl_projection[2]
    return p


def clip_to_window(clip, width, height, *, clip_range, ndc_y_down=False):
    """Clip coordinates -> (u, v, d): window pixel (row 0 at the top) and window depth."""
    ndc = clip[:3] / clip[3]
    u = (ndc[0] + 1) / 2 * width
    v = (ndc[1] + 1) / 2 * height if ndc_y_down else (1 - ndc[1]) / 2 * height
    d = (ndc[2] + 1) / 2 if clip_range == "minus_one_to_one" else ndc[2]
    return u, v, d


def opencv_project(intrinsics, world_to_camera, point):
    cam = world_to_camera[:3, :3] @ point + world_to_camera[:3, 3]
    uvw = intrinsics @ cam
    return uvw[0] / uvw[2], uvw[1] / uvw[2], cam[2]


def one_pixel_buffer(u, v, d, width, height, clear):
    """A depth buffer holding the clear value everywhere except the point's pixel."""
    buf = np.full((height, width), clear, dtype=np.float64)
    row, col = int(math.floor(v)), int(math.floor(u))
    buf[row, col] = d
    return buf, (row, col)


# Unreal: FInverseRotationMatrix (Yaw * Pitch * Roll, row vectors) and the view-space axis swap
# FMatrix(Plane(0,0,1,0), Plane(1,0,0,0), Plane(0,1,0,0), Plane(0,0,0,1)) used by FViewMatrices.
def ue_inverse_rotation(pitch, yaw, roll):
    (sp, cp), (sy, cy), (sr, cr) = ((math.sin(math.radians(a)), math.cos(math.radians(a))) for a in (pitch, yaw, roll))
    yaw_m = np.array([[cy, -sy, 0, 0], [sy, cy, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    pitch_m = np.array([[cp, 0, -sp, 0], [0, 1, 0, 0], [sp, 0, cp, 0], [0, 0, 0, 1]])
    roll_m = np.array([[1, 0, 0, 0], [0, cr, sr, 0], [0, -sr, cr, 0], [0, 0, 0, 1]])
    return yaw_m @ pitch_m @ roll_m


UE_VIEW_SWAP = np.array([[0, 0, 1, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)


def ue_translation(offset):
    m = np.eye(4)
    m[3, :3] = offset
    return m


def ue_reversed_z_perspective(half_fov_rad, width, height, min_z):
    """FReversedZPerspectiveMatrix(HalfFOV, Width, Height, MinZ): infinite far plane, row vectors."""
    t = math.tan(half_fov_rad)
    return np.array([[1 / t, 0, 0, 0], [0, width / t / height, 0, 0], [0, 0, 0, 1], [0, 0, min_z, 0]])


def ue_clip(point_cm, location_cm, rotator, hfov_deg, width, height, near_cm):
    """Unreal's own pipeline: [x y z 1] * Translation(-loc) * InvRotation * Swap * Projection."""
    view = ue_translation(-np.asarray(location_cm)) @ ue_inverse_rotation(*rotator) @ UE_VIEW_SWAP
    proj = ue_reversed_z_perspective(math.radians(hfov_deg) / 2, width, height, near_cm)
    return np.append(point_cm, 1.0) @ view @ proj, view


def quat_axis_angle(axis, deg):
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    half = math.radians(deg) / 2
    return np.append(axis * math.sin(half), math.cos(half))  # (x, y, z, w), Unity order


def quat_mul(a, b):
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz])


# --------------------------------------------------------------------------------------------
# OpenGL / Vulkan
# --------------------------------------------------------------------------------------------

W, H = 640, 360

# Worked example "OpenGL" in docs/conventions.md.
GL_EYE, GL_TARGET, GL_UP = (2.0, 1.5, 6.0), (0.3, 0.2, -1.0), (0.1, 1.0, 0.0)
GL_FRUSTUM = (-0.06, 0.1, -0.04, 0.05, 0.1, 100.0)  # off-centre: l != -r, b != -t
GL_POINT = np.array([0.5, 0.8, -2.0])
DOC_GL_PIXEL = (257.4206, 160.9290)
DOC_GL_DEPTH = 8.1231


def test_opengl_offcentre_projection_pixel_and_depth():
    view = gl_look_at(GL_EYE, GL_TARGET, GL_UP)
    proj = gl_frustum(*GL_FRUSTUM)
    assert proj[0, 2] != 0 and proj[1, 2] != 0
    u, v, d = clip_to_window(proj @ view @ np.append(GL_POINT, 1.0), W, H, clip_range="minus_one_to_one")

    k, w2c = from_opengl(W, H, view=view, projection=proj)
    u_cv, v_cv, z = opencv_project(k, w2c, GL_POINT)
    assert abs(u_cv - u) < PIXEL_TOL and abs(v_cv - v) < PIXEL_TOL
    assert z == pytest.approx(-(view @ np.append(GL_POINT, 1.0))[2], rel=1e-12)
    np.testing.assert_allclose(k[0, 1], 0.0)
    assert (u, v, z) == pytest.approx((*DOC_GL_PIXEL, DOC_GL_DEPTH), abs=1e-4)

    buf, (row, col) = one_pixel_buffer(u, v, d, W, H, clear=1.0)
    near, far = GL_FRUSTUM[4], GL_FRUSTUM[5]
    depth = decode_depth_buffer(buf, near, far, convention="opengl")
    assert depth[row, col] == pytest.approx(z, rel=DEPTH_RTOL)
    assert np.isinf(depth).sum() == W * H - 1
    depth_p = decode_from_projection(buf, proj, "minus_one_to_one")
    assert depth_p[row, col] == pytest.approx(z, rel=DEPTH_RTOL)
    assert np.isinf(depth_p).sum() == W * H - 1


def test_vulkan_y_down_zero_to_one_matches_opengl_pixel():
    view = gl_look_at(GL_EYE, GL_TARGET, GL_UP)
    gl = gl_frustum(*GL_FRUSTUM)
    near, far = GL_FRUSTUM[4], GL_FRUSTUM[5]
    vk = gl.copy()
    vk[1] *= -1.0  # NDC y down
    vk[2] = [0, 0, -far / (far - near), -far * near / (far - near)]  # clip z in [0, 1]
    point = np.append(GL_POINT, 1.0)
    u_gl, v_gl, _ = clip_to_window(gl @ view @ point, W, H, clip_range="minus_one_to_one")
    u, v, d = clip_to_window(vk @ view @ point, W, H, clip_range="zero_to_one", ndc_y_down=True)
    assert (u, v) == pytest.approx((u_gl, v_gl), abs=1e-9)  # the same image, row 0 on top

    k, w2c = from_opengl(W, H, view=view, projection=vk, ndc_y_down=True)
    u_cv, v_cv, z = opencv_project(k, w2c, GL_POINT)
    assert abs(u_cv - u) < PIXEL_TOL and abs(v_cv - v) < PIXEL_TOL
    assert decode_depth_buffer(d, near, far, convention="d3d") == pytest.approx(z, rel=DEPTH_RTOL)
    assert decode_from_projection(d, vk, "zero_to_one") == pytest.approx(z, rel=DEPTH_RTOL)
    with pytest.raises(InputError, match="ndc_y_down"):
        from_opengl(W, H, view=view, projection=vk)


def test_opengl_infinite_far_projection():
    view = gl_look_at(GL_EYE, GL_TARGET, GL_UP)
    near = 0.1
    proj = gl_frustum(*GL_FRUSTUM)
    proj[2] = [0, 0, -1, -2 * near]  # far -> inf
    u, v, d = clip_to_window(proj @ view @ np.append(GL_POINT, 1.0), W, H, clip_range="minus_one_to_one")
    k, w2c = from_opengl(W, H, view=view, projection=proj)
    u_cv, v_cv, z = opencv_project(k, w2c, GL_POINT)
    assert abs(u_cv - u) < PIXEL_TOL and abs(v_cv - v) < PIXEL_TOL
    assert decode_depth_buffer(d, near, math.inf, convention="opengl") == pytest.approx(z, rel=DEPTH_RTOL)
    assert decode_depth_buffer(d, near, None, convention="infinite") == pytest.approx(z, rel=DEPTH_RTOL)
    assert decode_from_projection(d, proj, "minus_one_to_one") == pytest.approx(z, rel=DEPTH_RTOL)
    assert np.isinf(decode_depth_buffer(1.0, near, None, convention="infinite"))


def test_projection_errors_are_explained():
    proj = gl_perspective(60, W / H, 0.1, 100)
    view = np.eye(4)
    with pytest.raises(InputError, match="transposed"):
        from_opengl(W, H, view=view, projection=gl_frustum(*GL_FRUSTUM).T)  # off-centre, so detectable
    with pytest.raises(InputError, match=r"\+z"):
        from_opengl(W, H, view=view, projection=proj * np.array([1, 1, 1, -1])[:, None])
    skewed = proj.copy()
    skewed[0, 1] = 0.2
    with pytest.raises(InputError, match="skew"):
        from_opengl(W, H, view=view, projection=skewed)
    oblique = proj.copy()
    oblique[2, 0] = 0.3
    with pytest.raises(InputError, match="oblique"):
        decode_from_projection(0.5, oblique, "minus_one_to_one")
    with pytest.raises(InputError, match="scale or shear"):
        from_opengl(W, H, view=np.diag([2.0, 2.0, 2.0, 1.0]), projection=proj)
    with pytest.raises(InputError, match="clip_range"):
        decode_from_projection(0.5, proj, "gl")


# --------------------------------------------------------------------------------------------
# Unity
# --------------------------------------------------------------------------------------------

# Worked example "Unity" in docs/conventions.md: Quaternion.Euler(10, 30, 5) = qy * qx * qz.
UNITY_POS = np.array([1.0, 2.0, -3.0])
UNITY_EULER = (10.0, 30.0, 5.0)
UNITY_FOV, UNITY_NEAR, UNITY_FAR = 60.0, 0.3, 1000.0
UNITY_POINT_LOCAL = np.array([0.7, -0.4, 5.0])  # x right, y up, z forward of the camera
DOC_UNITY_PIXEL = (363.6477, 204.9415)
DOC_UNITY_DEPTH = 5.0


def unity_camera():
    ex, ey, ez = UNITY_EULER
    rotation = rot_y(ey) @ rot_x(ex) @ rot_z(ez)  # Unity applies z, then x, then y
    quat = quat_mul(quat_mul(quat_axis_angle([0, 1, 0], ey), quat_axis_angle([1, 0, 0], ex)),
                    quat_axis_angle([0, 0, 1], ez))
    local_to_world = homogeneous(rotation, UNITY_POS)
    world_to_camera_gl = np.diag([1.0, 1.0, -1.0, 1.0]) @ np.linalg.inv(local_to_world)  # Unity's definition
    return quat, local_to_world, world_to_camera_gl


def test_unity_all_pose_forms_project_like_unity():
    quat, local_to_world, unity_view = unity_camera()
    point = (local_to_world @ np.append(UNITY_POINT_LOCAL, 1.0))[:3]  # a Unity (left-handed) world point
    proj = gl_perspective(UNITY_FOV, W / H, UNITY_NEAR, UNITY_FAR)  # Camera.projectionMatrix
    u, v, _ = clip_to_window(proj @ unity_view @ np.append(point, 1.0), W, H, clip_range="minus_one_to_one")
    # D3D / Vulkan / Metal: GPU matrix with reversed Z in [0, 1].
    gpu = reversed_zero_to_one(proj)
    _, _, d = clip_to_window(gpu @ unity_view @ np.append(point, 1.0), W, H, clip_range="zero_to_one")

    results = [
        from_unity(W, H, position=UNITY_POS, rotation=quat, vertical_fov_deg=UNITY_FOV),
        from_unity(W, H, matrix=local_to_world, projection=proj),
        from_unity(W, H, matrix=unity_view, matrix_is_world_to_camera=True, vertical_fov_deg=UNITY_FOV),
        from_opengl(W, H, view=unity_view, projection=proj, flip=UNITY_FLIP),
    ]
    point_rh = (UNITY_FLIP @ np.append(point, 1.0))[:3]
    for k, w2c in results:
        u_cv, v_cv, z = opencv_project(k, w2c, point_rh)
        assert abs(u_cv - u) < PIXEL_TOL and abs(v_cv - v) < PIXEL_TOL
        assert z == pytest.approx(UNITY_POINT_LOCAL[2], rel=1e-12)
        np.testing.assert_allclose(w2c, results[0][1], atol=1e-12)
    assert (u, v) == pytest.approx(DOC_UNITY_PIXEL, abs=1e-4)

    buf, (row, col) = one_pixel_buffer(u, v, d, W, H, clear=0.0)
    for depth in (decode_depth_buffer(buf, UNITY_NEAR, UNITY_FAR, convention="reversed"),
                  decode_from_projection(buf, gpu, "zero_to_one")):
        assert depth[row, col] == pytest.approx(DOC_UNITY_DEPTH, rel=DEPTH_RTOL)
        assert np.isinf(depth).sum() == W * H - 1


def test_unity_lens_shift_projection():
    quat, local_to_world, unity_view = unity_camera()
    proj = gl_perspective(UNITY_FOV, W / H, UNITY_NEAR, UNITY_FAR)
    proj[0, 2], proj[1, 2] = 0.15, -0.1  # Camera.lensShift (physical camera) moves the principal point
    point = (local_to_world @ np.append(UNITY_POINT_LOCAL, 1.0))[:3]
    u, v, _ = clip_to_window(proj @ unity_view @ np.append(point, 1.0), W, H, clip_range="minus_one_to_one")
    k, w2c = from_unity(W, H, position=UNITY_POS, rotation=quat, projection=proj)
    u_cv, v_cv, _ = opencv_project(k, w2c, (UNITY_FLIP @ np.append(point, 1.0))[:3])
    assert abs(u_cv - u) < PIXEL_TOL and abs(v_cv - v) < PIXEL_TOL
    assert k[0, 2] != W / 2 and k[1, 2] != H / 2


def test_unity_errors():
    quat, local_to_world, _ = unity_camera()
    with pytest.raises(InputError, match="flip"):  # a left-handed world kept as is would be a reflection
        from_unity(W, H, position=UNITY_POS, rotation=quat, vertical_fov_deg=60, flip=np.eye(4))
    with pytest.raises(InputError, match="unit quaternion"):
        from_unity(W, H, position=UNITY_POS, rotation=2 * quat, vertical_fov_deg=60)
    with pytest.raises(InputError, match="scale"):
        from_unity(W, H, matrix=local_to_world @ np.diag([2.0, 2.0, 2.0, 1.0]), vertical_fov_deg=60)
    with pytest.raises(InputError, match="either"):
        from_unity(W, H, position=UNITY_POS, rotation=quat, matrix=local_to_world, vertical_fov_deg=60)
    with pytest.raises(InputError, match="either"):
        from_unity(W, H, position=UNITY_POS, rotation=quat)


# --------------------------------------------------------------------------------------------
# Unreal
# --------------------------------------------------------------------------------------------

# Worked example "Unreal" in docs/conventions.md (centimetres, FRotator(Pitch, Yaw, Roll)).
UE_LOCATION = np.array([120.0, -340.0, 175.0])
UE_ROTATOR = (-12.0, 35.0, 7.0)
UE_HFOV, UE_NEAR_CM = 90.0, 10.0
UE_POINT = np.array([900.0, 150.0, 60.0])
DOC_UE_PIXEL = (300.8566, 154.8530)
DOC_UE_DEPTH_M = 9.2380


def ue_transform_fmatrix(location, rotator):
    """The camera's FMatrix: rotation rows = inverse of FInverseRotationMatrix, translation in the bottom row."""
    m = np.eye(4)
    m[:3, :3] = ue_inverse_rotation(*rotator)[:3, :3].T
    m[3, :3] = location
    return m


def test_unreal_pixel_and_reversed_infinite_depth():
    clip, view = ue_clip(UE_POINT, UE_LOCATION, UE_ROTATOR, UE_HFOV, W, H, UE_NEAR_CM)
    u, v, d = clip_to_window(clip, W, H, clip_range="zero_to_one")
    assert clip[3] == pytest.approx((np.append(UE_POINT, 1.0) @ view)[2])  # w = view-space depth in cm

    results = [
        from_unreal(W, H, location=UE_LOCATION, rotation=UE_ROTATOR, horizontal_fov_deg=UE_HFOV),
        from_unreal(W, H, transform=ue_transform_fmatrix(UE_LOCATION, UE_ROTATOR), horizontal_fov_deg=UE_HFOV),
    ]
    point_m = (UNREAL_FLIP @ np.append(0.01 * UE_POINT, 1.0))[:3]  # x forward, y left, z up, metres
    for k, w2c in results:
        u_cv, v_cv, z = opencv_project(k, w2c, point_m)
        assert abs(u_cv - u) < PIXEL_TOL and abs(v_cv - v) < PIXEL_TOL
        assert z == pytest.approx(0.01 * clip[3], rel=1e-12)
        np.testing.assert_allclose(w2c, results[0][1], atol=1e-12)
    assert (u, v, 0.01 * clip[3]) == pytest.approx((*DOC_UE_PIXEL, DOC_UE_DEPTH_M), abs=1e-4)

    buf, (row, col) = one_pixel_buffer(u, v, d, W, H, clear=0.0)
    depth = decode_depth_buffer(buf.astype(np.float32), UE_NEAR_CM * 0.01, None, convention="reversed_infinite")
    assert depth[row, col] == pytest.approx(0.01 * clip[3], rel=DEPTH_RTOL)  # even from float32
    assert np.isinf(depth).sum() == W * H - 1


def test_unreal_camera_centre_and_forward_axis():
    _, w2c = from_unreal(W, H, location=UE_LOCATION, rotation=(0.0, 90.0, 0.0), horizontal_fov_deg=90)
    c2w = rigid_inverse(w2c)
    np.testing.assert_allclose(c2w[:3, 3], [1.2, 3.4, 1.75], atol=1e-12)  # y negated, metres
    # Yaw 90 looks along Unreal +y (right), which is -y (right) in the right-handed x-forward/y-left world.
    np.testing.assert_allclose(c2w[:3, 2], [0.0, -1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(c2w[:3, 1], [0.0, 0.0, -1.0], atol=1e-12)  # OpenCV y (down) = -up


def test_unreal_transform_layout_error():
    m = ue_transform_fmatrix(UE_LOCATION, UE_ROTATOR)
    with pytest.raises(InputError, match="FMatrix layout"):
        from_unreal(W, H, transform=m.T, horizontal_fov_deg=90)


def opengl_camera_from_unreal(location_cm, rotator):
    """The same physical camera in a right-handed y-up OpenGL world (metres), built independently.

    OpenGL world from Unreal world: x_gl = y_ue (east), y_gl = z_ue (up), z_gl = -x_ue.
    """
    g = np.array([[0, 1, 0], [0, 0, 1], [-1, 0, 0]], dtype=np.float64)
    axes = ue_inverse_rotation(*rotator)[:3, :3].T  # rows: forward, right, up in Unreal world
    forward, right, up = (g @ axes[i] for i in range(3))
    camera_to_world = homogeneous(np.column_stack([right, up, -forward]), g @ (0.01 * np.asarray(location_cm)))
    return np.linalg.inv(camera_to_world), g


def check_unreal_relative_pose_matches_opengl(loc1, rot1, loc2, rot2, point_cm):
    proj = gl_perspective(60.0, W / H, 0.1, 100)
    _, ue1 = from_unreal(W, H, location=loc1, rotation=rot1, horizontal_fov_deg=90)
    _, ue2 = from_unreal(W, H, location=loc2, rotation=rot2, horizontal_fov_deg=90)
    view1, g = opengl_camera_from_unreal(loc1, rot1)
    view2, _ = opengl_camera_from_unreal(loc2, rot2)
    _, gl1 = from_opengl(W, H, view=view1, projection=proj)
    _, gl2 = from_opengl(W, H, view=view2, projection=proj)
    np.testing.assert_allclose(ue2 @ rigid_inverse(ue1), gl2 @ rigid_inverse(gl1), atol=1e-9)
    # The same point has the same camera coordinates in both.
    p_ue = (UNREAL_FLIP @ np.append(0.01 * np.asarray(point_cm), 1.0))
    p_gl = np.append(g @ (0.01 * np.asarray(point_cm)), 1.0)
    np.testing.assert_allclose(ue1 @ p_ue, gl1 @ p_gl, atol=1e-9)


def test_unreal_relative_pose_matches_opengl_fixed():
    check_unreal_relative_pose_matches_opengl(UE_LOCATION, UE_ROTATOR, [-500.0, 80.0, 320.0], (20.0, -140.0, -15.0),
                                              UE_POINT)


angles = st.tuples(st.floats(-89, 89), st.floats(-180, 180), st.floats(-180, 180))
locations = st.lists(st.floats(-1e4, 1e4), min_size=3, max_size=3)


@FAST
@given(loc1=locations, rot1=angles, loc2=locations, rot2=angles, point=locations)
def test_unreal_relative_pose_matches_opengl_property(loc1, rot1, loc2, rot2, point):
    check_unreal_relative_pose_matches_opengl(loc1, rot1, loc2, rot2, point)


@FAST
@given(rot=angles)
def test_unreal_rotation_matches_inverse_rotation_matrix(rot):
    # Two independent Unreal constructions (FRotationMatrix formula vs FInverseRotationMatrix product) agree.
    from engine.conventions import unreal_rotation_matrix
    np.testing.assert_allclose(unreal_rotation_matrix(*rot), ue_inverse_rotation(*rot)[:3, :3].T, atol=1e-12)


# --------------------------------------------------------------------------------------------
# Godot 4
# --------------------------------------------------------------------------------------------

# Worked example "Godot" in docs/conventions.md: Basis.from_euler((-15, 40, 8) deg), order YXZ.
GODOT_ORIGIN = np.array([3.0, 1.7, 4.0])
GODOT_EULER = (-15.0, 40.0, 8.0)
GODOT_FOV, GODOT_NEAR, GODOT_FAR = 75.0, 0.05, 4000.0
GODOT_POINT_LOCAL = np.array([-0.9, 0.3, -6.0])  # x right, y up, looking down -z
DOC_GODOT_PIXEL = (284.8129, 168.2710)
DOC_GODOT_DEPTH = 6.0


def godot_camera():
    ex, ey, ez = GODOT_EULER
    basis = rot_y(ey) @ rot_x(ex) @ rot_z(ez)
    transform = homogeneous(basis, GODOT_ORIGIN)
    point = (transform @ np.append(GODOT_POINT_LOCAL, 1.0))[:3]
    return basis, np.linalg.inv(transform), point


@pytest.mark.parametrize("keep_aspect", ["height", "width"])
def test_godot_pixel_and_reversed_depth(keep_aspect):
    basis, view, point = godot_camera()
    aspect = W / H
    fovy = GODOT_FOV
    if keep_aspect == "width":  # Projection.set_perspective(..., flip_fov=true): fovy = get_fovy(fov, 1 / aspect)
        fovy = math.degrees(2 * math.atan((1 / aspect) * math.tan(math.radians(GODOT_FOV) / 2)))
    proj = gl_perspective(fovy, aspect, GODOT_NEAR, GODOT_FAR)
    u, v, _ = clip_to_window(proj @ view @ np.append(point, 1.0), W, H, clip_range="minus_one_to_one")
    corrected = reversed_zero_to_one(proj)  # Godot 4.3+ depth correction (reverse_z, remap_z)
    _, _, d = clip_to_window(corrected @ view @ np.append(point, 1.0), W, H, clip_range="zero_to_one")

    for k, w2c in (from_godot(W, H, basis=basis, origin=GODOT_ORIGIN, fov_deg=GODOT_FOV, keep_aspect=keep_aspect),
                   from_godot(W, H, basis=basis, origin=GODOT_ORIGIN, projection=proj)):
        u_cv, v_cv, z = opencv_project(k, w2c, point)
        assert abs(u_cv - u) < PIXEL_TOL and abs(v_cv - v) < PIXEL_TOL
        assert z == pytest.approx(DOC_GODOT_DEPTH, rel=1e-12)
    if keep_aspect == "height":
        assert (u, v) == pytest.approx(DOC_GODOT_PIXEL, abs=1e-4)
    buf, (row, col) = one_pixel_buffer(u, v, d, W, H, clear=0.0)
    for depth in (decode_depth_buffer(buf, GODOT_NEAR, GODOT_FAR, convention="reversed"),
                  decode_from_projection(buf, corrected, "zero_to_one")):
        assert depth[row, col] == pytest.approx(DOC_GODOT_DEPTH, rel=DEPTH_RTOL)
        assert np.isinf(depth).sum() == W * H - 1


def test_godot_flip_changes_world_not_image():
    basis, _, point = godot_camera()
    z_up = np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)  # y-up -> z-up
    k, w2c = from_godot(W, H, basis=basis, origin=GODOT_ORIGIN, fov_deg=GODOT_FOV)
    k2, w2c2 = from_godot(W, H, basis=basis, origin=GODOT_ORIGIN, fov_deg=GODOT_FOV, flip=z_up)
    a = opencv_project(k, w2c, point)
    b = opencv_project(k2, w2c2, (z_up @ np.append(point, 1.0))[:3])
    assert a == pytest.approx(b, abs=1e-9)


# --------------------------------------------------------------------------------------------
# Depth buffers
# --------------------------------------------------------------------------------------------

def test_reversed_z_keeps_float32_precision_at_far_depths():
    near, far = 0.1, 1e5
    z = 1e4 * np.linspace(1.0, 1.5, 97)
    rev = encode_depth_buffer(z, near, far, convention="reversed").astype(np.float32)
    std = encode_depth_buffer(z, near, far, convention="d3d").astype(np.float32)
    rev_inf = encode_depth_buffer(z, near, None, convention="reversed_infinite").astype(np.float32)
    err_rev = np.max(np.abs(decode_depth_buffer(rev, near, far, convention="reversed") / z - 1))
    err_rev_inf = np.max(np.abs(decode_depth_buffer(rev_inf, near, None, convention="reversed_infinite") / z - 1))
    err_std = np.max(np.abs(decode_depth_buffer(std, near, far, convention="d3d") / z - 1))
    assert err_rev < DEPTH_RTOL and err_rev_inf < DEPTH_RTOL
    assert err_std > 1e-4  # standard float32 depth has only ~60 ns of resolution left near d = 1


@pytest.mark.parametrize("convention, clear", [("opengl", 1.0), ("d3d", 1.0), ("infinite", 1.0), ("reversed", 0.0),
                                               ("reversed_infinite", 0.0), ("linear01", 1.0)])
def test_clear_values_decode_to_inf(convention, clear):
    far = None if "infinite" in convention else 50.0
    out = decode_depth_buffer(np.array([[clear, 0.5]], dtype=np.float32), 0.1, far, convention=convention)
    assert np.isinf(out[0, 0]) and out[0, 0] > 0 and np.isfinite(out[0, 1]) and out[0, 1] > 0


def test_reversed_infinite_zero_is_inf_and_exact_inverse():
    out = decode_depth_buffer(np.array([0.0, 1.0, 0.25, 1e-7]), 0.1, None, convention="reversed_infinite")
    assert np.isposinf(out[0])
    np.testing.assert_allclose(out[1:], [0.1, 0.4, 1e6], rtol=1e-15)


def test_linear_depth_buffers():
    out = decode_depth_buffer(np.array([2.5, 100.0, np.inf]), 0.1, 100.0, convention="linear")
    assert out.tolist() == [2.5, math.inf, math.inf]  # far is the clear value
    out = decode_depth_buffer(np.array([0.025, 1.0]), 0.1, 100.0, convention="linear01")
    assert out.tolist() == pytest.approx([2.5, math.inf])
    with pytest.raises(InputError, match="2 values outside"):
        decode_depth_buffer(np.array([0.0, -1.0, 3.0]), 0.1, 100.0, convention="linear")


@pytest.mark.parametrize("convention", ["opengl", "d3d", "reversed", "reversed_infinite"])
def test_bad_buffers_raise_with_field_and_count(convention):
    far = None if convention == "reversed_infinite" else 100.0
    buf = np.array([[0.5, np.nan, 1.2], [-0.1, np.nan, 0.9]], dtype=np.float32)
    with pytest.raises(InputError) as info:
        decode_depth_buffer(buf, 0.1, far, convention=convention, frame=7, field_name="Z")
    err = info.value
    assert err.field == "Z" and err.frame == 7
    assert "2 NaN values" in err.problem and "2 values outside [0, 1]" in err.problem
    assert np.isnan(buf).sum() == 2 and buf[0, 2] == np.float32(1.2)  # input untouched, nothing clamped
    with pytest.raises(InputError, match="1 values outside"):
        decode_from_projection(np.array([0.5, 1.5]), gl_perspective(60, 1.5, 0.1, 100), "minus_one_to_one")


def test_depth_parameter_errors():
    with pytest.raises(InputError, match="near"):
        decode_depth_buffer([0.5], 10.0, 1.0, convention="d3d")
    with pytest.raises(InputError, match="near"):
        decode_depth_buffer([0.5], 0.0, 1.0, convention="d3d")
    with pytest.raises(InputError, match="None or inf"):
        decode_depth_buffer([0.5], 0.1, 100.0, convention="reversed_infinite")
    with pytest.raises(InputError, match="unknown depth convention"):
        decode_depth_buffer([0.5], 0.1, 100.0, convention="vulkan_reversed")
    with pytest.raises(InputError, match="float array"):
        decode_depth_buffer(np.array([3, 4], dtype=np.uint16), 0.1, 100.0, convention="d3d")
    with pytest.raises(InputError, match="outside \\[near, far\\]"):
        encode_depth_buffer([0.05], 0.1, 100.0, convention="reversed")


conventions_finite = st.sampled_from(["opengl", "d3d", "reversed", "linear", "linear01"])
conventions_all = st.sampled_from(["opengl", "d3d", "reversed", "infinite", "reversed_infinite", "linear", "linear01"])


@FAST
@given(convention=conventions_all, near=st.floats(1e-3, 10.0), far_ratio=st.floats(1.5, 1e6),
       fraction=st.floats(0.0, 0.999))
def test_depth_round_trip_property(convention, near, far_ratio, fraction):
    infinite = convention in ("infinite", "reversed_infinite")
    far = None if infinite else near * far_ratio
    top = near * far_ratio
    z = near + fraction * (top - near)
    d = encode_depth_buffer(np.array([z]), near, far, convention=convention)
    if convention != "linear":
        assert 0.0 <= d[0] <= 1.0
    back = decode_depth_buffer(d, near, far, convention=convention)
    assert back[0] == pytest.approx(z, rel=1e-9)
    assert np.isposinf(decode_depth_buffer(encode_depth_buffer([np.inf], near, far, convention=convention),
                                           near, far, convention=convention)[0])


@FAST
@given(fx=st.floats(50, 3000), fy_ratio=st.floats(0.8, 1.25), cx=st.floats(-0.2, 1.2), cy=st.floats(-0.2, 1.2),
       near=st.floats(1e-3, 1.0), far_ratio=st.floats(2, 1e5), infinite=st.booleans(), reversed_z=st.booleans(),
       clip_range=st.sampled_from(["minus_one_to_one", "zero_to_one"]), y_down=st.booleans(),
       fraction=st.floats(1e-3, 0.99))  # z == near exactly can round to d = -1e-17, which is (rightly) rejected
def test_projection_intrinsics_round_trip_property(fx, fy_ratio, cx, cy, near, far_ratio, infinite, reversed_z,
                                                   clip_range, y_down, fraction):
    k = np.array([[fx, 0, cx * W], [0, fx * fy_ratio, cy * H], [0, 0, 1]])
    far = math.inf if infinite else near * far_ratio
    proj = projection_from_intrinsics(k, W, H, near, far, clip_range=clip_range, reversed_z=reversed_z,
                                      ndc_y_down=y_down)
    np.testing.assert_allclose(intrinsics_from_projection(proj, W, H, ndc_y_down=y_down), k, rtol=1e-12, atol=1e-9)
    z = near + fraction * (near * far_ratio - near)
    _, _, d = clip_to_window(proj @ np.array([0.0, 0.0, -z, 1.0]), W, H, clip_range=clip_range)
    convention = ("reversed" if reversed_z else "d3d") + ("_infinite" if infinite and reversed_z else "")
    assert decode_from_projection(d, proj, clip_range) == pytest.approx(z, rel=1e-8)
    assert decode_depth_buffer(d, near, far, convention=convention) == pytest.approx(z, rel=1e-8)
    # Scaling the matrix (homogeneous) changes nothing.
    assert decode_from_projection(d, 3.0 * proj, clip_range) == pytest.approx(z, rel=1e-8)


def test_intrinsics_from_fov():
    k = intrinsics_from_fov(W, H, horizontal_fov_deg=90.0)
    np.testing.assert_allclose(k, [[320, 0, 320], [0, 320, 180], [0, 0, 1]], atol=1e-12)
    with pytest.raises(InputError, match="exactly one"):
        intrinsics_from_fov(W, H, horizontal_fov_deg=90.0, vertical_fov_deg=60.0)


# --------------------------------------------------------------------------------------------
# Radial distance
# --------------------------------------------------------------------------------------------

def test_radial_to_planar_uses_pixel_centres():
    k = np.array([[300.0, 0, 31.0], [0, 280.0, 22.5], [0, 0, 1]])
    h, w = 40, 60
    z = np.full((h, w), 4.0)
    z[5, 7] = np.inf
    radial = np.empty((h, w))
    for row in range(h):
        for col in range(w):
            ray = np.array([(col + 0.5 - k[0, 2]) / k[0, 0], (row + 0.5 - k[1, 2]) / k[1, 1], 1.0])
            radial[row, col] = np.linalg.norm(z[row, col] * ray) if np.isfinite(z[row, col]) else np.inf
    out = radial_to_planar(radial, k)
    np.testing.assert_allclose(out, z, rtol=1e-14)
    np.testing.assert_allclose(planar_to_radial(z, k), radial, rtol=1e-14)
    with pytest.raises(InputError, match="40 values outside"):
        radial_to_planar(np.where(np.arange(w)[None, :] == 3, 0.0, radial), k)


@FAST
@given(values=st.lists(st.floats(1e-3, 1e5), min_size=6, max_size=6), fx=st.floats(10, 2000))
def test_radial_planar_round_trip_property(values, fx):
    k = np.array([[fx, 0, 1.3], [0, fx, 0.7], [0, 0, 1]])
    z = np.array(values).reshape(2, 3)
    np.testing.assert_allclose(radial_to_planar(planar_to_radial(z, k), k), z, rtol=1e-13)


# --------------------------------------------------------------------------------------------
# Motion vectors
# --------------------------------------------------------------------------------------------

def test_motion_vectors_ndc_current_to_previous():
    proj = gl_perspective(60.0, W / H, 0.1, 100.0)
    eye = np.array([0.0, 1.0, 5.0])
    velocity = np.array([0.3, 0.05, -0.2])  # constant camera velocity per frame
    point = np.array([0.4, 0.9, -1.0, 1.0])

    def ndc_and_pixel(e):
        clip = proj @ gl_look_at(e, e + [0, 0, -1], [0, 1, 0]) @ point
        return clip[:2] / clip[3], np.array(clip_to_window(clip, W, H, clip_range="minus_one_to_one")[:2])

    (ndc_prev, px_prev), (ndc_cur, px_cur), (_, px_next) = (ndc_and_pixel(eye + s * velocity) for s in (-1, 0, 1))
    mv = (ndc_prev - ndc_cur)[None, None, :]  # what the engine writes: NDC, y up, current -> previous
    flow = motion_vectors_to_flow(mv, W, H, units="ndc", points_to="previous", y_up=True)
    np.testing.assert_allclose(flow[0, 0], px_cur - px_prev, atol=1e-9)  # exact: the negated vector
    np.testing.assert_allclose(flow[0, 0], px_next - px_cur, rtol=0.1)  # constant-velocity approximation only
    assert np.all(mv == (ndc_prev - ndc_cur))  # input untouched

    uv = np.array([[[(px_prev - px_cur)[0] / W, (px_prev - px_cur)[1] / H]]])  # UV, v down
    np.testing.assert_allclose(motion_vectors_to_flow(uv, W, H, units="uv", points_to="previous", y_up=False)[0, 0],
                               px_cur - px_prev, atol=1e-9)
    np.testing.assert_allclose(motion_vectors_to_flow([[1.5, -2.0]], W, H, units="pixels", points_to="next",
                                                      y_up=False), [[1.5, -2.0]])


def test_motion_vector_errors():
    with pytest.raises(InputError, match="1 non-finite"):
        motion_vectors_to_flow(np.array([[0.1, np.nan]]), W, H, units="ndc", points_to="previous", y_up=True)
    with pytest.raises(InputError, match="units"):
        motion_vectors_to_flow(np.zeros((2, 2)), W, H, units="metres", points_to="previous", y_up=True)
    with pytest.raises(InputError, match=r"\(\.\.\., 2\)"):
        motion_vectors_to_flow(np.zeros((2, 3)), W, H, units="ndc", points_to="previous", y_up=True)


def test_engine_does_not_import_torch():
    code = "import sys, engine.conventions; assert 'torch' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True, cwd=Path(__file__).resolve().parents[2])
