"""Opening an exported engine network: one session helper for the flow and infilling networks.

Where a network runs (``network_runtime``, from ``INTERLEAVE_ORT_DEVICE``): onnxruntime's CUDA execution
provider when onnxruntime has it (the ``onnxruntime-gpu`` package: the ``interleave[gpu]`` extra); else, on a
machine with an NVIDIA device where torch sees CUDA, torch (``engine.predict.torch_onnx``: the same graph
evaluated by torch operators; needs the ``onnx`` and ``torch`` packages); else onnxruntime on the CPU.
``cpu`` forces onnxruntime on the CPU, ``cuda`` a GPU (an InputError without one), ``torch`` the torch runner
(on CUDA when there, else on the CPU: its parity path). CPU sessions of onnxruntime sleep their idle pool
threads unless ``INTERLEAVE_ORT_SPIN=1``."""
from __future__ import annotations

import importlib.util
import json
import os
from pathlib import Path
from typing import Sequence

import onnxruntime as ort

from engine.core.errors import InputError

__all__ = ["open_network", "execution_providers", "network_runtime", "torch_gpu_present"]

#: the values of ``INTERLEAVE_ORT_DEVICE``
DEVICES = ("auto", "cpu", "cuda", "torch")


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


def _torch_runner_installed() -> bool:
    """Whether the packages the torch runner imports (torch, onnx) are installed, without importing them."""
    return importlib.util.find_spec("torch") is not None and importlib.util.find_spec("onnx") is not None


def torch_gpu_present() -> bool:
    """Whether the torch runner can use a GPU: torch and onnx are installed, the machine has an NVIDIA device
    node, and torch sees CUDA (torch is imported only when the first two hold)."""
    if not _torch_runner_installed() or not os.path.exists("/dev/nvidiactl"):
        return False
    from engine.predict.torch_onnx import torch_cuda_available
    return torch_cuda_available()


def network_runtime(available: Sequence[str], device: str = "auto", torch_gpu: bool = False):
    """Where a network runs: ``("onnxruntime", providers)`` or ``("torch", "cuda" | "cpu")``, from onnxruntime's
    ``available`` providers, the ``device`` asked for (``DEVICES``) and whether torch has a GPU (``torch_gpu``):
    onnxruntime's CUDA provider first, then torch on CUDA, then onnxruntime on the CPU (module docstring)."""
    if device not in DEVICES:
        raise InputError(f"must be one of {', '.join(DEVICES)}, got {device!r}", field="INTERLEAVE_ORT_DEVICE")
    if device == "torch":
        return "torch", "cuda" if torch_gpu else "cpu"
    ort_cuda = "CUDAExecutionProvider" in available
    if device in ("auto", "cuda") and not ort_cuda and torch_gpu:
        return "torch", "cuda"
    if device == "cuda" and not ort_cuda:
        raise InputError("no GPU runtime for the networks: install onnxruntime-gpu (pip install -e '.[gpu]'), or "
                         "torch with CUDA and onnx", field="INTERLEAVE_ORT_DEVICE")
    return "onnxruntime", execution_providers(available, device)


def open_network(path: Path, threads: int, metadata_key: str, field: str, missing: str):
    """(session, the JSON metadata under ``metadata_key``) of an exported engine network: an onnxruntime
    session, or a ``TorchOnnxSession`` with the same ``run`` / ``get_modelmeta`` (``network_runtime``);
    InputError naming the file when it is missing (``missing``) or lacks the metadata."""
    if not path.is_file():
        raise InputError(missing, file=path, field=field)
    device, available = os.environ.get("INTERLEAVE_ORT_DEVICE", "auto"), ort.get_available_providers()
    asks_torch = device == "torch" or (device in ("auto", "cuda") and "CUDAExecutionProvider" not in available)
    kind, where = network_runtime(available, device, asks_torch and torch_gpu_present())
    if kind == "torch":
        if not _torch_runner_installed():
            raise InputError("the torch runner needs the torch and onnx packages (pip install -e '.[train]')",
                             field="INTERLEAVE_ORT_DEVICE")
        from engine.predict.torch_onnx import TorchOnnxSession
        session = TorchOnnxSession(path, where, threads)
        return session, _metadata(session, path, metadata_key, field)
    options = ort.SessionOptions()
    options.intra_op_num_threads = int(threads)
    options.inter_op_num_threads = 1
    options.log_severity_level = 3  # errors only (exported graphs trigger harmless folding warnings)
    if os.environ.get("INTERLEAVE_ORT_SPIN", "0") != "1":  # idle pool threads sleep, as the kernels' do
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    session = ort.InferenceSession(str(path), options, providers=where)
    return session, _metadata(session, path, metadata_key, field)


def _metadata(session, path: Path, metadata_key: str, field: str) -> dict:
    meta = session.get_modelmeta().custom_metadata_map
    if metadata_key not in meta:
        raise InputError(f"has no '{metadata_key}' metadata: export it with this project's export command",
                         file=path, field=field)
    return json.loads(meta[metadata_key])
