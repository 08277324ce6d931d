"""Frame predictors: the interface (``base``), the classic methods (``classic``), DIS optical flow (``dis``),
the renderer's motion vectors (``mvec``), DeCOMPnet (``decomp``) and the registry of method names
(``registry``, where ``decomp[k=v]`` is parsed).

Modules import downhill only: ``base`` (with the CPU backend), ``dis``, ``onnx`` <- ``classic``, ``mvec``,
``decomp``, ``backend`` (the GL backend) <- ``registry`` (which sets a predictor's backend) <- this face, which
re-exports the public names (``from engine.predict import make_predictor, Target``).
"""
from engine.predict.backend import GlFrames
from engine.predict.base import (MAX_EXTRAPOLATION, CpuFrames, Prediction, Predictor, PreparedState, ResidentFrame,
                                 Target, Timer, extrapolation_factor, true_object_flow, warp_and_fill)
from engine.predict.classic import Flow2D, Flow2DState, Oracle, Repeat, Reproject
from engine.predict.decomp import (DEFAULT_MODEL, DecompConfig, DecompPredictor, DecompState, DecompTrueMotion,
                                   FlowNetwork, GateConfig, InfillNetwork, encode_color)
from engine.predict.dis import (DIS_MIN_SIDE, dis_block, dis_calc, dis_estimator, dis_flow, dis_target, encode8,
                                initial_flow, luma8, warp_error)
from engine.predict.mvec import Mvec, MvecConfig, MvecState
from engine.predict.registry import (AUTO, METHODS, decomp_config, make_predictor, method_parts, method_with,
                                     option_parts, resolve_auto, split_methods, use_backend)

__all__ = ["MAX_EXTRAPOLATION", "Prediction", "PreparedState", "Predictor", "Target", "Timer", "extrapolation_factor",
           "true_object_flow", "warp_and_fill", "Flow2D", "Flow2DState", "Oracle", "Repeat", "Reproject",
           "DEFAULT_MODEL", "DecompConfig", "DecompPredictor", "DecompState", "DecompTrueMotion", "FlowNetwork",
           "GateConfig", "InfillNetwork", "encode_color", "DIS_MIN_SIDE", "dis_block", "dis_calc", "dis_estimator",
           "dis_flow", "dis_target", "encode8", "initial_flow", "luma8", "warp_error", "METHODS", "decomp_config",
           "make_predictor", "split_methods", "Mvec", "MvecConfig", "MvecState", "AUTO", "resolve_auto",
           "option_parts", "method_parts", "method_with", "use_backend", "CpuFrames", "GlFrames", "ResidentFrame"]
