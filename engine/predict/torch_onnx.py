"""The engine's exported networks run by torch: the GPU path where onnxruntime has no CUDA provider.

``TorchOnnxSession(path, device)`` reads an ONNX graph (the files ``engine/weights`` ships and the export
commands write, opset 20) and evaluates its nodes one by one with torch operators on ``device`` ("cpu" or
"cuda"). It answers the two calls the engine makes of an onnxruntime session: ``run(None, feeds)`` (numpy
in, numpy out) and ``get_modelmeta().custom_metadata_map``. onnxruntime on the CPU is its oracle
(``tests/predict/test_torch_onnx.py``: every shipped network, the same outputs to float rounding).

Per input signature (names, shapes, dtypes) the first run records which values depend on the inputs' data:
the others (weights, constants, and everything computed from them and from input shapes only: most of the
exported graphs' shape arithmetic) are kept, and later runs evaluate only the data-dependent nodes. On a GPU
those nodes are captured as a CUDA graph when a signature comes a second time, and replayed (no launch per node
from Python), after a check that the replay gives the eager outputs; a graph that cannot be captured or
disagrees runs eagerly instead. A session keeps the ``MAX_PLANS`` most recently used signatures.

Conventions are ONNX's: NCHW / NCDHW tensors, Resize and GridSample coordinates as the attributes say
(``half_pixel`` / ``asymmetric``; ``align_corners``). Only the operators and attributes the shipped graphs use
are implemented; any other is refused when the graph is opened, with the operator named, never run wrongly.
Needs the ``onnx`` and ``torch`` packages (the ``train`` extra), imported only when a session is opened.
"""
from __future__ import annotations

import math
import os
from collections import OrderedDict
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np

from engine.core.errors import InputError

__all__ = ["TorchOnnxSession", "torch_cuda_available", "SUPPORTED_OPS"]


def torch_cuda_available() -> bool:
    """Whether torch and onnx import and torch sees a CUDA device (False where either package is missing)."""
    try:
        import onnx  # noqa: F401
        import torch
    except ImportError:
        return False
    return bool(torch.cuda.is_available())


@dataclass(frozen=True)
class _Meta:
    custom_metadata_map: dict


#: input signatures a session keeps plans (and graphs) for, the most recently used
MAX_PLANS = 16


@dataclass
class _Plan:
    """One input signature's plan: ``static`` values, the ``dynamic`` nodes, and their ``replay`` (a CUDA graph)
    where one was captured and checked."""
    static: dict
    dynamic: list
    replay: Optional[Callable] = None
    uses: int = 1


@dataclass(frozen=True)
class _Node:
    op: str
    inputs: tuple[str, ...]  # "" for an omitted optional input
    outputs: tuple[str, ...]
    attrs: dict


# ONNX TensorProto data types -> torch dtypes (the ones the shipped graphs use, and their neighbours)
_DTYPES = {1: "float32", 2: "uint8", 3: "int8", 5: "int16", 6: "int32", 7: "int64", 9: "bool", 10: "float16",
           11: "float64", 16: "bfloat16"}


def _torch():
    import torch
    return torch


def _ints(t) -> list[int]:
    return [int(v) for v in t.reshape(-1).tolist()]


def _axis(a: int, rank: int) -> int:
    return a + rank if a < 0 else a


def _binary(fn: Callable) -> Callable:
    return lambda n, x, y: [fn(x, y)]


def _div(n, x, y):
    torch = _torch()
    if x.dtype.is_floating_point or y.dtype.is_floating_point:
        return [x / y]
    return [torch.div(x, y, rounding_mode="trunc")]


def _conv(n, x, w, b=None):
    torch, f = _torch(), _torch().nn.functional
    nd = x.dim() - 2
    if n.attrs.get("auto_pad", "NOTSET") != "NOTSET":
        raise InputError(f"Conv auto_pad {n.attrs['auto_pad']} is not supported", field="model")
    pads = list(n.attrs.get("pads", [0] * (2 * nd)))
    begin, end = pads[:nd], pads[nd:]
    if begin != end:  # asymmetric: pad explicitly (torch pads last dims first)
        x = f.pad(x, [p for d in reversed(range(nd)) for p in (begin[d], end[d])])
        begin = [0] * nd
    conv = {1: f.conv1d, 2: f.conv2d, 3: f.conv3d}[nd]
    return [conv(x, w, b, stride=n.attrs.get("strides", [1] * nd), padding=begin,
                 dilation=n.attrs.get("dilations", [1] * nd), groups=int(n.attrs.get("group", 1)))]


