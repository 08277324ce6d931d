"""Real-time rendering of an exported static radiance field: OpenGL compute shaders, one ray per pixel.

``GlFieldRenderer(assets, width, height).render(K, world_to_camera)`` renders what
:func:`engine.fields.render.render_field` (the numpy reference, its test oracle) renders: colour (H, W, 3)
linear RGB, planar depth (H, W) with ``+inf`` where the opacity is below ``OPACITY_EPS``, and opacity, for
the assets ``interleave export field`` writes (``docs/field-assets.md``). It runs on a headless moderngl
context (EGL; Mesa llvmpipe is enough: OpenGL 4.5 compute shaders and ``GL_ARB_gpu_shader_fp64``).

How the shader maps the format (the design note is ``docs/field-assets.md``, "Real-time rendering"):

- **Shader per asset.** The GLSL is generated for one field: the number of samples, the spacing, the
  scene kind, the plane resolutions and channels and the MLP sizes are compile-time constants, and every
  MLP layer is emitted as straight-line ``dot`` products over vec4s, so nothing is indexed dynamically.
- **Planes** are one 2D array texture per scale, layer ``k * G + g`` holding channels ``4g .. 4g + 3`` of
  plane k (xy, xz, yz; G = ceil(C / 4), zero padding): float32 (``RGBA32F``) or, with ``quantized=True``,
  the uint8 codes (normalised ``RGBA8``) dequantised in the shader with the per-plane, per-channel
  ``[min, max]`` ranges of the export (``min + code / 255 (max - min)``, applied after the bilinear
  interpolation, with which it commutes). ``filtering="hardware"`` (default) lets the sampler interpolate
  (``GL_LINEAR``, clamp to edge) at texture coordinate ``(x + 0.5) / R`` with
  ``x = clamp((c + 1) / 2 (R - 1), 0, R - 1)`` (GL puts texel centres at ``(i + 0.5) / R``), which is
  ``grid_sample(align_corners=True, padding_mode="border")``: one fetch per texel group, at the filtering
  precision of the GL implementation (llvmpipe filters float textures in float32, identical to the
  reference here, but 8-bit textures to 8 bits; GPUs typically use 8-bit sub-texel weights).
  ``filtering="exact"`` reads the four texels with ``texelFetch`` and interpolates in float32.
- **MLP weights** are literals in the generated code (``weights="inline"``, default; 2.5x faster on
  llvmpipe than reading them from a buffer) or a uniform / storage buffer (``weights="buffer"``), rows
  padded to vec4. The columns of the first colour layer that multiply the view-direction encoding are
  applied once per pixel (the direction is the same for every sample of a ray): per sample only ``W_h h``.
- **Sampling** is the reference's: rays through pixel centres with camera z = 1 (t is planar depth; the
  direction is computed in float64 like ``camera_rays_np``), ``[near, far]`` clipped to the box for
  bounded scenes, ``num_samples`` bin-centre samples linear in t or in 1/t, ``torch.lerp``'s rounding.
- **Empty-space skipping**: samples are visited in chunks of 64; a cheap pass marks the samples of a chunk that
  are inside the cube, in an occupied cell (bit-packed grid in a storage buffer) and in a non-empty bin (a
  two-word mask), then the field is evaluated by looping over the marked ones only (llvmpipe runs a loop's body
  once with every lane idle: a fixed cost a chunk, which chunks of 32 paid twice at 64 samples). SIMD hardware
  (and llvmpipe, which runs 8 invocations per AVX2 vector and executes both sides of every branch under a mask)
  pays a loop iteration when any lane of the group needs it, so a loop over all samples that skips empty ones
  costs every sample; the loop over marked samples costs the most any lane has. Invocations are laid out so that
  each group of 8 is a 4x2 pixel block (coherent rays). In a bounded scene with linear spacing the grid holds
  each empty cell's Chebyshev distance to the nearest occupied one (a byte per cell) instead of a bit, and the
  cheap pass jumps over the samples that distance proves empty (a step moves a point by at most ``R / N`` cells
  per axis inside the box): the same samples are evaluated, fewer are tested (lego's baked field on llvmpipe:
  0.8x the CPU time a frame).
- **Early ray termination**: the march stops once the transmittance falls below ``transmittance_eps``;
  the latent rows of the density MLP and the colour MLP run only where the sample's weight exceeds
  ``color_eps`` (a saving on GPUs; llvmpipe evaluates the branch under a mask anyway).

Error bounds against the reference (colour in linear RGB, background and colours in [0, 1]): stopping at
transmittance T < ``transmittance_eps`` drops samples whose weights sum to at most T, so colour and
opacity change by at most ``transmittance_eps`` (1e-4 by default). A sample whose weight w is at most
``color_eps`` gets the background colour instead of its own (its weight still counts in the opacity): at
most ``num_samples * color_eps`` per pixel in total (64 * 1e-5 = 6.4e-4 by default; measured errors are far
smaller, see the tests). Planar depth moves by at most ``transmittance_eps / opacity * (far - near)``. Both
set to 0 give the reference's compositing up to float32 rounding. ``color_mode="latent"`` (colour MLP once
per pixel on the weight-averaged latent) is an approximation for comparison only: the MLP is not linear in
its input, and the bench measures ~27 dB against the exact colour. A field trained with deferred shading
(``field.shading = "deferred"``, ``docs/field-assets.md``) is shaded once per pixel exactly: its features
are composited and the colour MLP runs on them after the march (``color_mode`` must stay ``per-sample``).

The EGL context stays current on the thread that created the renderer; use it from that thread. The shader
generator and the renderer that compiles and feeds it stay in one module (~770 lines): every uniform,
buffer binding and texture layer is named by both sides; ``engine.fields.gldynamic`` reuses the generator
through its public hooks (``generate_shader``, ``ShaderParams``, ``linear_code``, ``mlp_hidden_code``).

>>> with GlFieldRenderer(load_field("runs/lego/export"), 960, 540) as r:     # doctest: +SKIP
...     out = r.render(K, world_to_camera)
>>> out["color"].shape, out["depth"].shape                                   # doctest: +SKIP
((540, 960, 3), (540, 960))

``python -m tools.bench_fields static EXPORT_DIR --sizes 512x512,960x540`` times this renderer against the
numpy and onnxruntime paths of :mod:`engine.fields.render` and (when torch is importable) the torch renderer.
"""
from __future__ import annotations

import math
import re
import threading
import time
from pathlib import Path
from typing import Callable, Optional, Sequence, Union

import numpy as np

from engine.core.checks import check_range
from engine.core.errors import InputError
from engine.core.frames import validate_intrinsics, validate_pose
from engine.fields.render import (FAR_AT_INFINITY, MIN_NEAR, OPACITY_EPS, PLANE_AXES, SH_C0, SH_C1, SH_C2, SH_C3,
                                  TRANSMITTANCE_EPS, FieldAssets, load_field)

__all__ = ["GlFieldRenderer", "TRANSMITTANCE_EPS", "COLOR_EPS", "available", "ShaderParams", "generate_shader",
           "linear_code", "mlp_hidden_code", "pad_matrix", "texture_layers", "check_options", "inline_params",
           "CAMERA_GLSL", "contract_glsl", "march_code", "color_head", "finish_shader", "set_uniforms",
           "camera_uniforms", "scene_uniforms"]

