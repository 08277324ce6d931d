"""Render an exported dynamic radiance field without torch: the numpy reference renderer of its assets.

Reads what ``interleave export dynamic`` writes (``dynamic.json`` + ``dynamic.npz`` + ``dynamic.onnx``; the
format is ``docs/field-assets.md``, "Dynamic fields") and renders colour and planar depth for any camera at
any time inside the trained range. The field is evaluated by the numpy code here (``query="numpy"``, the
oracle of the asset format and of the real-time shader ``engine/fields/gldynamic.py``) or by the exported ONNX
graph through onnxruntime (``query="onnx"``, the torch code that training ran).

Per sample (DeRF, thesis Ch. 5): the contracted point c and the normalised time tau give the motion
features (hex-planes xy, xz, yz, xt, yt, zt, Hadamard product per scale, scales concatenated), the flow MLP
gives ``flow = max_flow * tanh(.)`` (with motion slots, ``field.motion``: the slots' softmax-weighted affine
motions inside the tanh, :func:`slot_motion_np`), the canonical point ``c' = clamp(c + flow, -1, 1)`` is looked
up in the canonical tri-planes, the density MLP gives density and latent h, the colour MLP takes [h, encoded
view direction, encoded tau]. K-Planes-style exports (``kind="kplanes"``) have no motion model: the hex-plane
features of (c, tau) feed the density MLP and colour comes from [h, encoded view direction].

Conventions are the static renderer's (``engine/fields/render.py``, whose pure functions this module imports:
ray generation, sample placement, contraction, plane lookup, MLPs, compositing): OpenCV cameras, rigid
``world_to_camera``, pixel centres at +0.5, planar depth (+inf where the opacity is below ``OPACITY_EPS``),
linear RGB. Times are in the data's units (``time.range`` in the manifest); a time outside the trained range
(beyond a relative 1e-6, as ``models.fields.dynamic.model.normalize_times``) raises ``InputError``.

>>> field = load_dynamic_field("runs/dynamic/lego-derf/export")                    # doctest: +SKIP
>>> out = render_dynamic_field(field, K, world_to_camera, 540, 960, time=0.5)      # doctest: +SKIP
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple, Optional

import numpy as np

from engine.core.errors import InputError
from engine.core.frames import validate_intrinsics, validate_pose
from engine.fields.render import (PLANE_AXES, ExportedAssets, array_getter, bilinear_np, camera_rays_np,
                                  contract_np, decode_plane, direction_encoding_np, load_mlp, load_occupancy,
                                  march_field, mlp_np, pixel_shader, read_asset_files, sigmoid_np,
                                  uncontract_np)
from engine.fields.manifest import check_shading, check_time_range, section
from engine.geometry.motion import drop_long_vectors, projected_offsets

__all__ = ["DYNAMIC_FORMAT", "DYNAMIC_VERSION", "TIME_TOLERANCE", "SLOT_KEY_SIZE", "MotionSlots", "DynamicAssets",
           "load_dynamic_field", "normalize_time", "time_encoding_np", "triplane_features_np", "hex_plane_features_np",
           "slot_motion_np", "deform_np",
           "query_dynamic", "render_dynamic_field", "MOTION_ITERATIONS", "NEWTON_SETTLED", "JACOBIAN_STEP",
           "MIN_JACOBIAN_DET", "MAX_NEWTON_STEP", "MOTION_TOLERANCE",
           "earlier_points", "COHERENCE", "check_coherence", "time_before", "coherent_motion", "field_motion_vectors",
           "field_object_flow"]

DYNAMIC_FORMAT = "interleave-dynamic-field"
DYNAMIC_VERSION = 1
#: A time may exceed the trained range by this fraction of the range (at least 1e-6 absolute) before it is
#: refused; the same as ``models.fields.dynamic.model.TIME_TOLERANCE``.
TIME_TOLERANCE = 1e-6

#: Most Newton steps that invert the motion field (``earlier_points``), after one fixed-point step. A fixed-point
#: iteration multiplies the error by the flow's Lipschitz constant and diverges where that exceeds 1: at a moving
#: object's border a trained field's flow to the canonical time does (8 fixed-point steps left 6-16 % of lego's
#: moving pixels without an earlier point; ``docs/results/2026-12-01-field-vectors-newton.md``).
MOTION_ITERATIONS = 8
#: A point stops its Newton steps once its residual |c' + flow(c', tau') - C| (max over axes) is at most this.
NEWTON_SETTLED = 1e-5
#: The finite-difference step (contracted units) of the flow's Jacobian in those Newton steps.
JACOBIAN_STEP = 1e-3
#: Below this |det(I + d flow / dc)| (the motion field folds) a Newton step is a fixed-point step instead.
MIN_JACOBIAN_DET = 1e-3
#: Longest Newton step (contracted units): a step across a fold stays near the point it left.
MAX_NEWTON_STEP = 0.25
#: Largest residual |c' + flow(c', tau') - C| (contracted units) of an earlier point that counts as found.
MOTION_TOLERANCE = 1e-3
#: ``field_motion_vectors(coherence=...)`` of the renderers that feed ``mvec``: a point keeps its object motion
#: where its motion over the interval before, continued, misses the last interval's by at most this fraction of
#: it (measured of 0.5, 0.75 and 1 on three trained fields at k = 2: 0.75 is ahead of 0.5 on all three, and 1
#: keeps too much of a jittering field's motion; ``docs/results/2026-11-28-dynamic-vectors-fix.md``).
COHERENCE = 0.75

#: Plane groups and MLPs each kind of export holds (and the groups it may hold: a DeRF export whose canonical
#: field has time planes, ``field_config.canonical_time``); ``derf-slots``: a DeRF export with motion slots
#: (``field.motion.model == "slots"``), whose motion is the slots' logit planes and key table, no flow MLP.
_GROUPS = {"derf": ("canonical_spatial", "motion_spatial", "motion_temporal"),
           "derf-slots": ("canonical_spatial", "motion_slot_logits"), "kplanes": ("spatial", "temporal")}
_OPTIONAL_GROUPS = {"derf": ("canonical_temporal",), "derf-slots": ("canonical_temporal",), "kplanes": ()}
_MLPS = {"derf": ("density", "color", "flow"), "derf-slots": ("density", "color"), "kplanes": ("density", "color")}
#: Values per slot and time key of the slots' key table: dA (3 x 3, row-major), then T (3).
SLOT_KEY_SIZE = 12


class MotionSlots(NamedTuple):
    """A DeRF export's motion slots (``field.motion`` in the manifest; ``docs/field-assets.md``).

    Attributes:
        logits: (3, K + 1, R, R) logit planes xy, xz, yz; channel 0 is the still slot.
        still_bias: (K + 1,) added to the summed logits.
        keys: (Rt, K, 12) per time key (tau = -1 + 2 i / (Rt - 1)) and moving slot: dA row-major (9), then T (3).
    """

    logits: np.ndarray
    still_bias: np.ndarray
    keys: np.ndarray


@dataclass(eq=False)
class DynamicAssets(ExportedAssets):
    """An exported dynamic field in memory (see ``docs/field-assets.md``, "Dynamic fields").

    Attributes:
        manifest: ``dynamic.json``.
        planes: plane groups by name, one array per scale: ``canonical_spatial`` (3, C, R, R) xy, xz, yz;
            ``motion_spatial`` (3, Cm, Rm, Rm); ``motion_temporal`` (3, Cm, Rt, Rm) xt, yt, zt (DeRF), or
            ``spatial`` / ``temporal`` (K-Planes); a DeRF export may add ``canonical_temporal`` (3, C, Rt, R),
            the canonical field's time planes (its features are then hex-planes read at the canonical point).
            float32, dequantized when loaded with ``quantized``.
        mlps: ``density``, ``color`` (and ``flow`` for DeRF): ``(weight (out, in), bias (out,))`` per layer.
        occupancy: (R, R, R) bool over the contracted cube indexed [ix, iy, iz] (time-agnostic), or None.
        onnx_path: the exported query graph.
        slots: a DeRF export with motion slots: its :class:`MotionSlots` (the logit planes are also the plane
            group ``motion_slot_logits``), and no ``motion_spatial`` / ``motion_temporal`` planes nor ``flow``
            MLP; None otherwise.

    The attributes the static shader generator reads (``manifest``, ``density_layers``, ``color_layers``,
    ``occupancy``, ``bounded``, ``scene``, ``background``) mean what they mean for
    :class:`engine.fields.render.FieldAssets`; ``density_layers`` and ``color_layers`` are the canonical field's.
    """

    manifest: dict
    planes: dict[str, list[np.ndarray]] = field(repr=False)
    mlps: dict[str, list[tuple[np.ndarray, np.ndarray]]] = field(repr=False)
    occupancy: Optional[np.ndarray] = field(repr=False)
    onnx_path: Path
    _session: object = field(default=None, repr=False)
    slots: Optional[MotionSlots] = field(default=None, repr=False)

    @property
    def kind(self) -> str:
        return self.manifest["kind"]

    @property
    def has_motion(self) -> bool:
        return self.kind == "derf"

    @property
    def time_range(self) -> tuple[float, float]:
        t0, t1 = self.manifest["time"]["range"]
        return float(t0), float(t1)

    @property
    def max_flow(self) -> float:
        """The flow bound (contracted units): ``flow = max_flow * tanh(flow MLP output)``."""
        spec = self.manifest["field"]
        if "max_flow" in spec:
            return float(spec["max_flow"])
        return float(self.manifest["field_config"]["motion"]["max_flow"])  # exports made before the key

    @property
    def canonical_planes(self) -> list[np.ndarray]:
        """The spatial planes the density MLP's features come from (``canonical_spatial`` or ``spatial``)."""
        return self.planes["canonical_spatial" if self.has_motion else "spatial"]

    @property
    def density_layers(self) -> list[tuple[np.ndarray, np.ndarray]]:
        return self.mlps["density"]

    @property
    def color_layers(self) -> list[tuple[np.ndarray, np.ndarray]]:
        return self.mlps["color"]

    @property
    def flow_layers(self) -> list[tuple[np.ndarray, np.ndarray]]:
        return self.mlps["flow"]

    @property
    def canonical_temporal(self) -> Optional[list[np.ndarray]]:
        """A DeRF canonical field's time planes (``canonical_time``), or None (tri-planes only)."""
        return self.planes.get("canonical_temporal")