def _pool(n, x, kind: str):
    f = _torch().nn.functional
    nd = x.dim() - 2
    kernel = list(n.attrs["kernel_shape"])
    strides = list(n.attrs.get("strides", [1] * nd))
    pads = list(n.attrs.get("pads", [0] * (2 * nd)))
    if pads[:nd] != pads[nd:] or n.attrs.get("auto_pad", "NOTSET") != "NOTSET":
        raise InputError(f"{n.op} with asymmetric or automatic padding is not supported", field="model")
    ceil = bool(n.attrs.get("ceil_mode", 0))
    if kind == "max":
        if any(d != 1 for d in n.attrs.get("dilations", [1] * nd)):
            raise InputError("MaxPool with dilations is not supported", field="model")
        pool = {1: f.max_pool1d, 2: f.max_pool2d, 3: f.max_pool3d}[nd]
        return [pool(x, kernel, strides, pads[:nd], ceil_mode=ceil)]
    pool = {1: f.avg_pool1d, 2: f.avg_pool2d, 3: f.avg_pool3d}[nd]
    include = bool(n.attrs.get("count_include_pad", 0))
    return [pool(x, kernel, strides, pads[:nd], ceil_mode=ceil, count_include_pad=include)]


def _resize(n, x, roi=None, scales=None, sizes=None):
    torch, f = _torch(), _torch().nn.functional
    mode, transform = n.attrs.get("mode", "nearest"), n.attrs.get("coordinate_transformation_mode", "half_pixel")
    nd = x.dim() - 2
    if n.attrs.get("antialias", 0) or n.attrs.get("exclude_outside", 0):
        raise InputError("Resize with antialias or exclude_outside is not supported", field="model")
    if sizes is not None and sizes.numel():
        out = _ints(sizes)
        scale = None
    else:
        factors = [float(v) for v in scales.reshape(-1).tolist()]
        if factors[:2] != [1.0, 1.0]:
            raise InputError("Resize of the batch or channel axis is not supported", field="model")
        scale = factors[2:]
        out = None
    if mode == "linear" and transform == "half_pixel":
        kind = {1: "linear", 2: "bilinear", 3: "trilinear"}[nd]
        if out is not None:
            return [f.interpolate(x, size=out[2:], mode=kind, align_corners=False)]
        return [f.interpolate(x, scale_factor=scale, mode=kind, align_corners=False, recompute_scale_factor=False)]
    if mode == "nearest" and transform == "asymmetric" and n.attrs.get("nearest_mode", "round_prefer_floor") == "floor":
        if out is not None:
            return [f.interpolate(x, size=out[2:], mode="nearest")]
        return [f.interpolate(x, scale_factor=scale, mode="nearest", recompute_scale_factor=False)]
    raise InputError(f"Resize mode {mode} with {transform} coordinates is not supported", field="model")


def _grid_sample(n, x, grid):
    f = _torch().nn.functional
    mode = {"linear": "bilinear", "bilinear": "bilinear", "nearest": "nearest", "cubic": "bicubic",
            "bicubic": "bicubic"}[n.attrs.get("mode", "linear")]
    return [f.grid_sample(x, grid, mode=mode, padding_mode=n.attrs.get("padding_mode", "zeros"),
                          align_corners=bool(n.attrs.get("align_corners", 0)))]


def _pad(n, x, pads, value=None, axes=None):
    f = _torch().nn.functional
    rank = x.dim()
    p = _ints(pads)
    ax = [_axis(a, rank) for a in _ints(axes)] if axes is not None and axes.numel() else list(range(rank))
    half = len(p) // 2
    begin, end = dict(zip(ax, p[:half])), dict(zip(ax, p[half:]))
    flat = []
    for d in reversed(range(rank)):
        flat += [begin.get(d, 0), end.get(d, 0)]
    while len(flat) > 2 and flat[-2:] == [0, 0]:  # torch pads the trailing dims only: drop untouched leading ones
        flat = flat[:-2]
    mode = n.attrs.get("mode", "constant")
    if mode == "constant":
        fill = float(value.reshape(-1)[0]) if value is not None and value.numel() else 0.0
        return [f.pad(x, flat, mode="constant", value=fill)]
    if mode == "edge":
        return [f.pad(x, flat, mode="replicate")]
    if mode == "reflect":
        return [f.pad(x, flat, mode="reflect")]
    raise InputError(f"Pad mode {mode} is not supported", field="model")


