"""A trained field's real-time assets (``docs/field-assets.md``), built in memory from the torch model.

``static_assets(model)`` / ``dynamic_assets(model)`` return ``(arrays, manifest)``: the tri-plane textures
(float32, and uint8 with per-plane, per-channel [min, max] ranges), the MLP weights, the occupancy grid and
the manifest that ``engine.fields.render.load_field`` / ``engine.fields.dynamic.load_dynamic_field`` read.
``interleave export field|dynamic`` writes them beside the ONNX query graph (``export/``);
``gl_renderer(model, width, height)`` hands them to the GL renderer without writing an export, which is
how ``interleave eval field|dynamic --renderer gl`` scores a run in seconds.

The manifest names the ONNX file the export writes (``field.onnx`` / ``dynamic.onnx``); in memory no such
file exists, and the GL and numpy renderers never open it.
"""
from __future__ import annotations

import dataclasses
import json
import tempfile
from pathlib import Path
from typing import Optional

import numpy as np
from torch import nn

from models.fields.static.field import MAX_LOG_DENSITY

__all__ = ["STATIC_FORMAT", "STATIC_VERSION", "DYNAMIC_FORMAT", "DYNAMIC_VERSION", "OPSET", "quantize_planes",
           "direction_degree", "mlp_layers", "static_assets", "dynamic_assets", "load_assets", "gl_renderer"]

STATIC_FORMAT, STATIC_VERSION = "interleave-field", 1
DYNAMIC_FORMAT, DYNAMIC_VERSION = "interleave-dynamic-field", 1
OPSET = 20


