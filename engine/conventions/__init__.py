"""Game-engine conventions in, OpenCV out: cameras (``cameras``), depth buffers (``depth``), motion vectors
(``motion``). Interleave's own convention and the engine table: ``engine.conventions.cameras``."""
from engine.conventions.cameras import (CLIP_RANGES, IDENTITY_FLIP, OPENGL_EYE_TO_OPENCV, OPENGL_TO_OPENCV, UNITY_FLIP,
                                        UNITY_LOCAL_TO_OPENCV, UNREAL_FLIP, UNREAL_LOCAL_TO_OPENCV, from_godot,
                                        from_opengl, from_unity, from_unreal, intrinsics_from_fov,
                                        intrinsics_from_projection, look_at, opengl_to_opencv_world_to_camera,
                                        projection_from_intrinsics, quaternion_to_matrix, unreal_rotation_matrix)
from engine.conventions.depth import (DEPTH_CONVENTIONS, decode_depth_buffer, decode_from_projection,
                                      encode_depth_buffer, near_far_problem, planar_to_radial, projection_planes,
                                      radial_to_planar)
from engine.conventions.motion import (MOTION_DIRECTIONS, MOTION_UNITS, motion_vectors_to_flow,
                                       motion_vectors_to_previous)

__all__ = ["CLIP_RANGES", "IDENTITY_FLIP", "OPENGL_EYE_TO_OPENCV", "OPENGL_TO_OPENCV", "UNITY_FLIP",
           "UNITY_LOCAL_TO_OPENCV", "UNREAL_FLIP", "UNREAL_LOCAL_TO_OPENCV", "from_godot", "from_opengl", "from_unity",
           "from_unreal", "intrinsics_from_fov", "intrinsics_from_projection", "look_at",
           "opengl_to_opencv_world_to_camera", "projection_from_intrinsics", "quaternion_to_matrix",
           "unreal_rotation_matrix", "DEPTH_CONVENTIONS", "decode_depth_buffer", "decode_from_projection",
           "encode_depth_buffer", "planar_to_radial", "radial_to_planar", "near_far_problem", "projection_planes",
           "motion_vectors_to_flow",
           "motion_vectors_to_previous", "MOTION_UNITS", "MOTION_DIRECTIONS"]
