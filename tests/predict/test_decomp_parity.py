"""The committed flow network: onnxruntime (engine, no torch) against the torch model it was exported from,
both refining the same initial flow (``engine.predict.decomp.predictor.initial_flow``, the function training calls).

Tolerances: the ONNX graph against torch on the same inputs, 1e-3 px / scene units absolute (measured
about 1e-5); the engine's whole input path (numpy downsample, MPIs and camera warp, ``engine.geometry``)
against the torch one (``models.flow.train`` data path: the same downsample, ``models.flow.network.mpi_pair``):
the numpy warp matches the torch reference to 2e-4 on all but a few pixels (tests/geometry/test_geometry.py), so
the flows agree to 1e-3 at the median and 0.05 px at the 99th percentile.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from engine import geometry
from engine.geometry import Mpi as NpMpi
from engine.predict.decomp.network import DEFAULT_MODEL, METADATA_KEY, FlowNetwork
from engine.predict.dis import initial_flow
from export.flow import with_planes
from models.flow.network import mpi_pair
from models.flow.train import dis_initial_flow, frame_tensors, load_model
from tests.synthetic import two_layer_sequence

ROOT = Path(__file__).resolve().parents[2]
CHECKPOINT = ROOT / "models" / "weights" / "flow3d.pt"
pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def pair():
    frames, _ = two_layer_sequence(5, width=256, height=160, camera_speed=0.03, object_speed=0.1)
    return frames[1], frames[3]


def test_committed_network_matches_its_checkpoint(pair):
    net = FlowNetwork(DEFAULT_MODEL, threads=1)
    model = with_planes(load_model(CHECKPOINT), net.num_planes)  # the export's plane count (2; trained at 4)
    assert net.config == json.loads(json.dumps(model.config.__dict__))
    older, newest = pair
    tensors_n = frame_tensors(newest, 2)
    m_n, m_w = mpi_pair(*tensors_n, *frame_tensors(older, 2), net.num_planes)
    init = dis_initial_flow(tensors_n[0], m_w)  # the DIS flow the network refines, as in training
    with torch.no_grad():
        want = model(m_n, m_w, init)[0].numpy()
    assert not net.depth_flow  # exported with --no-depth-flow: dz comes out 0, (du, dv) as torch computes them
    want[2] = 0.0
    init_np = init[0].permute(1, 2, 0).numpy()

    def numpy_mpi(m):
        return NpMpi(m.color[0].numpy(), m.depth[0, 0].numpy(), m.alpha[0, 0].numpy(), m.plane_depths[0].numpy())

    got = net(numpy_mpi(m_n), numpy_mpi(m_w), init_np)
    assert got.shape == want.shape
    assert np.abs(got - want).max() < 1e-3
    assert np.abs(want[:2]).max() > 0.1  # a moving square: the comparison is not between zeros

    # the engine builds the same inputs without torch
    low_n = geometry.downsample_frame(newest.color, newest.depth, newest.camera.intrinsics, 2)
    low_p = geometry.downsample_frame(older.color, older.depth, older.camera.intrinsics, 2)
    e_n = geometry.build_mpi(low_n[0], low_n[1], net.num_planes)
    e_p = geometry.build_mpi(low_p[0], low_p[1], net.num_planes)
    e_w, _ = geometry.forward_warp_mpi(e_p._replace(plane_depths=e_n.plane_depths), low_p[2],
                                       older.camera.world_to_camera, low_n[2], newest.camera.world_to_camera)
    warped_color, _, acc = geometry.composite(e_w)
    engine_flow = net(e_n, e_w, initial_flow(low_n[0], warped_color, acc > 0))
    diff = np.abs(engine_flow - want)
    assert np.median(diff) < 1e-3 and np.percentile(diff, 99) < 0.05


def test_onnx_metadata_records_the_working_width():
    import onnx

    meta = {p.key: p.value for p in onnx.load(str(DEFAULT_MODEL), load_external_data=False).metadata_props}
    info = json.loads(meta[METADATA_KEY])
    assert info["working_width"] == 480 and info["model"]["num_planes"] == 2  # exported with --num-planes 2
    assert info["depth_flow"] is False  # and --no-depth-flow (the engine's decomp uses no dz)