def load_dynamic_field(path: str | Path, *, quantized: bool = False) -> DynamicAssets:
    """Load exported dynamic assets from a folder (or its ``dynamic.json``); ``quantized`` uses the uint8 planes.

    Raises:
        InputError: missing files, another format or version, an unknown kind, a bad time range, arrays whose
            shapes disagree with the manifest or with each other.
    """
    root, manifest, arrays = read_asset_files(path, "dynamic", DYNAMIC_FORMAT, DYNAMIC_VERSION,
                                              "interleave export dynamic RUN_DIR")
    meta_file, npz_file = root / "dynamic.json", root / "dynamic.npz"
    kind = manifest.get("kind")
    if kind not in ("derf", "kplanes"):
        raise InputError(f"has kind {kind!r}, expected one of ['derf', 'kplanes']", file=meta_file)
    check_time_range(manifest, meta_file)
    spec = section(manifest, "field", meta_file)
    check_shading(spec, meta_file)
    if kind == "derf" and "motion" in spec:
        model = section(spec, "motion", meta_file, "field").get("model")
        if model != "slots":
            raise InputError(f"field.motion.model is {model!r}, expected 'slots'", file=meta_file)
        kind = "derf-slots"  # the groups and MLPs of a DeRF export with motion slots
    get = array_getter(arrays, npz_file, "dynamic.json")
    planes: dict[str, list[np.ndarray]] = {}
    listed = manifest["field"]["planes"]
    for group in _GROUPS[kind] + tuple(g for g in _OPTIONAL_GROUPS[kind] if g in listed):
        if group not in listed:
            raise InputError(f"lists no plane group {group!r} (a {kind} export has {_GROUPS[kind]})", file=meta_file)
        planes[group] = []
        for p in manifest["field"]["planes"][group]:
            plane = decode_plane(p, get, group, quantized)
            if list(plane.shape) != list(p["shape"]) or plane.ndim != 4 or plane.shape[0] != 3 \
                    or min(plane.shape[2:]) < 2:
                raise InputError(f"plane {p['float']} has shape {plane.shape}, dynamic.json says {p['shape']} "
                                 "(3 planes, C channels, both sides >= 2)", file=npz_file)
            planes[group].append(plane)
    rows = int(manifest["time"]["time_resolution"])
    pairs = {"derf": [("motion_spatial", "motion_temporal")], "derf-slots": [],
             "kplanes": [("spatial", "temporal")]}[kind]
    if "canonical_temporal" in planes:
        pairs.append(("canonical_spatial", "canonical_temporal"))
    for spatial, temporal in pairs:
        if len(planes[spatial]) != len(planes[temporal]) or any(
                s.shape[:2] != t.shape[:2] or t.shape[3] != s.shape[3] or t.shape[2] != rows
                for s, t in zip(planes[spatial], planes[temporal])):
            raise InputError(f"{temporal} planes {[t.shape for t in planes[temporal]]} do not match {spatial} "
                             f"{[s.shape for s in planes[spatial]]} with {rows} time rows", file=npz_file)
    mlps: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    for name in _MLPS[kind]:
        if name not in manifest["field"]["mlps"]:
            raise InputError(f"lists no MLP {name!r}", file=meta_file)
        mlps[name] = load_mlp(manifest["field"]["mlps"][name], get, name, npz_file)
    occupancy = load_occupancy(manifest, get, npz_file)
    slots = _load_slots(spec["motion"], planes["motion_slot_logits"], get, rows, meta_file, npz_file) \
        if kind == "derf-slots" else None
    return DynamicAssets(manifest, planes, mlps, occupancy, root / manifest["onnx"]["file"], slots=slots)


