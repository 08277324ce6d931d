"""DeCOMPnet in the engine (thesis Ch. 6): MPIs, the motion gate, the 3D flow network, splatting, infilling.

Modules, lowest first: ``gate`` (the motion gate), ``upsample`` (flow upsampling; its numpy oracle in
``reference``), ``network`` (the ONNX flow network), ``infill`` (the infilling network), ``predictor``
(``DecompConfig``, the stages and ``DecompPredictor``).
"""
from engine.predict.decomp.gate import GateConfig, encode_color, motion_boxes, motion_residual
from engine.predict.decomp.infill import DEFAULT_INFILL_MODEL, InfillNetwork
from engine.predict.decomp.network import DEFAULT_MODEL, METADATA_KEY, FlowNetwork
from engine.predict.decomp.predictor import DecompConfig, DecompPredictor, DecompState, DecompTrueMotion
from engine.predict.decomp.upsample import upsample_flow

__all__ = ["GateConfig", "encode_color", "motion_boxes", "motion_residual", "DEFAULT_INFILL_MODEL",
           "InfillNetwork", "DEFAULT_MODEL", "METADATA_KEY", "FlowNetwork", "DecompConfig", "DecompPredictor",
           "DecompState", "DecompTrueMotion", "upsample_flow"]
