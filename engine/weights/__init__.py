"""The committed ONNX networks (model card: ``engine/weights/README.md``)."""
from pathlib import Path

#: Folder of the committed networks.
WEIGHTS_DIR = Path(__file__).resolve().parent
#: DeCOMPnet's 3D flow network (``configs/flow3d.json``), its 2D ablation and the infilling network.
FLOW3D = WEIGHTS_DIR / "flow3d.onnx"
FLOW2D = WEIGHTS_DIR / "flow2d.onnx"
INFILL = WEIGHTS_DIR / "infill.onnx"
#: The all-pairs-correlation 2D flow network (``models.flow.corrflow``): ``flow2d[estimator=corr]``.
CORRFLOW = WEIGHTS_DIR / "corrflow.onnx"