def _slice(n, x, starts, ends, axes=None, steps=None):
    rank = x.dim()
    s, e = _ints(starts), _ints(ends)
    ax = [_axis(a, rank) for a in _ints(axes)] if axes is not None and axes.numel() else list(range(len(s)))
    st = _ints(steps) if steps is not None and steps.numel() else [1] * len(s)
    index = [slice(None)] * rank
    for a, b, c, step in zip(ax, s, e, st):
        if step <= 0:
            raise InputError("Slice with a step below 1 is not supported", field="model")
        size = x.shape[a]
        b = max(0, min(size, b + size if b < 0 else b))
        c = max(0, min(size, c + size if c < 0 else c))
        index[a] = slice(b, max(b, c), step)
    return [x[tuple(index)]]


def _reshape(n, x, shape):
    target = _ints(shape)
    if not n.attrs.get("allowzero", 0):
        target = [x.shape[i] if v == 0 else v for i, v in enumerate(target)]
    return [x.reshape(target)]


def _squeeze(n, x, axes=None):
    if axes is None or not axes.numel():
        return [x.squeeze()] if x.dim() else [x]
    for a in sorted((_axis(a, x.dim()) for a in _ints(axes)), reverse=True):
        x = x.squeeze(a)
    return [x]


def _unsqueeze(n, x, axes):
    rank = x.dim() + axes.numel()
    for a in sorted(_axis(a, rank) for a in _ints(axes)):
        x = x.unsqueeze(a)
    return [x]


def _gather(n, x, idx):
    torch = _torch()
    a = _axis(int(n.attrs.get("axis", 0)), x.dim())
    idx = torch.where(idx < 0, idx + x.shape[a], idx)
    out = x.index_select(a, idx.reshape(-1).long())
    return [out.reshape(tuple(x.shape[:a]) + tuple(idx.shape) + tuple(x.shape[a + 1:]))]


def _split(n, x, split=None):
    a = _axis(int(n.attrs.get("axis", 0)), x.dim())
    if split is not None and split.numel():
        return list(x.split(_ints(split), dim=a))
    parts = int(n.attrs.get("num_outputs", len(n.outputs)))
    return list(x.split(math.ceil(x.shape[a] / parts), dim=a))


def _reduce(n, x, axes, kind: str):
    keep = bool(n.attrs.get("keepdims", 1))
    if axes is None or not axes.numel():
        if n.attrs.get("noop_with_empty_axes", 0):
            return [x]
        dims = list(range(x.dim()))
    else:
        dims = [_axis(a, x.dim()) for a in _ints(axes)]
    if kind == "sum":
        return [x.sum(dim=dims, keepdim=keep)]
    out = x
    for d in sorted(dims, reverse=True):
        out = out.amax(dim=d, keepdim=keep)
    return [out]


def _clip(n, x, lo=None, hi=None):
    torch = _torch()
    if lo is not None:
        x = torch.maximum(x, lo.to(x.dtype))
    if hi is not None:
        x = torch.minimum(x, hi.to(x.dtype))
    return [x]


def _cast(n, x):
    torch = _torch()
    to = int(n.attrs["to"])
    if to not in _DTYPES:
        raise InputError(f"Cast to ONNX type {to} is not supported", field="model")
    return [x.to(getattr(torch, _DTYPES[to]))]


def _range(n, start, limit, delta):
    torch = _torch()
    return [torch.arange(start.item(), limit.item(), delta.item(), dtype=start.dtype, device=start.device)]


def _expand(n, x, shape):
    torch = _torch()
    return [x.expand(torch.broadcast_shapes(tuple(x.shape), tuple(_ints(shape))))]


def _shape(n, x):
    torch = _torch()
    dims = list(x.shape)[int(n.attrs.get("start", 0)):n.attrs.get("end", None)]
    return [torch.tensor(dims, dtype=torch.int64, device=x.device)]


def _instance_norm(n, x, scale, bias):
    f = _torch().nn.functional
    return [f.instance_norm(x, weight=scale, bias=bias, eps=float(n.attrs.get("epsilon", 1e-5)))]