#: Default weight below which a sample's colour MLP is not evaluated (the background colour stands in).
COLOR_EPS = 1e-5
#: Largest uniform-buffer size used for the weights (bytes); bigger MLPs go to a storage buffer.
_UBO_LIMIT = 65536
_TILE = 8
#: Tiles per shader invocation on a software renderer (llvmpipe): measured in
#: docs/results/2026-11-27-field-render-cost.md; hardware renderers get 1.
SOFTWARE_TILES = 8

_AVAILABLE: Optional[bool] = None
#: the OpenGL version the field renderers ask EGL for (compute shaders); without it moderngl asks for 3.3, which
#: NVIDIA's driver gives exactly
REQUIRED_GL = 430


def available() -> bool:
    """True when a headless EGL context with OpenGL 4.5 compute shaders and fp64 can be created (cached)."""
    global _AVAILABLE
    if _AVAILABLE is None:
        try:
            import moderngl

            ctx = moderngl.create_standalone_context(backend="egl", require=REQUIRED_GL)
            try:
                _AVAILABLE = ctx.version_code >= 430 and "GL_ARB_gpu_shader_fp64" in ctx.extensions
            finally:
                ctx.release()
        except Exception:  # no moderngl, no EGL
            _AVAILABLE = False
    return _AVAILABLE


# ----------------------------------------------------------------------------------------------------
# Packing the arrays and generating the shader


class ShaderParams:
    """The weights and ranges as one (M, 4) float32 array of vec4 rows, with GLSL references to them."""

    def __init__(self) -> None:
        self.rows: list[np.ndarray] = []
        self.count = 0

    def add(self, array: np.ndarray) -> int:
        """Append an array whose size is a multiple of 4 (row-major), return its first vec4 row."""
        a = np.ascontiguousarray(array, np.float32).reshape(-1, 4)
        offset = self.count
        self.rows.append(a)
        self.count += a.shape[0]
        return offset

    def array(self) -> np.ndarray:
        return np.concatenate(self.rows, axis=0) if self.rows else np.zeros((1, 4), np.float32)