def _load_slots(spec: dict, logits: list[np.ndarray], get, rows: int, meta_file: Path, npz_file: Path
                ) -> MotionSlots:
    """The manifest's ``field.motion`` of a slot export, its arrays checked against each other and ``rows``."""
    for key in ("still_bias", "keys"):
        if not isinstance(spec.get(key), str):
            raise InputError(f"field.motion.{key} must name an array, got {spec.get(key)!r}", file=meta_file)
    if len(logits) != 1:
        raise InputError(f"plane group 'motion_slot_logits' must hold one plane, got {len(logits)}", file=meta_file)
    plane = logits[0]
    bias = get(spec["still_bias"], "field.motion.still_bias").astype(np.float32)
    keys = get(spec["keys"], "field.motion.keys").astype(np.float32)
    k = plane.shape[1] - 1
    if k < 1 or plane.shape[2] != plane.shape[3] or bias.shape != (k + 1,) or keys.shape != (rows, k, SLOT_KEY_SIZE):
        raise InputError(f"motion slots disagree: logits {plane.shape} (3, K + 1, R, R), still bias {bias.shape} "
                         f"(K + 1,), keys {keys.shape} ({rows}, K, {SLOT_KEY_SIZE}), K >= 1", file=npz_file)
    return MotionSlots(plane, bias, keys)


