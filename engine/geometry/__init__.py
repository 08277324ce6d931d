"""Reprojection, multi-plane images (MPI), forward splatting and compositing: the engine's numpy geometry.

``models/geometry.py`` holds the same functions in torch (batched, differentiable: the reference training
uses); ``tests/geometry`` checks these against it. Conventions: ``engine/core/frames.py`` (OpenCV axes,
pixel centres at +0.5, planar depth with +inf sky, linear RGB); design note: ``docs/geometry.md``.
Modules: ``camera`` (unproject, project, reproject), ``mpi`` (build, downsample, composite), ``splat``
(forward warp), ``holefill``, ``kernels`` (numba), ``reference`` (numpy oracles); ``backends.gl`` runs the
warp and the hole fill as OpenGL compute passes, held to these.
"""
from engine.geometry.camera import (MAX_PIXEL_COORD, TINY_DEPTH, pixel_centers, project, relative_transform, reproject,
                                    seen_before, unproject)
from engine.geometry.mpi import (Mpi, build_mpi, composite, disocclusion_mask, downsample_factor, downsample_flow,
                                 downsample_frame, plane_depths, plane_index, visibility)
from engine.geometry.splat import (COVERAGE_THRESHOLD, DEFAULT_SHARPNESS, MIN_LOG_WEIGHT, SUBPIXEL_SNAP,
                                   forward_warp_frame, forward_warp_moved_frame, forward_warp_mpi)

__all__ = ["MAX_PIXEL_COORD", "TINY_DEPTH", "pixel_centers", "project", "relative_transform", "reproject",
           "seen_before", "unproject", "Mpi", "build_mpi", "composite", "disocclusion_mask", "downsample_factor",
           "downsample_flow",
           "downsample_frame", "plane_depths", "plane_index", "visibility", "COVERAGE_THRESHOLD",
           "DEFAULT_SHARPNESS", "MIN_LOG_WEIGHT", "SUBPIXEL_SNAP", "forward_warp_frame", "forward_warp_moved_frame",
           "forward_warp_mpi"]
