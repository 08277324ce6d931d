"""Opening an exported engine network in onnxruntime: one session helper for the flow and infilling networks.

Sessions run on the CUDA execution provider when onnxruntime has it (the ``onnxruntime-gpu`` package: the
``interleave[gpu]`` extra) and ``INTERLEAVE_ORT_DEVICE`` is not ``cpu``, else on the CPU; CPU sessions sleep
their idle pool threads unless ``INTERLEAVE_ORT_SPIN=1``."""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Sequence

import onnxruntime as ort

from engine.core.errors import InputError

__all__ = ["open_network", "execution_providers"]


def execution_providers(available: Sequence[str], device: str = "auto") -> list[str]:
    """The onnxruntime providers to ask for, best first: CUDA when ``available`` lists it and ``device`` is
    ``auto`` or ``cuda``, then the CPU (always there as the fallback); ``device`` ``cpu`` forces the CPU and
    ``cuda`` without the CUDA provider is an InputError."""
    if device not in ("auto", "cpu", "cuda"):
        raise InputError(f"must be auto, cpu or cuda, got {device!r}", field="INTERLEAVE_ORT_DEVICE")
    cuda = "CUDAExecutionProvider" in available
    if device == "cuda" and not cuda:
        raise InputError("the CUDA execution provider is missing: install onnxruntime-gpu (pip install -e "
                         "'.[gpu]')", field="INTERLEAVE_ORT_DEVICE")
    return (["CUDAExecutionProvider"] if cuda and device != "cpu" else []) + ["CPUExecutionProvider"]


def open_network(path: Path, threads: int, metadata_key: str, field: str, missing: str):
    """(onnxruntime session, the JSON metadata under ``metadata_key``) of an exported engine network;
    InputError naming the file when it is missing (``missing``) or lacks the metadata."""
    if not path.is_file():
        raise InputError(missing, file=path, field=field)
    options = ort.SessionOptions()
    options.intra_op_num_threads = int(threads)
    options.inter_op_num_threads = 1
    options.log_severity_level = 3  # errors only (exported graphs trigger harmless folding warnings)
    if os.environ.get("INTERLEAVE_ORT_SPIN", "0") != "1":  # idle pool threads sleep, as the kernels' do
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    providers = execution_providers(ort.get_available_providers(), os.environ.get("INTERLEAVE_ORT_DEVICE", "auto"))
    session = ort.InferenceSession(str(path), options, providers=providers)
    meta = session.get_modelmeta().custom_metadata_map
    if metadata_key not in meta:
        raise InputError(f"has no '{metadata_key}' metadata: export it with this project's export command",
                         file=path, field=field)
    return session, json.loads(meta[metadata_key])
