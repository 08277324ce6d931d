"""Opening an exported engine network in onnxruntime (CPU): one session helper for the flow and infilling
networks. Sessions sleep their idle pool threads unless ``INTERLEAVE_ORT_SPIN=1``."""
from __future__ import annotations

import json
import os
from pathlib import Path

import onnxruntime as ort

from engine.core.errors import InputError

__all__ = ["open_network"]


def open_network(path: Path, threads: int, metadata_key: str, field: str, missing: str):
    """(onnxruntime CPU session, the JSON metadata under ``metadata_key``) of an exported engine network;
    InputError naming the file when it is missing (``missing``) or lacks the metadata."""
    if not path.is_file():
        raise InputError(missing, file=path, field=field)
    options = ort.SessionOptions()
    options.intra_op_num_threads = int(threads)
    options.inter_op_num_threads = 1
    options.log_severity_level = 3  # errors only (exported graphs trigger harmless folding warnings)
    if os.environ.get("INTERLEAVE_ORT_SPIN", "0") != "1":  # idle pool threads sleep, as the kernels' do
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    meta = session.get_modelmeta().custom_metadata_map
    if metadata_key not in meta:
        raise InputError(f"has no '{metadata_key}' metadata: export it with this project's export command",
                         file=path, field=field)
    return session, json.loads(meta[metadata_key])