def _where(n, c, x, y):
    return [_torch().where(c, x, y)]


def _concat(n, *xs):
    torch = _torch()
    a = int(n.attrs["axis"])
    return [torch.cat([x for x in xs], dim=_axis(a, xs[0].dim()))]


def _transpose(n, x):
    perm = n.attrs.get("perm")
    return [x.permute(*perm) if perm is not None else x.permute(*reversed(range(x.dim())))]


def _softmax(n, x):
    return [_torch().softmax(x, dim=_axis(int(n.attrs.get("axis", -1)), x.dim()))]


def _unary(name: str) -> Callable:
    def run(n, x):
        torch = _torch()
        return [{"Relu": torch.relu, "Tanh": torch.tanh, "Sigmoid": torch.sigmoid, "Sqrt": torch.sqrt,
                 "Reciprocal": torch.reciprocal, "Neg": torch.neg, "Abs": torch.abs, "Not": torch.logical_not,
                 "IsNaN": torch.isnan, "Identity": lambda v: v}[name](x)]
    return run


def _is_inf(n, x):
    torch = _torch()
    pos, neg = int(n.attrs.get("detect_positive", 1)), int(n.attrs.get("detect_negative", 1))
    return [(torch.isposinf(x) if pos else torch.zeros_like(x, dtype=torch.bool))
            | (torch.isneginf(x) if neg else torch.zeros_like(x, dtype=torch.bool))]


def _leaky(n, x):
    return [_torch().nn.functional.leaky_relu(x, float(n.attrs.get("alpha", 0.01)))]


#: ONNX operator -> fn(node, *inputs) -> [outputs]; omitted optional inputs arrive as None
_OPS: dict[str, Callable] = {
    "Add": _binary(lambda x, y: x + y), "Sub": _binary(lambda x, y: x - y), "Mul": _binary(lambda x, y: x * y),
    "Div": _div, "MatMul": _binary(lambda x, y: _torch().matmul(x, y)),
    "Greater": _binary(lambda x, y: x > y), "GreaterOrEqual": _binary(lambda x, y: x >= y),
    "Less": _binary(lambda x, y: x < y), "And": _binary(lambda x, y: x & y),
    "Conv": _conv, "MaxPool": lambda n, x: _pool(n, x, "max"), "AveragePool": lambda n, x: _pool(n, x, "avg"),
    "Resize": _resize, "GridSample": _grid_sample, "Pad": _pad, "Slice": _slice, "Reshape": _reshape,
    "Squeeze": _squeeze, "Unsqueeze": _unsqueeze, "Gather": _gather, "Split": _split,
    "ReduceSum": lambda n, x, axes=None: _reduce(n, x, axes, "sum"),
    "ReduceMax": lambda n, x, axes=None: _reduce(n, x, axes, "max"),
    "Clip": _clip, "Cast": _cast, "CastLike": lambda n, x, like: [x.to(like.dtype)], "Range": _range,
    "Expand": _expand, "Shape": _shape, "InstanceNormalization": _instance_norm, "Where": _where,
    "Concat": _concat, "Transpose": _transpose, "Softmax": _softmax, "LeakyRelu": _leaky, "IsInf": _is_inf,
    **{name: _unary(name) for name in ("Relu", "Tanh", "Sigmoid", "Sqrt", "Reciprocal", "Neg", "Abs", "Not",
                                       "IsNaN", "Identity")},
}

#: the operators ``TorchOnnxSession`` runs (``Constant`` is folded when the graph is read)
SUPPORTED_OPS = frozenset(_OPS) | {"Constant"}

#: operator -> the positions of its inputs that are read as Python numbers (axes, shapes, pads, scales, bounds):
#: a plan hands those of them that do not depend on the data over as host (CPU) copies, so that a run on a GPU
#: does not wait for a device-to-host copy, which would stall the queue of kernels, at each such node
_HOST_INPUTS = {"Slice": (1, 2, 3, 4), "Reshape": (1,), "Squeeze": (1,), "Unsqueeze": (1,), "Pad": (1, 2, 3),
                "Expand": (1,), "ReduceSum": (1,), "ReduceMax": (1,), "Split": (1,), "Resize": (1, 2, 3)}