# ----------------------------------------------------------------------------------------------------
# Pure functions (numpy mirrors of models/fields/dynamic/model.py; tested against it)


def normalize_time(time: float, time_range: tuple[float, float]) -> np.float32:
    """A time in the data's units -> tau in [-1, 1] (float32; 0 when the range is one time).

    Raises:
        InputError: ``time`` not finite, or outside ``time_range`` by more than :data:`TIME_TOLERANCE` of it;
            the message names the time and the range (the field cannot extrapolate in time).
    """
    t_min, t_max = float(time_range[0]), float(time_range[1])
    t = float(time)
    if not math.isfinite(t):
        raise InputError(f"must be finite, got {time!r}", field="time")
    span = t_max - t_min
    tol = TIME_TOLERANCE * max(1.0, abs(span), abs(t_min), abs(t_max))
    if t < t_min - tol or t > t_max + tol:
        raise InputError(f"time {t:.6g} is outside the trained range [{t_min:.6g}, {t_max:.6g}]: the field cannot "
                         "extrapolate in time", field="time")
    if span <= 0:
        return np.float32(0.0)
    # float32 arithmetic as models.fields.dynamic.model.normalize_times on a float32 tensor
    tau = np.float32(2.0) * (np.float32(t) - np.float32(t_min)) / np.float32(span) - np.float32(1.0)
    return np.float32(min(max(tau, -1.0), 1.0))


def time_encoding_np(taus: np.ndarray, frequencies: int) -> np.ndarray:
    """The canonical colour MLP's time input: (N,) -> (N, 2 L + 1) = [tau, sin(2^k tau), cos(2^k tau)], k < L."""
    scaled = taus[:, None] * (2.0 ** np.arange(frequencies, dtype=np.float32))
    return np.concatenate([taus[:, None], np.sin(scaled), np.cos(scaled)], axis=-1).astype(np.float32)


def triplane_features_np(planes: list[np.ndarray], coords: np.ndarray) -> np.ndarray:
    """Tri-plane features (N, C x scales) at contracted coordinates (N, 3): per scale the product of the xy,
    xz, yz planes' bilinear lookups (border-clamped), scales concatenated, scale 0 first."""
    feats = []
    for plane in planes:
        prod = None
        for k, (a, b) in enumerate(PLANE_AXES):
            f = bilinear_np(plane[k], coords[:, a], coords[:, b])
            prod = f if prod is None else prod * f
        feats.append(prod)
    return np.concatenate(feats, axis=0).T


def hex_plane_features_np(spatial: list[np.ndarray], temporal: list[np.ndarray], coords: np.ndarray,
                          taus: np.ndarray) -> np.ndarray:
    """Hex-plane features (thesis Eq. 5.1) (N, C x scales) at contracted coordinates (N, 3) and normalised
    times (N,): per scale (xy xz yz product) times (xt yt zt product); a time plane (3, C, Rt, R) has the
    spatial coordinate along its width and tau along its height."""
    feats = []
    for s_plane, t_plane in zip(spatial, temporal):
        space = triplane_features_np([s_plane], coords)
        prod = None
        for k in range(3):
            f = bilinear_np(t_plane[k], coords[:, k], taus)
            prod = f if prod is None else prod * f
        feats.append(space * prod.T)
    return np.concatenate(feats, axis=1)