def quantize_planes(plane: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(3, C, R, R) float -> uint8 codes (3, C, R, R) and ranges (3, C, 2) [min, max] per plane and channel.

    Decoding is ``min + code / 255 * (max - min)``; a constant channel has max == min and decodes exactly.
    """
    lo = plane.min(axis=(2, 3))
    hi = plane.max(axis=(2, 3))
    span = np.where(hi > lo, hi - lo, 1.0)
    codes = np.rint((plane - lo[..., None, None]) / span[..., None, None] * 255.0).clip(0, 255).astype(np.uint8)
    return codes, np.stack([lo, hi], axis=-1).astype(np.float32)


def direction_degree(cfg) -> int:
    """The manifest's ``direction_degree`` of a ``FieldConfig``: 0 for ``direction_encoding="none"``, which has no
    degree (the config keeps its default there, which the manifest check refuses)."""
    return 0 if cfg.direction_encoding == "none" else int(cfg.direction_degree)


def mlp_layers(mlp: nn.Module) -> list[nn.Linear]:
    """The linear layers of an ``MLP`` (``models.fields.components.encodings``), input to output."""
    return [m for m in mlp.net if isinstance(m, nn.Linear)]


def _add_mlps(arrays: dict[str, np.ndarray], named: dict[str, nn.Module]) -> dict[str, list[dict]]:
    """Write each MLP's layers into ``arrays`` (``W`` (out, in): y = W x + b); their manifest entries."""
    mlps = {}
    for name, mlp in named.items():
        layers = []
        for j, lin in enumerate(mlp_layers(mlp)):
            arrays[f"{name}_w{j}"] = lin.weight.detach().float().cpu().numpy()
            arrays[f"{name}_b{j}"] = lin.bias.detach().float().cpu().numpy()
            layers.append({"weight": f"{name}_w{j}", "bias": f"{name}_b{j}",
                           "in": int(lin.in_features), "out": int(lin.out_features)})
        mlps[name] = layers
    return mlps


def _add_plane(arrays: dict[str, np.ndarray], key: str, plane) -> np.ndarray:
    """Write a plane tensor as float32 + uint8 codes + ranges under ``key``; returns the float array."""
    p = plane.detach().float().cpu().numpy()
    codes, ranges = quantize_planes(p)
    arrays[key], arrays[f"{key}_u8"], arrays[f"{key}_range"] = p, codes, ranges
    return p


def _add_occupancy(arrays: dict[str, np.ndarray], model, **extra) -> Optional[dict]:
    if model.occupancy is None or int(model.occupancy.updates) == 0:
        return None
    arrays["occupancy"] = model.occupancy.occupied.cpu().numpy().astype(np.uint8)
    return {"array": "occupancy", "resolution": int(model.occupancy.resolution),
            "occupied_fraction": float(model.occupancy.occupied.float().mean()), **extra}


def _render_section(model) -> dict:
    rc = model.render_config
    return {"num_samples": int(rc.num_samples), "spacing": "linear" if model.bounded else "disparity",
            "ndc_margin": float(rc.ndc_margin)}


def static_assets(model) -> tuple[dict[str, np.ndarray], dict]:
    """``(arrays, manifest)`` of a :class:`models.fields.static.model.StaticFieldModel` (no parity entries)."""
    cfg = model.field.config
    arrays: dict[str, np.ndarray] = {}
    planes_meta = []
    for i, plane in enumerate(model.field.encoding.planes):
        p = _add_plane(arrays, f"planes_{i}", plane)
        planes_meta.append({"scale": i, "resolution": int(p.shape[-1]), "channels": int(p.shape[1]),
                            "float": f"planes_{i}", "uint8": f"planes_{i}_u8", "range": f"planes_{i}_range"})
    mlps = _add_mlps(arrays, {"density": model.field.density_mlp, "color": model.field.color_mlp})
    manifest = {
        "format": STATIC_FORMAT, "version": STATIC_VERSION,
        "scene": model.scene.to_dict(),
        "background": [float(x) for x in model.background],
        "render": _render_section(model),
        "field": {"plane_axes": [[0, 1], [0, 2], [1, 2]], "planes": planes_meta,
                  "feature_combine": "product over planes, concatenated over scales",
                  "density_bias": float(cfg.density_bias), "max_log_density": MAX_LOG_DENSITY,
                  "geo_feature_dim": int(cfg.geo_feature_dim), "shading": cfg.shading,
                  "direction_encoding": cfg.direction_encoding, "direction_degree": direction_degree(cfg),
                  "mlps": mlps},
        "occupancy": _add_occupancy(arrays, model),
        "onnx": {"file": "field.onnx", "inputs": ["points", "directions"], "outputs": ["density", "color"],
                 "opset": OPSET},
        "field_config": dataclasses.asdict(cfg),
    }
    return arrays, manifest


def _slots(model):
    """The DeRF field's ``SlotMotion`` (motion slots), or None (hex-plane motion field, or K-Planes)."""
    return model.field.motion_field.slot_motion if model.has_motion else None


def _dynamic_planes(model) -> dict:
    """Every plane group by name (what the manifest lists)."""
    field = model.field
    if model.has_motion:
        canonical_time = field.canonical_field.temporal_planes()
        slots = _slots(model)
        motion = ({"motion_slot_logits": [slots.logits]} if slots is not None else
                  {"motion_spatial": field.motion_field.spatial_planes(),
                   "motion_temporal": field.motion_field.temporal_planes()})
        return {"canonical_spatial": field.canonical_field.spatial_planes(), **motion,
                **({"canonical_temporal": canonical_time} if canonical_time else {})}
    return {"spatial": field.encoding.spatial_planes(), "temporal": field.encoding.temporal_planes()}


def _dynamic_mlps(model) -> dict[str, nn.Module]:
    field = model.field
    if model.has_motion:
        flow = {"flow": field.motion_field.flow_mlp} if _slots(model) is None else {}
        return {"density": field.canonical_field.density_mlp, "color": field.canonical_field.color_mlp, **flow}
    return {"density": field.density_mlp, "color": field.color_mlp}


def _slot_section(arrays: dict[str, np.ndarray], slots) -> dict:
    """Write the motion slots' still bias and key table into ``arrays``; the manifest's ``field.motion``."""
    arrays["motion_slot_still_bias"] = slots.still_bias.detach().float().cpu().numpy()
    arrays["motion_slot_keys"] = slots.keys.detach().float().cpu().numpy()
    return {"model": "slots", "slots": int(slots.slots), "resolution": int(slots.resolution),
            "logits": "motion_slot_logits", "still_bias": "motion_slot_still_bias", "keys": "motion_slot_keys",
            "keys_layout": "(Rt, K, 12): per time key i (tau = -1 + 2 i / (Rt - 1)) and moving slot k, dA_k "
                           "row-major (9), then T_k (3); linear in tau between keys"}


def dynamic_assets(model, canonical_limit=None) -> tuple[dict[str, np.ndarray], dict]:
    """``(arrays, manifest)`` of a :class:`models.fields.dynamic.model.DynamicFieldModel` (no parity entries);
    ``canonical_limit``: the run's ``scores.json`` value, recorded in the manifest."""
    arrays: dict[str, np.ndarray] = {}
    planes_meta: dict[str, list] = {}
    for group, tensors in _dynamic_planes(model).items():
        planes_meta[group] = []
        for i, plane in enumerate(tensors):
            key = f"{group}_{i}"
            p = _add_plane(arrays, key, plane)
            planes_meta[group].append({"scale": i, "shape": list(p.shape), "float": key, "uint8": f"{key}_u8",
                                       "range": f"{key}_range"})
    mlps = _add_mlps(arrays, _dynamic_mlps(model))
    cfg = model.config
    canonical_cfg = cfg.canonical
    slots = _slots(model)
    motion_text = ("flow MLP(motion features)" if slots is None else
                   "sum_k w_k (dA_k(tau) c + T_k(tau)), w = softmax(logit planes(c) + still bias)")
    t0, t1 = model.time_range
    manifest = {
        "format": DYNAMIC_FORMAT, "version": DYNAMIC_VERSION, "kind": cfg.kind,
        "scene": model.scene.to_dict(), "background": [float(x) for x in model.background],
        "render": _render_section(model),
        "time": {"range": [t0, t1], "normalised": "tau = clamp(2 (t - t_min) / (t_max - t_min) - 1, -1, 1); 0 when "
                                                  "t_max = t_min", "time_resolution": int(model.time_resolution)},
        "field": {
            "spatial_plane_axes": [[0, 1], [0, 2], [1, 2]],
            "temporal_plane_axes": "xt, yt, zt: spatial coordinate along the width, tau along the height",
            "feature_combine": "per scale, product over the group's planes (hex-planes: all six); scales "
                               "concatenated",
            "planes": planes_meta, "mlps": mlps, "density_bias": float(canonical_cfg.density_bias),
            "max_log_density": MAX_LOG_DENSITY, "geo_feature_dim": int(canonical_cfg.geo_feature_dim),
            "shading": canonical_cfg.shading, "direction_encoding": canonical_cfg.direction_encoding,
            "direction_degree": direction_degree(canonical_cfg),
            **({"time_frequencies": int(cfg.time_frequencies),
                "color_input": "[h, direction encoding, fourier(tau): tau, sin(2^k tau), cos(2^k tau)]",
                "max_flow": float(cfg.motion.max_flow),  # the flow bound as a number (renderers read it)
                "flow": f"{float(cfg.motion.max_flow)} * tanh({motion_text}) in contracted units; "
                        "canonical = contracted point + flow, clamped to [-1, 1] for the canonical lookup"}
               if model.has_motion else {"color_input": "[h, direction encoding]"}),
            **({"motion": _slot_section(arrays, slots)} if slots is not None else {}),
        },
        "occupancy": _add_occupancy(arrays, model, time_agnostic="max over trained times"),
        "onnx": {"file": "dynamic.onnx", "inputs": ["points", "times", "directions"],
                 "outputs": ["density", "color"], "opset": OPSET},
        "canonical_limit": canonical_limit,
        "field_config": dataclasses.asdict(cfg),
    }
    return arrays, manifest


def load_assets(arrays: dict[str, np.ndarray], manifest: dict, stem: str):
    """The renderers' asset object of ``(arrays, manifest)``, through the same loader (and checks) as an export
    on disk: written to a temporary folder (uncompressed) and read back. ``stem``: ``field`` or ``dynamic``."""
    from engine.fields.dynamic import load_dynamic_field
    from engine.fields.render import load_field

    loader = {"field": load_field, "dynamic": load_dynamic_field}[stem]
    with tempfile.TemporaryDirectory(prefix="interleave-assets-") as tmp:
        np.savez(Path(tmp) / f"{stem}.npz", **arrays)
        (Path(tmp) / f"{stem}.json").write_text(json.dumps(manifest))
        return loader(tmp)


def gl_renderer(model, width: int, height: int, **options):
    """A GL renderer (``engine.fields.gl.GlFieldRenderer`` or ``engine.fields.gldynamic.GlDynamicRenderer``)
    of a static or dynamic torch model at ``width`` x ``height``, from assets made in memory; ``options`` go
    to the renderer (e.g. ``filtering="exact"``)."""
    from models.fields.dynamic.model import DynamicFieldModel

    if isinstance(model, DynamicFieldModel):
        from engine.fields.gldynamic import GlDynamicRenderer

        arrays, manifest = dynamic_assets(model)
        return GlDynamicRenderer(load_assets(arrays, manifest, "dynamic"), width, height, **options)
    from engine.fields.gl import GlFieldRenderer

    arrays, manifest = static_assets(model)
    return GlFieldRenderer(load_assets(arrays, manifest, "field"), width, height, **options)
