"""The exported 3D flow network of ``decomp`` in onnxruntime (no torch): ``(m_n, m^w_{n-k}) -> u(n -> n-k)``.

MPIs are (C, Z, H, W) with planes near (0) to far (Z - 1); flows (3, Z, H, W) = (du, dv) pixels, dz scene
units; an initial flow (H, W, 2) pixels.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from engine.core.errors import InputError
from engine.geometry import Mpi
from engine.predict.onnx import open_network
from engine.weights import FLOW3D

__all__ = ["FlowNetwork", "DEFAULT_MODEL", "METADATA_KEY"]

#: The committed 3D flow network (``configs/flow3d.json``; see ``engine/weights/README.md``).
DEFAULT_MODEL = FLOW3D
#: ONNX metadata key holding the network's ``Flow3DConfig`` and training facts (JSON), set by ``export.flow``.
METADATA_KEY = "interleave.flow3d"


class FlowNetwork:
    """The exported flow network in onnxruntime: ``(m_n, m^w_{n-k}) -> u(n -> n-k)`` (3, Z, H, W).

    Reads the network's config from the ONNX metadata (``METADATA_KEY``): number of planes, pyramid stride,
    mode ('3d' or the '2d' ablation), the working width the training frames had and whether the graph
    computes dz (``depth_flow``; without it dz comes out 0).
    """

    def __init__(self, path: str | Path, threads: int = 2) -> None:
        path = Path(path)
        self.session, info = open_network(path, threads, METADATA_KEY, "model", "flow network not found (train "
                                          "and export one: interleave train flow / interleave export flow)")
        self.path = path
        self.config: dict = info["model"]
        self.num_planes = int(self.config["num_planes"])
        self.stride = 2 ** len(self.config["encoder_channels"])
        self.working_width = int(info.get("working_width", 480))
        self.mode = str(self.config["mode"])
        self.needs_initial_flow = bool(self.config.get("initial_flow", False))
        #: whether the graph computes dz (exports with ``--no-depth-flow`` return dz = 0 uncomputed)
        self.depth_flow = bool(info.get("depth_flow", True))

    def __call__(self, mpi_n: Mpi, mpi_prev_warped: Mpi, init: Optional[np.ndarray] = None) -> np.ndarray:
        """Flow (3, Z, H, W) float32 = (du, dv) pixels, dz scene units; 0 where ``mpi_n.alpha`` is 0.

        ``init`` (H, W, 2): the 2D flow to refine (``engine.predict.dis.initial_flow``), required by networks
        trained with one.
        """
        z = mpi_n.alpha.shape[0]
        if z != self.num_planes or mpi_prev_warped.alpha.shape != mpi_n.alpha.shape:
            raise InputError(f"MPIs of shape {mpi_n.alpha.shape} / {mpi_prev_warped.alpha.shape}: the network "
                             f"takes two MPIs of {self.num_planes} planes", field="mpi")
        feeds = {
            "color_n": mpi_n.color[None], "depth_n": mpi_n.depth[None, None], "alpha_n": mpi_n.alpha[None, None],
            "color_prev": mpi_prev_warped.color[None], "depth_prev": mpi_prev_warped.depth[None, None],
            "alpha_prev": mpi_prev_warped.alpha[None, None],
            "plane_depths": np.asarray(mpi_n.plane_depths, dtype=np.float32)[None],
        }
        if self.needs_initial_flow:
            if init is None or init.shape != mpi_n.alpha.shape[1:] + (2,):
                raise InputError(f"this network refines an initial flow of shape {mpi_n.alpha.shape[1:] + (2,)}",
                                 field="init")
            feeds["initial_flow"] = np.moveaxis(init, -1, 0)[None]
        # the exported graph takes sizes that are multiples of the pyramid stride: pad with alpha = 0 (ignored
        # by the partial convolutions, as Flow3D pads internally) and crop the flow back
        h, w = mpi_n.alpha.shape[1:]
        ph, pw = -h % self.stride, -w % self.stride
        if ph or pw:
            feeds = {k: v if k == "plane_depths" else np.pad(v, [(0, 0)] * (v.ndim - 2) + [(0, ph), (0, pw)])
                     for k, v in feeds.items()}
        feeds = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in feeds.items()}
        return self.session.run(None, feeds)[0][0][..., :h, :w]