def slot_motion_np(slots: MotionSlots, coords: np.ndarray, taus: np.ndarray) -> np.ndarray:
    """The motion slots' mixed motion (N, 3) at contracted points (N, 3) and normalised times (N,), before the
    flow bound (``models.fields.dynamic.model.slot_motion``): ``sum_k w_k (dA_k(tau) c + T_k(tau))`` with
    ``w = softmax(sum of the xy, xz, yz logit planes at c + still_bias)`` over K + 1 slots (slot 0 still, no
    motion) and the keys linear in tau (clamped to [-1, 1]) between the Rt keys. Computed in the dtype of the
    inputs (float64 in, float64 out).

    Raises:
        InputError: coords not (N, 3), taus not (N,), or arrays whose shapes disagree.
    """
    logits, bias, keys = slots
    if coords.ndim != 2 or coords.shape[1] != 3 or taus.shape != coords.shape[:1]:
        raise InputError(f"need coords (N, 3) and taus (N,), got {coords.shape} and {taus.shape}", field="coords")
    rows, k = keys.shape[0], keys.shape[1]
    if logits.shape[:2] != (3, k + 1) or bias.shape != (k + 1,) or keys.shape[2] != SLOT_KEY_SIZE or rows < 2:
        raise InputError(f"logits {logits.shape}, still bias {bias.shape} and keys {keys.shape} disagree",
                         field="slots")
    z = sum(bilinear_np(logits[p], coords[:, a], coords[:, b]) for p, (a, b) in enumerate(PLANE_AXES)).T + bias
    e = np.exp(z - z.max(axis=1, keepdims=True))
    weights = (e / e.sum(axis=1, keepdims=True))[:, 1:]  # (N, K)
    x = (np.clip(taus, -1.0, 1.0) + 1.0) * (0.5 * (rows - 1))
    i0 = np.clip(np.floor(x), 0, rows - 2)
    frac = (x - i0)[:, None, None]
    index = i0.astype(np.int64)
    params = keys[index] * (1.0 - frac) + keys[index + 1] * frac  # (N, K, 12)
    mix = (weights[..., None] * params).sum(axis=1)
    return (mix[:, :9].reshape(-1, 3, 3) * coords[:, None, :]).sum(axis=-1) + mix[:, 9:]