def _attribute(attr) -> Any:
    from onnx import helper, numpy_helper
    value = helper.get_attribute_value(attr)
    if isinstance(value, bytes):
        return value.decode()
    if hasattr(value, "raw_data") or hasattr(value, "dims"):  # a TensorProto
        return numpy_helper.to_array(value)
    if isinstance(value, (list, tuple)):
        return [v.decode() if isinstance(v, bytes) else v for v in value]
    return value


def _constant_value(node) -> np.ndarray:
    from onnx import numpy_helper
    for attr in node.attribute:
        if attr.name == "value":
            return numpy_helper.to_array(attr.t)
        if attr.name in ("value_float", "value_int"):
            return np.array(attr.f if attr.name == "value_float" else attr.i,
                            np.float32 if attr.name == "value_float" else np.int64)
        if attr.name in ("value_floats", "value_ints"):
            return np.array(list(attr.floats) if attr.name == "value_floats" else list(attr.ints),
                            np.float32 if attr.name == "value_floats" else np.int64)
    raise InputError(f"Constant node {node.name!r} has no supported value attribute", field="model")


class TorchOnnxSession:
    """An exported engine network evaluated by torch on ``device`` (see the module docstring).

    Raises:
        InputError: the file cannot be read as ONNX, or uses an operator this runner does not implement.
    """

    def __init__(self, path: str | Path, device: str = "cpu", threads: int = 0) -> None:
        import onnx
        torch = _torch()
        self.path = Path(path)
        try:
            model = onnx.load(str(self.path))
        except Exception as exc:  # a truncated or foreign file: one line naming it
            raise InputError(f"cannot be read as an ONNX model ({exc.__class__.__name__})", file=self.path,
                             field="model") from None
        self.device = torch.device(device)
        if threads and self.device.type == "cpu":
            torch.set_num_threads(int(threads))
        self._meta = _Meta({p.key: p.value for p in model.metadata_props})
        self.input_names = [i.name for i in model.graph.input]
        self.output_names = [o.name for o in model.graph.output]
        self._constants: dict[str, Any] = {}
        for init in model.graph.initializer:
            self._constants[init.name] = self._tensor(onnx.numpy_helper.to_array(init))
        self._nodes: list[_Node] = []
        unsupported = set()
        for node in model.graph.node:
            if node.domain not in ("", "ai.onnx"):
                unsupported.add(f"{node.domain}.{node.op_type}")
            elif node.op_type == "Constant":
                self._constants[node.output[0]] = self._tensor(_constant_value(node))
            elif node.op_type not in _OPS:
                unsupported.add(node.op_type)
            else:
                self._nodes.append(_Node(node.op_type, tuple(node.input), tuple(node.output),
                                         {a.name: _attribute(a) for a in node.attribute}))
        if unsupported:
            raise InputError(f"uses operators the torch runner does not implement: {', '.join(sorted(unsupported))}",
                             file=self.path, field="model")
        self._plans: OrderedDict[tuple, _Plan] = OrderedDict()
        #: on a GPU each signature's nodes are captured as a CUDA graph and replayed (no launch per node from
        #: Python); ``INTERLEAVE_TORCH_GRAPHS=0`` runs them one by one
        self.graphs = self.device.type == "cuda" and os.environ.get("INTERLEAVE_TORCH_GRAPHS", "1") != "0"

    def _tensor(self, array: np.ndarray):
        torch = _torch()
        return torch.from_numpy(np.array(array, copy=True, order="C")).to(self.device)

    def get_modelmeta(self) -> _Meta:
        """The graph's metadata, as onnxruntime's ``InferenceSession.get_modelmeta`` gives it."""
        return self._meta

    def _evaluate(self, nodes: Sequence[_Node], env: dict) -> None:
        for node in nodes:
            args = [env[name] if name else None for name in node.inputs]
            while args and args[-1] is None:  # trailing omitted optional inputs
                args.pop()
            for name, value in zip(node.outputs, _OPS[node.op](node, *args)):
                if name:
                    env[name] = value

    def _plan(self, feeds: dict) -> tuple["_Plan", Optional[list]]:
        """For the signature of ``feeds``: the plan (the values that do not depend on the inputs' data, computed
        once; the nodes that do, in graph order; on a GPU their replay, ``_capture``), and the outputs for
        ``feeds`` where making or checking the plan computed them (None: the caller runs the plan)."""
        key = tuple((name, tuple(feeds[name].shape), str(feeds[name].dtype)) for name in self.input_names)
        plan = self._plans.get(key)
        if plan is None:
            static = dict(self._constants)
            dynamic_names = set(self.input_names)
            dynamic: list[_Node] = []
            probe = {**static, **feeds}
            for node in self._nodes:
                self._evaluate([node], probe)
                if node.op != "Shape" and any(name in dynamic_names for name in node.inputs if name):
                    dynamic.append(self._with_host_inputs(node, static, dynamic_names))
                    dynamic_names.update(node.outputs)
                else:
                    static.update({name: probe[name] for name in node.outputs if name})
            self._plans[key] = _Plan(static, dynamic)
            while len(self._plans) > MAX_PLANS:  # the least recently used signature goes (sizes vary: decomp's boxes)
                self._plans.popitem(last=False)
            return self._plans[key], [probe[name] for name in self.output_names]
        self._plans.move_to_end(key)
        plan.uses += 1
        if self.graphs and plan.uses == 2:  # a size seen again: worth a graph (a box seen once is not)
            want = self._eager(plan, feeds)
            plan.replay = self._checked_replay(plan, feeds, want)
            return plan, want
        return plan, None

    def _eager(self, plan: "_Plan", tensors: dict) -> list:
        env = {**plan.static, **tensors}
        self._evaluate(plan.dynamic, env)
        return [env[name] for name in self.output_names]

    def _checked_replay(self, plan: "_Plan", tensors: dict, want: list) -> Optional[Callable]:
        """``_capture``'s replay of ``plan``, kept only when it gives the eager outputs ``want`` for ``tensors``
        (to 1e-4 of the largest value); None (eager runs) when capture fails or disagrees."""
        torch = _torch()
        try:
            replay = self._capture(plan, tensors)
            got = replay(tensors)
        except Exception:  # an operator that cannot be captured (a host read, an allocation): eager runs
            return None
        for a, b in zip(want, got):
            scale = max(1.0, float(a.abs().max())) if a.numel() and a.dtype.is_floating_point else 1.0
            if a.shape != b.shape or not torch.allclose(a.double(), b.double(), rtol=0, atol=1e-4 * scale):
                return None
        return replay

    def _capture(self, plan: "_Plan", tensors: dict) -> Callable:
        """A CUDA graph of ``plan``'s nodes: ``replay(tensors)`` copies the inputs into the graph's buffers,
        replays it and returns its output buffers (overwritten by the next replay)."""
        torch = _torch()
        inputs = {name: tensor.clone() for name, tensor in tensors.items()}
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):  # warm-up off the capture, as torch.cuda.graph requires
            for _ in range(2):
                self._eager(plan, inputs)
        torch.cuda.current_stream().wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            outputs = self._eager(plan, inputs)

        def replay(feeds: dict) -> list:
            for name, tensor in feeds.items():
                inputs[name].copy_(tensor)
            graph.replay()
            return outputs
        return replay

    @staticmethod
    def _with_host_inputs(node: _Node, static: dict, dynamic_names: set) -> _Node:
        """``node`` reading its number-like inputs (``_HOST_INPUTS``) that do not depend on the data from host
        copies, added to ``static`` under the name ``NAME@host``."""
        inputs = list(node.inputs)
        for i in _HOST_INPUTS.get(node.op, ()):
            name = inputs[i] if i < len(inputs) else ""
            if name and name not in dynamic_names:
                static.setdefault(f"{name}@host", static[name].cpu())
                inputs[i] = f"{name}@host"
        return _Node(node.op, tuple(inputs), node.outputs, node.attrs)

    def run(self, output_names: Optional[Sequence[str]], feeds: dict) -> list[np.ndarray]:
        """The graph's outputs (all of them for ``output_names`` None) for the numpy ``feeds``, as numpy arrays."""
        torch = _torch()
        missing = [name for name in self.input_names if name not in feeds]
        if missing:
            raise InputError(f"missing inputs {missing}", file=self.path, field="model")
        with torch.inference_mode():
            tensors = {name: self._tensor(np.asarray(feeds[name])) for name in self.input_names}
            plan, outputs = self._plan(tensors)
            if outputs is None:
                outputs = (plan.replay or partial(self._eager, plan))(tensors)
            outputs = dict(zip(self.output_names, outputs))
            names = self.output_names if output_names is None else list(output_names)
            return [outputs[name].detach().cpu().numpy() for name in names]