def _pad_to(n: int) -> int:
    return -(-n // 4) * 4


def pad_matrix(w: np.ndarray, rows: int, cols: int, col_map: Optional[np.ndarray] = None) -> np.ndarray:
    """(out, in) -> (rows, cols) zero-padded; ``col_map[j]`` is the padded column of input j."""
    out = np.zeros((rows, cols), np.float32)
    cm = np.arange(w.shape[1]) if col_map is None else col_map
    out[:w.shape[0], cm] = w
    return out


def linear_code(name: str, xs: list[str], w_off: int, n_out4: int, biases: list[str], relu: bool
            ) -> tuple[list[str], list[str]]:
    """GLSL for ``y = W x + b`` on vec4 inputs ``xs``: rows of W at ``P[w_off + j * len(xs) + k]``."""
    ni = len(xs)
    lines, outs = [], []
    for q in range(n_out4):
        comps = []
        for r in range(4):
            j = 4 * q + r
            terms = [f"dot(P[{w_off + j * ni + k}], {xs[k]})" for k in range(ni)]
            comps.append(" + ".join(terms) if terms else "0.0")
        expr = f"vec4({', '.join(comps)}) + {biases[q]}"
        if relu:
            expr = f"max({expr}, vec4(0.0))"
        lines.append(f"vec4 {name}{q} = {expr};")
        outs.append(f"{name}{q}")
    return lines, outs


def mlp_hidden_code(prefix: str, params: ShaderParams, xs: list[str], layers, first_cols: Optional[np.ndarray] = None
                ) -> tuple[list[str], list[str]]:
    """All layers of ``layers`` (each (W, b)) with ReLU after each one; returns code and output vec4s."""
    lines: list[str] = []
    for i, (w, b) in enumerate(layers):
        rows = _pad_to(w.shape[0])
        wp = pad_matrix(w, rows, 4 * len(xs), first_cols if i == 0 else None)
        w_off = params.add(wp)
        b_off = params.add(np.pad(b, (0, rows - b.shape[0])))
        code, xs = linear_code(f"{prefix}{i}_", xs, w_off, rows // 4, [f"P[{b_off + q}]" for q in range(rows // 4)], True)
        lines += code
    return lines, xs


def _direction_encoding(kind: str, degree: int) -> list[str]:
    """Scalar GLSL expressions of the encoding of unit direction ``dir`` (``direction_encoding_np``)."""
    if kind == "sh":
        out = [f"{SH_C0!r}"]
        if degree > 1:
            out += [f"-{SH_C1!r} * dir.y", f"{SH_C1!r} * dir.z", f"-{SH_C1!r} * dir.x"]
        if degree > 2:
            out += [f"{SH_C2[0]!r} * dir.x * dir.y", f"-{SH_C2[1]!r} * dir.y * dir.z",
                    f"{SH_C2[2]!r} * (3.0 * dir.z * dir.z - 1.0)", f"-{SH_C2[3]!r} * dir.x * dir.z",
                    f"{SH_C2[4]!r} * (dir.x * dir.x - dir.y * dir.y)"]
        if degree > 3:
            xx, yy, zz = "(dir.x * dir.x)", "(dir.y * dir.y)", "(dir.z * dir.z)"
            out += [f"-{SH_C3[0]!r} * dir.y * (3.0 * {xx} - {yy})", f"{SH_C3[1]!r} * dir.x * dir.y * dir.z",
                    f"-{SH_C3[2]!r} * dir.y * (5.0 * {zz} - 1.0)", f"{SH_C3[3]!r} * dir.z * (5.0 * {zz} - 3.0)",
                    f"-{SH_C3[4]!r} * dir.x * (5.0 * {zz} - 1.0)", f"{SH_C3[5]!r} * dir.z * ({xx} - {yy})",
                    f"-{SH_C3[6]!r} * dir.x * ({xx} - 3.0 * {yy})"]
        return out
    if kind == "fourier":
        axes = ("dir.x", "dir.y", "dir.z")
        scaled = [f"{axes[a]} * {float(2.0 ** k)!r}" for k in range(degree) for a in range(3)]
        return list(axes) + [f"sin({s})" for s in scaled] + [f"cos({s})" for s in scaled]
    if kind == "none":
        return []
    raise InputError(f"unknown direction encoding {kind!r} (expected sh, fourier or none)", field="direction_encoding")


_TEMPLATE = """
#version 450
layout(local_size_x = 64) in;

%(params_decl)s
layout(std430, binding = 1) readonly buffer OccBuf { uint occ_bits[]; };
layout(std430, binding = 2) writeonly buffer RgbdBuf { vec4 out_rgbd[]; };
layout(std430, binding = 3) writeonly buffer OpacityBuf { float out_opacity[]; };
%(count_decl)s
%(samplers)s

uniform ivec2 size;             // W, H
uniform dvec4 k_vals;           // K00 (fx), K01, K02 (cx), K11 (fy)
uniform double k_cy;            // K12
uniform dmat3 rot;              // world_to_camera rotation: rot[i][j] = R[i, j]
uniform vec3 origin;            // camera centre, float32
uniform float near;
uniform float far;
uniform vec3 box_lo;
uniform vec3 box_hi;
uniform vec3 box_center;
uniform vec3 box_half;
uniform mat3 ndc_rot;           // NDC reference camera rotation (q = R p + t)
uniform vec3 ndc_t;
uniform vec4 ndc_k;             // k00, k01, k02, k11
uniform float ndc_k12;
uniform vec2 ndc_size;          // W, H
uniform float ndc_margin;
uniform float scene_near;
uniform vec3 background;
uniform float transmittance_eps;
uniform float color_eps;

const int N = %(num_samples)d;
const float INF = uintBitsToFloat(0x7f800000u);

%(camera_glsl)s

%(contract_glsl)s

float lerp_(float a, float b, float w) {
    // torch.lerp's formula, exact at both ends (sample positions round as in training)
    precise float r = w < 0.5 ? a + w * (b - a) : b - (b - a) * (1.0 - w);
    return r;
}

float one_minus_exp(float x) {  // 1 - exp(-x) = -expm1(-x), accurate for small x
    return x < 1e-3 ? x * (1.0 - x * (0.5 - x * (1.0 / 6.0))) : 1.0 - exp(-x);
}

void shade(ivec2 tile) {
    // 8x8 tiles whose SIMD groups of 8 invocations are 4x2 pixel blocks (coherent rays: fewer idle lanes)
    uint lid = gl_LocalInvocationIndex, chunk = lid >> 3u, lane = lid & 7u;
    ivec2 pix = tile * 8 + ivec2((chunk & 1u) * 4u + (lane & 3u), (chunk >> 1u) * 2u + (lane >> 2u));
    if (pix.x >= size.x || pix.y >= size.y) return;
    int o = pix.y * size.x + pix.x;

    vec3 d = pixel_ray(pix);
    float dnorm = length(d);
    vec3 dir = d / dnorm;

    float t0 = near, t1 = far;
%(bounds)s
    t1 = max(t1, t0);
%(spacing_setup)s

%(per_pixel)s

    float tau_sum = 0.0, trans = 1.0, acc = 0.0, dsum = 0.0;
    vec3 col = vec3(0.0);
%(accum_decl)s
    // Samples are visited in chunks of 64: first the cheap test of every sample of the chunk (inside the
    // cube, occupied cell, non-empty bin) into a bit mask (x: samples 0-31 of the chunk, y: 32-63), then the
    // field only at the kept ones. A GPU or llvmpipe executes a branch for all the lanes of a SIMD group, so a
    // loop over the kept samples costs (max kept in the group) evaluations where a loop over all samples with
    // a skip would cost N; llvmpipe also runs a loop's body once with every lane idle, a chunk's fixed cost.
    bool done = false;
    uint evaluated = 0u;
    for (int base = 0; base < N && !done; base += 64) {
        uvec2 kept = uvec2(0u);
        int jump = 1;
        for (int j = 0; j < 64 && base + j < N; j += jump) {
            int i = base + j;
%(locate)s
            if (keep) {
                if (j < 32) kept.x |= 1u << uint(j); else kept.y |= 1u << uint(j - 32);
            }
%(advance)s
        }
        while (kept.x != 0u || kept.y != 0u) {
            int j;
            if (kept.x != 0u) {
                j = findLSB(kept.x);
                kept.x &= kept.x - 1u;
            } else {
                j = 32 + findLSB(kept.y);
                kept.y &= kept.y - 1u;
            }
            ++evaluated;
            int i = base + j;
%(locate)s
%(features)s
%(density)s
            float sigma = exp(min(raw + %(density_bias)r, %(max_log)r));
            float len = delta * dnorm;
            float tau = (sigma == 0.0 || len == 0.0) ? 0.0 : sigma * len;
            float w = trans * one_minus_exp(tau);
            tau_sum += tau;
            trans = exp(-tau_sum);  // T_i = exp(-sum_{j<i} tau_j), as the reference
            acc += w;
            dsum += w * t;
            if (w > color_eps) {
%(latent)s
%(color_sample)s
            } else {
                col += w * background;
            }
            if (trans < transmittance_eps) {  // early ray termination
                done = true;
                break;
            }
        }
    }
%(color_final)s
    col += (1.0 - acc) * background;
    float depth = acc >= %(opacity_eps)r ? dsum / max(acc, %(opacity_eps)r) : INF;
    out_rgbd[o] = vec4(col, depth);
    out_opacity[o] = acc;
%(count_write)s
}

void main() {
    // TILES (defined at compile time) tiles stacked along y per invocation: on llvmpipe every call of the
    // shader pays a prologue that grows with the MLP code (constants set up before the march), so shading
    // several pixels per call amortises it; a GPU gets 1
    for (int r = 0; r < TILES; ++r) shade(ivec2(gl_WorkGroupID.x, int(gl_WorkGroupID.y) * TILES + r));
}
"""


#: GLSL of the camera ray through a pixel centre (camera z = 1): float64 like ``camera_rays_np``, then float32.
#: Uniforms ``k_vals``, ``k_cy``, ``rot`` (:func:`camera_uniforms`).
CAMERA_GLSL = """vec3 pixel_ray(ivec2 pix) {  // world direction R^T (K^-1 (u, v, 1)) of pixel centre (u, v) = pix + 0.5
    double u = double(pix.x) + 0.5LF, v = double(pix.y) + 0.5LF;
    double cy = (v - k_cy) / k_vals.w;
    double cx = (u - k_vals.z - k_vals.y * (v - k_cy) / k_vals.w) / k_vals.x;
    dvec3 cam = dvec3(cx, cy, 1.0LF);
    return vec3(cam.x * rot[0][0] + cam.y * rot[1][0] + cam.z * rot[2][0],
                cam.x * rot[0][1] + cam.y * rot[1][1] + cam.z * rot[2][1],
                cam.x * rot[0][2] + cam.y * rot[1][2] + cam.z * rot[2][2]);
}"""

_BOX_CONTRACT = """vec3 contract(vec3 p) {  // world point -> the field's cube (as contract_np)
    return (p - box_center) / box_half;
}"""

_NDC_CONTRACT = """vec3 contract(vec3 p) {  // world point -> the field's cube (as contract_np); behind the camera: -2
    vec3 q = ndc_rot * p + ndc_t;
    vec3 c = vec3(-2.0);
    if (q.z > 0.0) {
        float pu = (ndc_k.x * q.x + ndc_k.y * q.y) / q.z + ndc_k.z;
        float pv = ndc_k.w * q.y / q.z + ndc_k12;
        c = vec3((2.0 * pu / ndc_size.x - 1.0) / (1.0 + ndc_margin),
                 (2.0 * pv / ndc_size.y - 1.0) / (1.0 + ndc_margin), 1.0 - 2.0 * scene_near / q.z);
    }
    return c;
}"""


def contract_glsl(bounded: bool) -> str:
    """GLSL ``vec3 contract(vec3 p)`` of a bounded (box) or forward-facing (NDC) scene; its uniforms are
    :func:`scene_uniforms`'."""
    return _BOX_CONTRACT if bounded else _NDC_CONTRACT


def set_uniforms(program, values: dict) -> None:
    """Set ``values`` (name -> value) on a moderngl program, skipping the uniforms its compiler optimised out."""
    for name, value in values.items():
        try:
            program[name].value = value
        except KeyError:  # optimised out of this program
            pass


def camera_uniforms(intrinsics, world_to_camera) -> dict:
    """The uniforms of :data:`CAMERA_GLSL` and the ray origin for a checked camera (OpenCV axes, rigid pose).

    Raises:
        InputError: intrinsics not a finite pinhole K with positive focal lengths; pose not rigid.
    """
    k = validate_intrinsics(intrinsics)
    pose = validate_pose(world_to_camera)
    rot = pose[:3, :3]
    origin = (-rot.T @ pose[:3, 3]).astype(np.float32)
    return {"k_vals": (float(k[0, 0]), float(k[0, 1]), float(k[0, 2]), float(k[1, 1])), "k_cy": float(k[1, 2]),
            "rot": tuple(float(x) for x in rot.flatten()),  # column-major upload: rot[i][j] = R[i, j]
            "origin": tuple(float(x) for x in origin)}


def scene_uniforms(assets, width: int, height: int) -> dict:
    """The uniforms of a field's scene (size, near, the box or the NDC camera: :func:`contract_glsl`'s), float32."""
    scene = assets.scene
    values = {"size": (int(width), int(height)), "scene_near": float(np.float32(scene["near"]))}
    if assets.bounded:
        lo = np.asarray(scene["box_min"], np.float32)
        hi = np.asarray(scene["box_max"], np.float32)
        values.update(box_lo=tuple(map(float, lo)), box_hi=tuple(map(float, hi)),
                      box_center=tuple(map(float, (lo + hi) / np.float32(2))),
                      box_half=tuple(map(float, (hi - lo) / np.float32(2))))
    else:
        k = np.asarray(scene["ndc_intrinsics"], np.float32)
        t = np.asarray(scene["ndc_world_to_camera"], np.float32)
        values.update(ndc_rot=tuple(float(x) for x in t[:3, :3].flatten(order="F")),  # column-major
                      ndc_t=tuple(float(x) for x in t[:3, 3]),
                      ndc_k=(float(k[0, 0]), float(k[0, 1]), float(k[0, 2]), float(k[1, 1])),
                      ndc_k12=float(k[1, 2]), ndc_size=tuple(float(x) for x in scene["ndc_size"]),
                      ndc_margin=float(np.float32(assets.manifest["render"]["ndc_margin"])))
    return values


def march_code(assets) -> dict[str, str]:
    """The template's ray setup of a field's scene and sampling (``bounds``, ``spacing_setup``) and ``locate``,
    the per-sample code that places sample ``i`` (``t``, ``delta``, world ``p``, contracted ``c``) and sets
    ``keep`` (inside the cube, non-empty bin, occupied cell of ``assets.occupancy``)."""
    render = assets.manifest["render"]
    if assets.bounded:
        bounds = """    {   // slab test against the box (as engine.fields.render._ray_box)
        float enter = -1e30, leave = 1e30;
        for (int a = 0; a < 3; ++a) {
            bool parallel = d[a] == 0.0;
            float inv = 1.0 / (parallel ? 1.0 : d[a]);
            float ta = (box_lo[a] - origin[a]) * inv, tb = (box_hi[a] - origin[a]) * inv;
            bool inside = origin[a] >= box_lo[a] && origin[a] <= box_hi[a];
            float lo_a = parallel ? (inside ? -1e30 : 1e30) : min(ta, tb);
            float hi_a = parallel ? (inside ? 1e30 : -1e30) : max(ta, tb);
            enter = max(enter, lo_a);
            leave = min(leave, hi_a);
        }
        t0 = max(t0, enter);
        t1 = min(t1, leave);
    }"""
    else:
        bounds = ""
    contract = "        vec3 c = contract(p);"
    if render["spacing"] == "linear":
        spacing_setup = ""
        sample_t = """        float e0 = lerp_(t0, t1, float(i) / float(N));
        float e1 = lerp_(t0, t1, float(i + 1) / float(N));
        float t = lerp_(t0, t1, (float(i) + 0.5) / float(N));
        float delta = max(e1 - e0, 0.0);"""
    else:
        spacing_setup = f"""    float s_near = 1.0 / max(t0, {MIN_NEAR!r});
    float s_far = 1.0 / max(min(t1, {FAR_AT_INFINITY!r}), max(t0, {MIN_NEAR!r}));"""
        sample_t = """        float e0 = 1.0 / lerp_(s_near, s_far, float(i) / float(N));
        float e1 = 1.0 / lerp_(s_near, s_far, float(i + 1) / float(N));
        float t = 1.0 / lerp_(s_near, s_far, (float(i) + 0.5) / float(N));
        float delta = max(e1 - e0, 0.0);"""
    occupancy, advance = "", ""
    if assets.occupancy is not None:
        res = assets.occupancy.shape[0]
        if skips_by_distance(assets):
            occupancy = f"""uint dist = 0u;
if (keep) {{  // empty-cell distance grid [ix, iy, iz], a byte per cell; 0 = occupied
    ivec3 oi = clamp(ivec3(floor((c + 1.0) * {0.5 * res!r})), ivec3(0), ivec3({res - 1}));
    uint cell = uint((oi.x * {res} + oi.y) * {res} + oi.z);
    dist = (occ_bits[cell >> 2u] >> ((cell & 3u) << 3u)) & 255u;
    keep = dist == 0u;
}}"""
            # a step moves a point by at most res / N cells along each axis (the box clip bounds the ray to the
            # cube): the next floor((dist - 2) N / res) samples lie in cells closer than dist - 1, all empty
            # (one cell of margin for rounding); they are the samples the test would reject, skipped
            per_cell = float(render["num_samples"]) / float(res)
            advance = f"            jump = dist >= 2u ? int(float(dist - 2u) * {per_cell!r}) + 1 : 1;"
        else:
            occupancy = f"""if (keep) {{  // occupancy grid [ix, iy, iz], bit-packed
    ivec3 oi = clamp(ivec3(floor((c + 1.0) * {0.5 * res!r})), ivec3(0), ivec3({res - 1}));
    uint bit = uint((oi.x * {res} + oi.y) * {res} + oi.z);
    keep = (occ_bits[bit >> 5u] & (1u << (bit & 31u))) != 0u;
}}"""
    locate = "\n".join(sample_t.splitlines() + ["precise vec3 p = origin + t * d;"] + contract.splitlines()
                        + ["bool keep = delta > 0.0 && all(lessThanEqual(abs(c), vec3(1.0)));"]
                        + occupancy.splitlines())
    locate = "\n".join("            " + line.strip() for line in locate.splitlines())
    return {"bounds": bounds, "spacing_setup": spacing_setup, "locate": locate, "advance": advance}


def skips_by_distance(assets) -> bool:
    """Whether the march skips runs of empty samples by each empty cell's distance to the nearest occupied one
    (bounded scenes with linear spacing, where a step's length along each axis is bounded; elsewhere each
    sample tests its cell's bit)."""
    return (assets.occupancy is not None and bool(assets.bounded)
            and assets.manifest["render"]["spacing"] == "linear")


def empty_distance(occupancy: np.ndarray, cap: int = 255) -> np.ndarray:
    """(R, R, R) bool occupancy -> (R, R, R) uint8: each cell's Chebyshev distance in cells to the nearest occupied
    cell (0 on occupied cells), capped at ``cap`` (also where nothing is occupied)."""
    occ = np.asarray(occupancy, dtype=bool)
    if occ.ndim != 3:
        raise InputError(f"must be a 3D grid, got shape {occ.shape}", field="occupancy")
    dist = np.full(occ.shape, cap, np.uint8)
    reached = occ.copy()
    dist[reached] = 0
    for k in range(1, cap):
        if reached.all() or not reached.any():
            break
        grown = reached.copy()
        for axis in range(3):  # the 3x3x3 neighbourhood, one axis at a time
            near = grown.copy()
            lo = [slice(None)] * 3
            hi = [slice(None)] * 3
            lo[axis], hi[axis] = slice(1, None), slice(None, -1)
            near[tuple(lo)] |= grown[tuple(hi)]
            near[tuple(hi)] |= grown[tuple(lo)]
            grown = near
        dist[grown & ~reached] = k
        reached = grown
    return dist


def occupancy_words(assets) -> np.ndarray:
    """The occupancy storage buffer of ``assets`` as uint32 words: the empty-cell distances a byte per cell
    (little-endian, :func:`skips_by_distance`) or the occupancy a bit per cell; one zero word without a grid."""
    occ = assets.occupancy
    if occ is None:
        return np.zeros(1, np.uint32)
    if skips_by_distance(assets):
        flat = empty_distance(occ).reshape(-1)
        return np.pad(flat, (0, (-flat.size) % 4)).view("<u4").astype(np.uint32)
    flat = np.ascontiguousarray(occ, dtype=bool).reshape(-1)
    return np.packbits(np.pad(flat, (0, (-flat.size) % 32)), bitorder="little").view(np.uint32)


def color_head(params: ShaderParams, enc: list[str], colr, latent_dim: int, lat_rows: int
               ) -> tuple[list[str], Callable[..., tuple[list[str], str]]]:
    """The colour MLP of a field: GLSL run once per pixel (the encoding ``enc``, scalar expressions of ``dir``, and
    the first layer's columns that read it) and ``color_net(inputs, indent, activation)``, the code of the rest of
    the MLP on vec4 inputs (the latent, ``lat_rows`` rows) and the expression of its RGB output (``sigmoid`` or
    ``tanh``). The first layer's columns are the latent's ``latent_dim`` then the encoding's."""
    enc_rows = _pad_to(len(enc))
    enc_vecs = [f"e{q}" for q in range(enc_rows // 4)]
    per_pixel = []
    for q in range(enc_rows // 4):
        comps = [enc[4 * q + r] if 4 * q + r < len(enc) else "0.0" for r in range(4)]
        per_pixel.append(f"    vec4 e{q} = vec4({', '.join(comps)});")
    w0, b0 = colr[0]
    if w0.shape[1] != latent_dim + len(enc):
        raise InputError(f"colour MLP takes {w0.shape[1]} inputs, expected latent {latent_dim} + encoding {len(enc)}",
                         field="mlps")
    rows0 = _pad_to(w0.shape[0])
    we_off = params.add(pad_matrix(w0[:, latent_dim:], rows0, enc_rows)) if enc else None
    b0_off = params.add(np.pad(b0, (0, rows0 - b0.shape[0])))
    if enc:
        code, base_vecs = linear_code("cb", enc_vecs, we_off, rows0 // 4,
                                      [f"P[{b0_off + q}]" for q in range(rows0 // 4)], False)
        per_pixel += ["    " + line for line in code]
    else:
        base_vecs = [f"P[{b0_off + q}]" for q in range(rows0 // 4)]
    wh_off = params.add(pad_matrix(w0[:, :latent_dim], rows0, lat_rows))
    last_is_first = len(colr) == 1

    def color_net(inputs: list[str], indent: str, activation: str = "sigmoid") -> tuple[list[str], str]:
        code, xs = linear_code("c0_", inputs, wh_off, rows0 // 4, base_vecs, not last_is_first)
        lines = list(code)
        if not last_is_first:
            hidden, xs = mlp_hidden_code("ch", params, xs, colr[1:-1]) if len(colr) > 2 else ([], xs)
            lines += hidden
            w_l, b_l = colr[-1]
            out_off = params.add(pad_matrix(w_l, 4, 4 * len(xs)))
            b_off = params.add(np.pad(b_l, (0, 4 - b_l.shape[0])))
            code, xs = linear_code("co", xs, out_off, 1, [f"P[{b_off}]"], False)
            lines += code
        rgb = f"(1.0 / (1.0 + exp(-{xs[0]}.xyz)))" if activation == "sigmoid" else f"tanh({xs[0]}.xyz)"
        return [indent + line for line in lines], rgb

    return per_pixel, color_net


def generate_shader(assets: FieldAssets, planes: list[np.ndarray], ranges: Optional[list[np.ndarray]], *,
              filtering: str, color_mode: str, params_kind: str, extra_encoding: Sequence[str] = (),
              sample_code: Optional[Callable[["ShaderParams"], tuple[list[str], list[str], list[str]]]] = None,
              count_evaluations: bool = False) -> tuple[str, np.ndarray, list[dict], str]:
    """GLSL source, the packed parameter array, the plane-texture specs and where the weights live
    (``const``: literals in the source, ``ubo`` or ``ssbo``) of one field.

    Two hooks let ``engine/fields/gldynamic.py`` render a dynamic field with this shader: ``extra_encoding`` are
    scalar GLSL expressions appended to the view-direction encoding (further per-pixel inputs of the colour
    MLP's first layer: the encoded time); ``sample_code(params)`` returns GLSL declarations (samplers,
    uniforms), code run per evaluated sample before the plane lookup, which may move the contracted point
    ``c`` (a motion field: ``c = clamp(c + flow, -1, 1)``), and code run after it, which may change the
    features ``f<scale>_<group>`` (vec4s of channels 4 group .. 4 group + 3; K-Planes' time planes), its
    weights added to ``params``. ``count_evaluations`` writes each pixel's number of evaluated samples to a
    uint buffer at binding 4 (``out_count``)."""
    spec = assets.manifest["field"]
    params = ShaderParams()
    quantized = ranges is not None

    # tri-plane features: per scale and channel group, the product over the three planes
    samplers, feat_lines, feat_vecs, tex_specs = [], [], [], []
    col_map, base = [], 0
    for s, plane in enumerate(planes):
        _, c, r, _ = plane.shape
        g = -(-c // 4)
        samplers.append(f"uniform sampler2DArray planes{s};")
        tex_specs.append({"scale": s, "resolution": r, "channels": c, "groups": g})
        col_map += [base + ch for ch in range(c)]
        base += 4 * g
        rng_off = None
        if quantized:
            lo = np.zeros((3, 4 * g), np.float32)
            span = np.zeros((3, 4 * g), np.float32)
            lo[:, :c] = ranges[s][..., 0]
            span[:, :c] = ranges[s][..., 1] - ranges[s][..., 0]
            rng_off = params.add(np.stack([lo.reshape(3, g, 4), span.reshape(3, g, 4)], axis=2))  # (3, g, 2, 4)
        rm1 = float(r - 1)
        for k, (a, b) in enumerate(PLANE_AXES):
            ca, cb = "xyz"[a], "xyz"[b]
            feat_lines.append(f"        {{ // scale {s}, plane {k} ({ca}{cb})")
            feat_lines.append(f"            float x = clamp((c.{ca} + 1.0) * 0.5 * {rm1!r}, 0.0, {rm1!r});")
            feat_lines.append(f"            float y = clamp((c.{cb} + 1.0) * 0.5 * {rm1!r}, 0.0, {rm1!r});")
            if filtering == "exact":
                last = float(r - 2)
                feat_lines.append(f"            float x0 = min(floor(x), {last!r}), y0 = min(floor(y), {last!r});")
                feat_lines.append("            float fx = x - x0, fy = y - y0;")
                feat_lines.append("            ivec2 i0 = ivec2(int(x0), int(y0));")
            else:
                feat_lines.append(f"            vec2 uv = (vec2(x, y) + 0.5) * {1.0 / r!r};")
            for gi in range(g):
                layer = k * g + gi
                if filtering == "exact":
                    fetch = [f"texelFetch(planes{s}, ivec3(i0 + ivec2({dx}, {dy}), {layer}), 0)"
                             for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1))]
                    val = (f"({fetch[0]} * (1.0 - fx) + {fetch[1]} * fx) * (1.0 - fy) + "
                           f"({fetch[2]} * (1.0 - fx) + {fetch[3]} * fx) * fy")
                else:
                    val = f"texture(planes{s}, vec3(uv, {float(layer)!r}))"
                if quantized:
                    lo_ref = f"P[{rng_off + (k * g + gi) * 2}]"
                    span_ref = f"P[{rng_off + (k * g + gi) * 2 + 1}]"
                    val = f"{lo_ref} + ({val}) * {span_ref}"
                name = f"f{s}_{gi}"
                if k == 0:
                    feat_lines.append(f"            {name} = {val};")
                else:
                    feat_lines.append(f"            {name} *= {val};")
            feat_lines.append("        }")
        feat_vecs += [f"f{s}_{gi}" for gi in range(g)]
    feat_decl = "        vec4 " + ", ".join(feat_vecs) + ";"
    features = feat_decl + "\n" + "\n".join(feat_lines)
    if sample_code is not None:  # a dynamic field's motion field or time planes
        declarations, before, after = sample_code(params)
        samplers += declarations
        indent = "        "
        features = "\n".join([indent + line for line in before] + [features] + [indent + line for line in after])

    # density MLP: hidden layers, then the raw density row; the latent rows only where needed
    dens = assets.density_layers
    hidden_code, hid = mlp_hidden_code("dh", params, feat_vecs, dens[:-1], np.asarray(col_map))
    w_last, b_last = dens[-1]
    first_cols = np.asarray(col_map) if len(dens) == 1 else None
    in_cols = 4 * len(hid)
    raw_off = params.add(pad_matrix(w_last[:1], 1, in_cols, first_cols).reshape(-1))
    latent_dim = w_last.shape[0] - 1
    lat_rows = _pad_to(latent_dim)
    lat_w = params.add(pad_matrix(w_last[1:], lat_rows, in_cols, first_cols))
    lat_b = params.add(np.pad(b_last[1:], (0, lat_rows - latent_dim)))
    bias_vec = params.add(np.array([b_last[0], 0, 0, 0], np.float32))
    raw_terms = " + ".join(f"dot(P[{raw_off + kk}], {hid[kk]})" for kk in range(len(hid)))
    density = "\n".join("        " + line for line in hidden_code)
    density += f"\n        float raw = {raw_terms} + P[{bias_vec}].x;"
    lat_code, lat_vecs = linear_code("h", hid, lat_w, lat_rows // 4, [f"P[{lat_b + q}]" for q in range(lat_rows // 4)],
                                 False)

    # colour MLP: the direction columns of its first layer once per pixel, the rest per sample
    enc = _direction_encoding(spec["direction_encoding"], int(spec["direction_degree"])) + list(extra_encoding)
    per_pixel, color_net = color_head(params, enc, assets.color_layers, latent_dim, lat_rows)

    latent = "\n".join("            " + line for line in lat_code)
    deferred = spec.get("shading", "per-sample") == "deferred"
    if deferred and color_mode != "per-sample":
        raise InputError(f"a deferred field renders its own way: {color_mode!r} is for per-sample fields",
                         field="color_mode")
    if deferred:  # features sigmoid(h) composited; the colour MLP once per pixel (exact: trained this way)
        accum_decl = "\n".join(f"    vec4 ha{q} = vec4(0.0);" for q in range(lat_rows // 4))
        color_sample = "\n".join(f"            ha{q} += w / (1.0 + exp(-{v}));" for q, v in enumerate(lat_vecs))
        code, residual = color_net([f"ha{q}" for q in range(lat_rows // 4)], "    ", "tanh")
        color_final = "\n".join(code) + f"\n    col = ha0.xyz + acc * {residual};  // + (1 - acc) background below"
    elif color_mode == "per-sample":
        code, rgb = color_net(lat_vecs, "            ")
        color_sample = "\n".join(code) + f"\n            col += w * {rgb};"
        accum_decl, color_final = "", ""
    else:  # "latent": the colour MLP once per pixel on the weight-averaged latent (an approximation)
        accum_decl = "\n".join(f"    vec4 ha{q} = vec4(0.0);" for q in range(lat_rows // 4)) + "\n    float wl = 0.0;"
        color_sample = "\n".join(f"            ha{q} += w * {v};" for q, v in enumerate(lat_vecs))
        color_sample += "\n            wl += w;"
        code, rgb = color_net([f"(ha{q} / wl)" for q in range(lat_rows // 4)], "        ")
        color_final = "    if (wl > 0.0) {\n" + "\n".join(code) + f"\n        col += wl * {rgb};\n    }}"

    features = "\n".join("    " + line for line in features.splitlines())
    density = "\n".join("    " + line for line in density.splitlines())
    source, packed, kind = finish_shader(assets, params, params_kind, {
        "samplers": "\n".join(samplers), "per_pixel": "\n".join(per_pixel), "accum_decl": accum_decl,
        "features": features, "density": density, "density_bias": float(spec["density_bias"]),
        "max_log": float(spec["max_log_density"]), "latent": latent, "color_sample": color_sample,
        "color_final": color_final}, count_evaluations)
    return source, packed, tex_specs, kind


def finish_shader(assets, params: ShaderParams, params_kind: str, values: dict, count_evaluations: bool = False
                  ) -> tuple[str, np.ndarray, str]:
    """The template filled with ``values`` (the field's per-sample code: ``samplers``, ``per_pixel``,
    ``accum_decl``, ``features``, ``density``, ``density_bias``, ``max_log``, ``latent``, ``color_sample``,
    ``color_final``) and the scene's ray setup and sampling (:func:`march_code`): GLSL source, the packed
    parameters and where they live (``const``: literals in the source, ``ubo`` or ``ssbo``)."""
    packed = params.array()
    if params_kind == "const":
        params_decl = ""
        kind = "const"
    elif params_kind == "ubo" and packed.nbytes <= _UBO_LIMIT:
        params_decl = f"layout(std140, binding = 0) uniform Params {{ vec4 P[{packed.shape[0]}]; }};"
        kind = "ubo"
    else:
        params_decl = "layout(std430, binding = 0) readonly buffer Params { vec4 P[]; };"
        kind = "ssbo"
    source = _TEMPLATE % {
        "params_decl": params_decl, "num_samples": int(assets.manifest["render"]["num_samples"]),
        **march_code(assets), **values, "opacity_eps": float(OPACITY_EPS), "camera_glsl": CAMERA_GLSL,
        "contract_glsl": contract_glsl(assets.bounded),
        "count_decl": ("layout(std430, binding = 4) writeonly buffer CountBuf { uint out_count[]; };"
                       if count_evaluations else ""),
        "count_write": "    out_count[o] = evaluated;" if count_evaluations else "",
    }
    if kind == "const":
        source = inline_params(source, packed)
    return source, packed, kind


def inline_params(source: str, packed: np.ndarray) -> str:
    """``source`` with every ``P[i]`` replaced by the literal ``vec4`` of row i of ``packed`` (the weights as
    literals in the code; float32 round-trips through 9 significant digits)."""
    return re.sub(r"P\[(\d+)\]", lambda m: "vec4(%s)" % ", ".join("%.9g" % v for v in packed[int(m.group(1))]),
                  source)


# ----------------------------------------------------------------------------------------------------
# The renderer


def _uint8_planes(assets: FieldAssets) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The uint8 plane codes (3, C, R, R) and ranges (3, C, 2) of each scale, from the assets' ``field.npz``."""
    npz = assets.onnx_path.parent / "field.npz"
    if not npz.is_file():
        raise InputError("file does not exist (quantized=True reads the uint8 planes from it)", file=npz)
    codes, ranges = [], []
    with np.load(npz) as data:
        for p in assets.manifest["field"]["planes"]:
            if p["uint8"] not in data.files or p["range"] not in data.files:
                raise InputError(f"lacks the uint8 planes {p['uint8']!r} / {p['range']!r}", file=npz)
            c, r = data[p["uint8"]], data[p["range"]].astype(np.float32)
            if c.dtype != np.uint8 or c.shape != (3, p["channels"], p["resolution"], p["resolution"]) \
                    or r.shape != (3, p["channels"], 2):
                raise InputError(f"uint8 plane {p['uint8']!r} has shape {c.shape} / {c.dtype}, range {r.shape}",
                                 file=npz)
            codes.append(c)
            ranges.append(r)
    return codes, ranges


def texture_layers(plane: np.ndarray, groups: int) -> np.ndarray:
    """(3, C, H, W) -> (3 * G, H, W, 4): layer k * G + g holds channels 4g .. 4g + 3 of plane k (zero padded)."""
    three, c, h, w = plane.shape
    padded = np.zeros((three, 4 * groups, h, w), plane.dtype)
    padded[:, :c] = plane
    return np.ascontiguousarray(padded.reshape(three, groups, 4, h, w).transpose(0, 1, 3, 4, 2).reshape(-1, h, w, 4))


def _check_tiles(tiles) -> Optional[int]:
    if tiles is None:
        return None
    if isinstance(tiles, bool) or not isinstance(tiles, (int, np.integer)) or not 1 <= tiles <= 64:
        raise InputError(f"must be None or an integer in [1, 64], got {tiles!r}", field="tiles_per_invocation")
    return int(tiles)


def check_options(width, height, *, filtering: str, color_mode: str, weights: str, transmittance_eps: float,
                   color_eps: float) -> None:
    """InputError naming the first bad renderer option."""
    if not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) and 1 <= v <= 16384
               for v in (width, height)):
        raise InputError(f"must be integers in [1, 16384], got {width!r} x {height!r}", field="size")
    if filtering not in ("exact", "hardware"):
        raise InputError(f"must be exact or hardware, got {filtering!r}", field="filtering")
    if color_mode not in ("per-sample", "latent"):
        raise InputError(f"must be per-sample or latent, got {color_mode!r}", field="color_mode")
    if weights not in ("inline", "buffer"):
        raise InputError(f"must be inline or buffer, got {weights!r}", field="weights")
    for name, value in (("transmittance_eps", transmittance_eps), ("color_eps", color_eps)):
        if not (math.isfinite(value) and 0.0 <= value < 1.0):
            raise InputError(f"must be in [0, 1), got {value}", field=name)


class GlFieldRenderer:
    """One headless GL context with the compute shader, textures and buffers of one exported field.

    Args:
        assets: :func:`engine.fields.render.load_field`'s result, or the export folder.
        width, height: the output size in pixels (fixed for the renderer: buffers are allocated once).
        quantized: sample the uint8 planes (with their per-plane, per-channel ranges) instead of float32.
        filtering: ``exact`` (four ``texelFetch`` + float32 bilinear, as the reference) or ``hardware``
            (the texture unit's bilinear filter).
        transmittance_eps: early ray termination once the transmittance is below this (0: never).
        color_eps: samples with weight at most this skip the colour MLP and count as background colour
            (0: every sample with a non-zero weight is coloured).
        color_mode: ``per-sample`` (exact) or ``latent`` (the colour MLP once per pixel on the weight-averaged
            latent vector: an approximation, since the MLP is not linear in the latent; see the bench). A
            deferred field is rendered exactly with ``per-sample`` and refuses ``latent``.
        tiles_per_invocation: 8x8 pixel tiles each shader invocation shades, stacked along y (``None``:
            ``SOFTWARE_TILES`` on llvmpipe, where it amortises a per-call prologue, 1 on a GPU). The frame is
            the same for any value.
        count_evaluations: also count the field evaluations of every pixel (``render`` returns them as
            ``evaluations``; what :func:`engine.fields.render.evaluated_samples` counts on the reference): a
            profiling aid, one more buffer written.
        context: ``None`` (default): a context of its own. A ``engine.geometry.backends.gl.GlContext`` (e.g.
            ``shared_context()``): render on the frame backend's context, so that ``render_to_buffer`` hands
            a frame to ``GlFrameWarper.from_rgbd`` without a readback.

    Raises:
        InputError: bad size or option, assets the shader cannot map (plane resolution below 2).
    """

    count_evaluations = False
    tiles_per_invocation: Optional[int] = None

    def __init__(self, assets: Union[FieldAssets, str, Path], width: int, height: int, *, quantized: bool = False,
                 filtering: str = "hardware", transmittance_eps: float = TRANSMITTANCE_EPS,
                 color_eps: float = COLOR_EPS, color_mode: str = "per-sample", weights: str = "inline",
                 tiles_per_invocation: Optional[int] = None, count_evaluations: bool = False,
                 context=None) -> None:
        if not isinstance(assets, FieldAssets):
            assets = load_field(assets)
        check_options(width, height, filtering=filtering, color_mode=color_mode, weights=weights,
                       transmittance_eps=transmittance_eps, color_eps=color_eps)
        for p in assets.planes:
            if p.shape[-1] < 2:
                raise InputError(f"plane resolution {p.shape[-1]} < 2 cannot be interpolated", field="planes")
        self._configure(assets, width, height, quantized=quantized, filtering=filtering, color_mode=color_mode,
                        transmittance_eps=transmittance_eps, color_eps=color_eps,
                        tiles_per_invocation=tiles_per_invocation, count_evaluations=count_evaluations)
        if quantized:
            planes, ranges = _uint8_planes(assets)
        else:
            planes, ranges = assets.planes, None
        self.source, packed, tex_specs, self.params_kind = generate_shader(
            assets, planes, ranges, filtering=filtering, color_mode=color_mode,
            params_kind="const" if weights == "inline" else "ubo", count_evaluations=self.count_evaluations)
        self._setup(packed, [(f"planes{spec['scale']}", texture_layers(plane, spec["groups"]))
                             for spec, plane in zip(tex_specs, planes)], "f1" if quantized else "f4", context)

    def _configure(self, assets, width: int, height: int, *, quantized: bool, filtering: str, color_mode: str,
                   transmittance_eps: float, color_eps: float, tiles_per_invocation: Optional[int],
                   count_evaluations: bool) -> None:
        """Record the (checked) options; ``tiles_per_invocation`` is checked here."""
        self.assets = assets
        self.width, self.height = int(width), int(height)
        self.quantized = bool(quantized)
        self.filtering = filtering
        self.color_mode = color_mode
        self.transmittance_eps = float(transmittance_eps)
        self.color_eps = float(color_eps)
        self.count_evaluations = bool(count_evaluations)
        self.tiles_per_invocation = _check_tiles(tiles_per_invocation)

    def _setup(self, packed: np.ndarray, textures: list[tuple[str, np.ndarray]], dtype: str, context=None) -> None:
        """Create the context (or take ``context``'s), compile ``self.source`` and upload the parameters, the
        occupancy grid and the plane textures: ``(sampler name, (layers, H, W, 4) array)``, bound to units 0,
        1, ... in that order (``dtype`` ``f4``: RGBA32F; ``f1``: normalised RGBA8)."""
        import moderngl

        self._lock = threading.Lock()
        self._gl = context
        if context is None:
            self.ctx = moderngl.create_standalone_context(backend="egl", require=REQUIRED_GL)
        else:
            if not hasattr(context, "call") or not hasattr(context, "ctx"):
                raise InputError(f"must be a GlContext, got {type(context).__name__}", field="context")
            self.ctx = context.ctx
        self._textures, self._buffers = [], []
        self._run(lambda: self._build(packed, textures, dtype))

    def _run(self, fn):
        """``fn()`` with this renderer's context current: on the shared context's thread, or under the lock."""
        if self._gl is not None:
            return self._gl.call(fn)
        with self._lock, self.ctx:  # make this context current (another module's GL context may be)
            return fn()

    def _build(self, packed: np.ndarray, textures: list, dtype: str) -> None:
        if self.tiles_per_invocation is None:
            from engine.geometry.backends.gl.context import is_software_renderer

            software = is_software_renderer(str(self.ctx.info.get("GL_RENDERER", "")))
            self.tiles_per_invocation = SOFTWARE_TILES if software else 1
        version, rest = self.source.lstrip("\n").split("\n", 1)  # the #version line must stay first
        start = time.perf_counter()
        self.program = self.ctx.compute_shader(f"{version}\n#define TILES {self.tiles_per_invocation}\n{rest}")
        self.compile_seconds = time.perf_counter() - start
        for name, layers in textures:
            self._add_texture(name, self.ctx.texture_array((layers.shape[2], layers.shape[1], layers.shape[0]), 4,
                                                           layers.tobytes(), dtype=dtype))
        self._params = self.ctx.buffer(packed.tobytes())
        self._occ = self.ctx.buffer(occupancy_words(self.assets).tobytes())
        n = self.width * self.height
        self._rgbd = self.ctx.buffer(reserve=16 * n)
        self._opacity = self.ctx.buffer(reserve=4 * n)
        self._buffers += [self._params, self._occ, self._rgbd, self._opacity]
        self._count = None
        if self.count_evaluations:
            self._count = self.ctx.buffer(reserve=4 * n)
            self._buffers.append(self._count)
        self._set_static_uniforms()

    def _add_texture(self, name: str, texture) -> None:
        """Bind ``texture`` (2D array or 3D, filtered by ``filtering``, clamped at its edges) to the shader's sampler
        ``name`` on the next unit (``_bind`` binds it again before each dispatch)."""
        import moderngl

        linear = moderngl.LINEAR if self.filtering == "hardware" else moderngl.NEAREST
        texture.filter = (linear, linear)
        texture.repeat_x = texture.repeat_y = False
        if hasattr(texture, "repeat_z"):
            texture.repeat_z = False
        unit = len(self._textures)
        texture.use(location=unit)
        self._set(name, unit)
        self._textures.append(texture)

    def _set(self, name: str, value) -> None:
        set_uniforms(self.program, {name: value})

    def _set_static_uniforms(self) -> None:
        scene = self.assets.scene
        set_uniforms(self.program, {
            **scene_uniforms(self.assets, self.width, self.height), "near": float(np.float32(scene["near"])),
            "far": float(np.float32(scene["far"])), "background": tuple(float(x) for x in self.assets.background),
            "transmittance_eps": self.transmittance_eps, "color_eps": self.color_eps})

    def render(self, intrinsics, world_to_camera) -> dict[str, np.ndarray]:
        """Render the field from a camera (OpenCV axes, rigid world-to-camera, pixel centres at +0.5).

        Returns:
            ``color`` (H, W, 3) float32 linear RGB, ``depth`` (H, W) float32 planar (+inf where the opacity
            is below ``OPACITY_EPS``), ``opacity`` (H, W) float32, ``seconds`` (wall time of the dispatch
            and read-back); with ``count_evaluations``, ``evaluations`` (H, W) uint32.

        Raises:
            InputError: intrinsics not a finite pinhole K with positive focal lengths; pose not rigid.
        """
        dispatch = self._dispatcher(intrinsics, world_to_camera)

        def run():
            start = time.perf_counter()
            dispatch()
            n = self.width * self.height
            rgbd = np.frombuffer(self._rgbd.read(size=16 * n), np.float32).reshape(self.height, self.width, 4)
            opacity = np.frombuffer(self._opacity.read(size=4 * n), np.float32).reshape(self.height, self.width)
            seconds = time.perf_counter() - start
            count = None
            if self._count is not None:
                count = np.frombuffer(self._count.read(size=4 * n), np.uint32).reshape(self.height, self.width)
            return rgbd, opacity, seconds, count

        rgbd, opacity, seconds, count = self._run(run)
        out = {"color": rgbd[..., :3].copy(), "depth": rgbd[..., 3].copy(), "opacity": opacity.copy(),
               "seconds": seconds}
        if count is not None:
            out["evaluations"] = count.copy()
        return out

    def dispatch_seconds(self, intrinsics, world_to_camera, frames: int = 1) -> list[float]:
        """Wall seconds of ``frames`` renders from this camera, one after another, each from its dispatch to
        ``ctx.finish()`` with nothing read back: the renderer's own time, for benchmarks. The frames go to this
        renderer's buffers; uniforms that only :meth:`render` sets (a dynamic field's time) keep the last render's.

        Raises:
            InputError: ``frames`` not an integer >= 1; bad intrinsics or pose.
        """
        frames = check_range(frames, "frames", low=1, integer=True)
        dispatch = self._dispatcher(intrinsics, world_to_camera)

        def timed() -> list[float]:
            seconds = []
            for _ in range(frames):
                start = time.perf_counter()
                dispatch()
                self.ctx.finish()
                seconds.append(time.perf_counter() - start)
            return seconds
        return self._run(timed)

    def render_to_buffer(self, intrinsics, world_to_camera):
        """``render`` with nothing read back, on a renderer made with ``context``: returns this renderer's
        buffer of (H, W, 4) float32 (r, g, b linear, planar depth with +inf where the opacity is below
        ``OPACITY_EPS``) per pixel, rows top to bottom, valid until the next render. The frame backend takes
        it as a frame with ``GlFrameWarper.from_rgbd(buffer, (H, W))`` (a GPU-side copy).

        Raises:
            InputError: a renderer with a context of its own; bad intrinsics or pose.
        """
        if self._gl is None:
            raise InputError("renders to a buffer only on a shared context: make the renderer with context=",
                             field="context")
        self._run(self._dispatcher(intrinsics, world_to_camera))
        return self._rgbd

    def _dispatcher(self, intrinsics, world_to_camera):
        """The checked camera's dispatch, to run with the context current (``_run``)."""
        camera = camera_uniforms(intrinsics, world_to_camera)

        def dispatch() -> None:
            set_uniforms(self.program, camera)
            self._bind()
            tile_rows = -(-self.height // _TILE)
            gx, gy = -(-self.width // _TILE), -(-tile_rows // self.tiles_per_invocation)
            self.program.run(gx, gy, 1)
            self.ctx.memory_barrier()
        return dispatch

    def _bind(self) -> None:
        for spec_unit, tex in enumerate(self._textures):
            tex.use(location=spec_unit)
        if self.params_kind == "ubo":
            self._params.bind_to_uniform_block(0)
        elif self.params_kind == "ssbo":
            self._params.bind_to_storage_buffer(0)
        self._occ.bind_to_storage_buffer(1)
        self._rgbd.bind_to_storage_buffer(2)
        self._opacity.bind_to_storage_buffer(3)
        if self._count is not None:
            self._count.bind_to_storage_buffer(4)

    def release(self) -> None:
        """Free the GL objects and the context unless it is a shared one (the renderer is unusable afterwards)."""
        if self.ctx is None:
            return

        def free() -> None:
            for obj in self._textures + self._buffers + [self.program]:
                obj.release()
        self._run(free)
        if self._gl is None:
            self.ctx.release()
        self.ctx = None

    def __enter__(self) -> "GlFieldRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.release()