def deform_np(assets: DynamicAssets, coords: np.ndarray, taus: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The motion field: contracted points (N, 3) at normalised times (N,) -> canonical points (N, 3) (not
    clamped) and flow (N, 3), ``flow = max_flow * tanh(flow MLP(hex-plane features))``, or with motion slots
    ``max_flow * tanh(slot_motion_np(.))``."""
    if assets.slots is not None:
        motion = slot_motion_np(assets.slots, coords, taus)
    else:
        feats = hex_plane_features_np(assets.planes["motion_spatial"], assets.planes["motion_temporal"], coords,
                                      taus)
        motion = mlp_np(feats, assets.flow_layers)
    flow = (np.float32(assets.max_flow) * np.tanh(motion)).astype(np.float32)
    return coords + flow, flow


def query_dynamic(assets: DynamicAssets, coords: np.ndarray, taus: np.ndarray, directions: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Density (N,) per scene unit and linear RGB (N, 3) at contracted coordinates (N, 3) in [-1, 1]^3,
    normalised times (N,) and unit world view directions (N, 3) (numpy, float32).

    DeRF: canonical point ``clamp(c + flow, -1, 1)``, canonical tri-planes (hex-planes at (canonical point,
    tau) with ``canonical_temporal``), density MLP (density and latent h), colour MLP on [h, direction
    encoding, time encoding]. K-Planes: hex-plane features of (c, tau), density MLP, colour MLP on [h,
    direction encoding]. A deferred export (``field.shading``) gives the features ``sigmoid(h)`` (N, G) instead
    of the colour: :func:`render_dynamic_field` composites them and runs the colour MLP once per pixel.
    """
    coords = np.asarray(coords, np.float32)
    taus = np.asarray(taus, np.float32)
    spec = assets.manifest["field"]
    if assets.has_motion:
        canonical, _ = deform_np(assets, coords, taus)
        canonical = np.clip(canonical, -1.0, 1.0)
        feats = (triplane_features_np(assets.canonical_planes, canonical) if assets.canonical_temporal is None
                 else hex_plane_features_np(assets.canonical_planes, assets.canonical_temporal, canonical, taus))
    else:
        feats = hex_plane_features_np(assets.planes["spatial"], assets.planes["temporal"], coords, taus)
    out = mlp_np(feats, assets.density_layers)
    sigma = np.exp(np.minimum(out[:, 0] + spec["density_bias"], spec["max_log_density"]))
    if assets.deferred:  # the features sigmoid(h); the colour once per pixel (render_dynamic_field)
        return sigma.astype(np.float32), sigmoid_np(out[:, 1:]).astype(np.float32)
    inputs = [out[:, 1:], direction_encoding_np(np.asarray(directions, np.float32), spec["direction_encoding"],
                                                spec["direction_degree"])]
    if assets.has_motion:
        inputs.append(time_encoding_np(taus, int(spec["time_frequencies"])))
    rgb = sigmoid_np(mlp_np(np.concatenate(inputs, axis=-1), assets.color_layers))
    return sigma.astype(np.float32), rgb.astype(np.float32)


def render_dynamic_field(assets: DynamicAssets, intrinsics, world_to_camera, height: int, width: int,
                         time: float, *, query: str = "numpy", chunk: int = 16384, near: Optional[float] = None,
                         far: Optional[float] = None) -> dict[str, np.ndarray]:
    """Render colour (H, W, 3) linear RGB, planar depth (H, W) (+inf: no surface) and opacity (H, W) at a time.

    Sampling and compositing are the static renderer's (:func:`engine.fields.render.render_field`); the
    occupancy grid is time-agnostic (the max over trained times). A deferred export is shaded as a static one
    (:func:`engine.fields.render.shade_pixels_np`), with the encoded time after the direction encoding (DeRF).

    Args:
        assets: from :func:`load_dynamic_field`.
        intrinsics, world_to_camera: the camera (validated: K finite with positive focal lengths, pose rigid).
        time: in the data's units, inside ``assets.time_range`` (else InputError naming the time and range).
        query: ``numpy`` (:func:`query_dynamic`) or ``onnx`` (``dynamic.onnx`` in onnxruntime).
        near, far: planar-depth bounds of every ray (default: the scene's).

    Returns:
        ``color``, ``depth``, ``opacity`` and ``seconds`` (wall time, ray generation included).
    """
    if query not in ("numpy", "onnx"):
        raise InputError(f"must be numpy or onnx, got {query!r}", field="query")
    tau = normalize_time(time, assets.time_range)

    def evaluate(points: np.ndarray, coords: np.ndarray, directions: np.ndarray):
        if query == "numpy":
            return query_dynamic(assets, coords, np.full(coords.shape[0], tau, np.float32), directions)
        return assets.onnx_session().run(None, {"points": points, "times": np.full(points.shape[0], time, np.float32),
                                                "directions": directions})

    extra = time_encoding_np(np.array([tau], np.float32), int(assets.manifest["field"]["time_frequencies"]))[0] \
        if assets.has_motion else None
    return march_field(assets, intrinsics, world_to_camera, height, width, evaluate, chunk=chunk, near=near, far=far,
                       shade=pixel_shader(assets, extra), channels=assets.feature_dim)


# ----------------------------------------------------------------------------------------------------
# Motion vectors: where a rendered surface point was at an earlier time (the field's own correspondence)


def _newton_step(assets: DynamicAssets, earlier: np.ndarray, at: np.ndarray, flow: np.ndarray, residual: np.ndarray,
                 taus: np.ndarray) -> np.ndarray:
    """One Newton step of ``g(e) = e + flow(e, tau) - C = 0`` from ``earlier`` (N, 3) float32, given ``at`` (it
    clamped to the cube), ``flow`` there and ``residual`` g: the Jacobian ``I + d flow / dc`` by forward
    differences of ``JACOBIAN_STEP`` at ``at``, solved by Cramer's rule (the GL pass's arithmetic); a fixed-point
    step where the Jacobian is near singular; at most ``MAX_NEWTON_STEP`` long."""
    h = np.float32(JACOBIAN_STEP)
    cols = []
    for axis in range(3):
        shifted = at.copy()
        shifted[:, axis] += h
        col = (deform_np(assets, shifted, taus)[1] - flow) / h
        col[:, axis] += np.float32(1.0)
        cols.append(col)
    r0, r1, r2 = np.cross(cols[1], cols[2]), np.cross(cols[2], cols[0]), np.cross(cols[0], cols[1])
    det = (cols[0] * r0).sum(axis=1)
    singular = ~(np.abs(det) >= MIN_JACOBIAN_DET)
    g = residual
    solved = np.stack([(r0 * g).sum(axis=1), (r1 * g).sum(axis=1), (r2 * g).sum(axis=1)], axis=1)
    step = np.where(singular[:, None], g, solved / np.where(singular, np.float32(1.0), det)[:, None])
    length = np.sqrt((step * step).sum(axis=1))
    step = step * np.where(length > MAX_NEWTON_STEP, np.float32(MAX_NEWTON_STEP) / np.maximum(length, 1e-30),
                           np.float32(1.0))[:, None]
    return (earlier - step).astype(np.float32)


def earlier_points(assets: DynamicAssets, coords: np.ndarray, tau: float, tau_earlier: float, *,
                   iterations: int = MOTION_ITERATIONS) -> tuple[np.ndarray, np.ndarray]:
    """Contracted points (N, 3) at normalised time ``tau`` -> the contracted points at ``tau_earlier`` that the
    motion field maps to the same canonical point (float32), and whether each was found (bool (N,)).

    DeRF maps a point c at tau to the canonical point ``C = c + flow(c, tau)`` (thesis Eq. 5.3; the
    correspondence the sparse flow prior trains, Eq. 5.7). The earlier point c' solves
    ``c' + flow(c', tau_earlier) = C`` inside the cube: one fixed-point step ``c'_1 = C - flow(c, tau_earlier)``
    (exact where the flow does not vary in space), then up to ``iterations`` Newton steps (:func:`_newton_step`),
    a point stopping once its residual is at most ``NEWTON_SETTLED``. Newton also converges where the flow's
    spatial derivative exceeds 1 (a moving object's border), where a fixed-point iteration diverges. A
    point is found when the last iterate lies in the cube and solves the equation within ``MOTION_TOLERANCE``
    (contracted units); else (no earlier point in the field, a fold, no convergence) it is not. A K-Planes
    export has no motion model: its points do not move.
    """
    coords = np.asarray(coords, np.float32)
    n = coords.shape[0]
    if not assets.has_motion or n == 0:
        return coords.copy(), np.ones(n, bool)
    canonical, _ = deform_np(assets, coords, np.full(n, tau, np.float32))
    taus = np.full(n, tau_earlier, np.float32)
    earlier = (canonical - deform_np(assets, coords, taus)[1]).astype(np.float32)
    worst = np.empty(n, np.float32)  # max |residual| at each point's last iterate
    active = np.arange(n)
    for step in range(int(iterations) + 1):  # the last residual is the found check's
        at = np.clip(earlier[active], -1.0, 1.0)
        _, flow = deform_np(assets, at, taus[active])
        residual = earlier[active] + flow - canonical[active]
        worst[active] = np.abs(residual).max(axis=1)
        going = ~(worst[active] <= NEWTON_SETTLED)
        active, at, flow, residual = active[going], at[going], flow[going], residual[going]
        if active.size == 0 or step == int(iterations):
            break
        earlier[active] = _newton_step(assets, earlier[active], at, flow, residual, taus[active])
    found = (np.abs(earlier) <= 1.0).all(axis=1) & (worst <= MOTION_TOLERANCE)
    return earlier, found


def _checked_depth(depth) -> np.ndarray:
    depth = np.asarray(depth)
    if depth.ndim != 2 or depth.dtype.kind != "f" or np.isnan(depth).any() or (depth <= 0).any():
        raise InputError(f"must be (H, W) planar depth > 0 (+inf for the background), got {depth.shape} "
                         f"{depth.dtype}", field="depth")
    return depth


def _points_at(assets: DynamicAssets, k: np.ndarray, pose: np.ndarray, depth: np.ndarray, time: float,
               other_time: float, iterations: int, coherence: Optional[float] = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """The surface point of each pixel (the ray at its planar depth) where it is at ``other_time``: world points
    (H W, 3) float32 (the background: its ray direction; NaN where the motion field gives no point, see
    :func:`earlier_points`), and which pixels have a finite depth (H W,). With ``coherence``, a point whose
    motion fails :func:`coherent_motion` stays where it is."""
    tau, tau_other = normalize_time(time, assets.time_range), normalize_time(other_time, assets.time_range)
    h, w = depth.shape
    origin, dirs = camera_rays_np(k, pose, h, w)
    origin, dirs = origin.astype(np.float32), dirs.astype(np.float32)  # the renderer's float32 rays
    d = depth.reshape(-1).astype(np.float32)
    finite = np.isfinite(d)
    points = np.where(finite[:, None], origin + np.where(finite, d, 0)[:, None] * dirs, dirs)
    render = assets.manifest["render"]
    coords = contract_np(assets.scene, points, render["ndc_margin"])
    inside = finite & (np.abs(coords) <= 1.0).all(axis=-1)
    moved, found = earlier_points(assets, coords[inside], tau, tau_other, iterations=iterations)
    moved = np.where(found[:, None], uncontract_np(assets.scene, moved, render["ndc_margin"]), np.nan)
    if coherence is not None:  # a found point whose motion is not steady stays where it is
        steady = coherent_motion(assets, coords[inside], points[inside], moved, tau, tau_other, coherence,
                                 iterations=iterations)
        moved[found & ~steady] = points[inside][found & ~steady]
    points[inside] = moved
    return points, finite


def field_object_flow(assets: DynamicAssets, intrinsics, world_to_camera, depth: np.ndarray, time: float,
                      target_time: float, *, iterations: int = MOTION_ITERATIONS) -> np.ndarray:
    """The field's own motion of each pixel's surface point from ``time`` to ``target_time`` as an object flow
    in this frame's view (H, W, 3) float32: (du, dv) pixels and dz planar depth, where the point would be
    seen by the same camera (``engine.geometry.splat``'s object flow; the camera's motion is the warp's).
    Zero on the background and where the motion field gives no point. What an oracle of a field renderer
    moves frame n by (the field knows its future)."""
    k = validate_intrinsics(intrinsics)
    pose = validate_pose(world_to_camera)
    depth = _checked_depth(depth)
    h, w = depth.shape
    points, finite = _points_at(assets, k, pose, depth, time, target_time, iterations)
    q = points.astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    flow = np.concatenate([projected_offsets(q, k, u.reshape(-1), v.reshape(-1)),
                           (q[:, 2] - np.where(finite, depth.reshape(-1), 0.0))[:, None]], axis=1)
    flow[~(finite & np.isfinite(flow).all(axis=1))] = 0.0
    return flow.reshape(h, w, 3).astype(np.float32)


def check_coherence(coherence: Optional[float]) -> None:
    """Raise InputError unless ``coherence`` (the ratio of :func:`coherent_motion`) is None or finite and >= 0."""
    if coherence is not None and not (math.isfinite(coherence) and coherence >= 0):
        raise InputError(f"must be finite and >= 0, got {coherence!r}", field="coherence")


def time_before(tau: float, tau_earlier: float) -> Optional[float]:
    """The normalised time of the interval before ``tau_earlier`` -> ``tau``, ``2 tau_earlier - tau`` (float32
    arithmetic), clipped to [-1, 1]; None where it lies outside the trained range (beyond TIME_TOLERANCE)."""
    before = np.float32(2.0) * np.float32(tau_earlier) - np.float32(tau)
    return None if abs(float(before)) > 1.0 + TIME_TOLERANCE else float(np.clip(before, -1.0, 1.0))


def coherent_motion(assets: DynamicAssets, coords: np.ndarray, points: np.ndarray, earlier: np.ndarray,
                    tau: float, tau_earlier: float, ratio: float, *, iterations: int = MOTION_ITERATIONS
                    ) -> np.ndarray:
    """Which points move steadily: (N,) bool. ``coords`` (N, 3) contracted and ``points`` (N, 3) world are the
    points at normalised time ``tau``, ``earlier`` (N, 3) world where the motion field puts them at
    ``tau_earlier`` (:func:`earlier_points`, NaN where none). A point is steady where its motion over the interval
    before, ``tau_before = 2 tau_earlier - tau`` -> ``tau_earlier``, continued, misses its last motion by at most
    ``ratio`` times that motion: ``|(p - e) - (e - b)| <= ratio |p - e|`` with b its point at ``tau_before``
    (world units). Not steady: a motion that turns, starts, stops or jitters faster than that (what
    extrapolating the last motion gets wrong), or no point at ``tau_before`` inside the field's cube (the
    inversion did not settle). Steady where there is nothing to compare with: a point at ``tau_before`` outside
    the cube, ``tau_before`` outside the trained range, or an export without a motion model.
    """
    n = coords.shape[0]
    tau_before = time_before(tau, tau_earlier)
    if not assets.has_motion or n == 0 or tau_before is None:
        return np.ones(n, bool)
    before, found = earlier_points(assets, coords, tau, tau_before, iterations=iterations)
    outside = (np.abs(before) > 1.0).any(axis=1)
    before = uncontract_np(assets.scene, before, assets.manifest["render"]["ndc_margin"]).astype(np.float64)
    last = np.asarray(points, np.float64) - earlier
    with np.errstate(invalid="ignore"):
        turned = np.linalg.norm(last - (earlier - before), axis=1) > float(ratio) * np.linalg.norm(last, axis=1)
    return outside | (found & ~turned)


def field_motion_vectors(assets: DynamicAssets, intrinsics, world_to_camera, depth: np.ndarray, time: float,
                         earlier_world_to_camera, earlier_time: float, *, earlier_intrinsics=None,
                         iterations: int = MOTION_ITERATIONS, coherence: Optional[float] = None) -> np.ndarray:
    """Engine-style motion vectors (H, W, 2) float32 of a dynamic field's frame: from each pixel centre to where
    its surface point was in the frame seen by the earlier camera at ``earlier_time``, in pixels (x right,
    y down), camera motion included (``docs/motion-vectors.md``).

    The surface point is the pixel's ray at its rendered planar ``depth`` (+inf: the background, which moves
    with the camera's rotation alone); inside the field's cube it moves by :func:`earlier_points`, outside
    it is static. NaN where the motion field gives no earlier point (see :func:`earlier_points`), where the
    earlier point is behind (or on) the earlier camera's plane, lies at infinity (a forward-facing scene's far
    end) or projects more than ``MAX_MOTION_DIAGONALS`` frame diagonals away.
    With ``coherence`` (a ratio, :data:`COHERENCE` for ``mvec``), a point whose motion is not steady over the
    interval before (:func:`coherent_motion`) gets the camera's vector alone: ``mvec`` extrapolates the vectors,
    and a trained field's motion that jitters in time extrapolates worse than none
    (``docs/results/2026-11-28-dynamic-vectors-fix.md``). Without it, the field's motion as it is.
    The numpy oracle of ``GlDynamicRenderer.motion_vectors``.

    Raises:
        InputError: bad intrinsics or poses, a depth that is not (H, W) positive (or +inf), times outside the
            trained range, a coherence that is not finite and >= 0.
    """
    check_coherence(coherence)
    k = validate_intrinsics(intrinsics)
    pose = validate_pose(world_to_camera)
    k_prev = k if earlier_intrinsics is None else validate_intrinsics(earlier_intrinsics,
                                                                      field_name="earlier_intrinsics")
    prev = validate_pose(earlier_world_to_camera, field_name="earlier_world_to_camera")
    depth = _checked_depth(depth)
    h, w = depth.shape
    points, finite = _points_at(assets, k, pose, depth, time, earlier_time, iterations, coherence)
    # finite points: world -> earlier camera; the background: directions, rotation only
    q = points.astype(np.float64) @ prev[:3, :3].T + np.where(finite, 1.0, 0.0)[:, None] * prev[:3, 3]
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    out = drop_long_vectors(projected_offsets(q, k_prev, u.reshape(-1), v.reshape(-1)), h, w)
    return out.reshape(h, w, 2).astype(np.float32)
