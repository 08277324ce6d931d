"""Dense optical flow on the GPU: a pyramidal DIS-style estimator (Kroeger et al. 2016, "Fast optical flow
using dense inverse search") as OpenGL compute passes, for ``flow2d`` on the GL backend.

Convention (that of ``engine.predict.dis.dis_calc``): the flow from ``first`` to ``second`` is (H, W, 2)
float32 pixels (du, dv), x right, y down, pixel centres at +0.5: pixel (y, x) of ``first`` shows what
``second`` shows at (x + 0.5 + du, y + 0.5 + dv). Both images are read as DIS reads them: linear RGB
display-encoded to 8 bits, then OpenCV's 8-bit luma (``engine.predict.dis.luma8``; pass ``flow_luma``
computes it on the GPU from the colour buffer, bit-exact).

Passes (``shaders/flow_*.comp``, one per pass): ``flow_luma`` (8-bit luma, level 0), ``flow_downsample``
(2 x 2 block means, the pyramid: level l + 1 is ceil(level l / 2) a side, x_l + 0.5 = 2 (x_{l+1} + 0.5)),
then per level from the coarsest to ``finest_level``: ``flow_upsample`` (the coarser level's flow, bilinear,
doubled), ``flow_patch`` (inverse search per patch, ``GlFlowConfig.sweeps`` times, later sweeps starting from
the best of the patch's and its 4 neighbours' flows: a parallel stand-in for DIS's sequential spatial
propagation), ``flow_densify`` (patch flows averaged per pixel, weighted by their photometric error), and
DIS's variational refinement (``flow_refine_warp``, ``flow_refine_derivs``, then per fixed-point iteration
``flow_refine_system`` and red-black ``flow_refine_sor``, finally ``flow_refine_apply``); last,
``flow_upsample`` to the full size. Any size from 1 x 1 works (a level smaller than a patch is read with
clamped borders: no padding as ``dis_calc`` needs).

Fewer dispatches, the same arithmetic (on a GPU by default; ``dispatch_counts`` counts them: 399 an estimate
at 1920x1080 by the passes above, 73 so): the coarse levels (at most ``GlFlowConfig.coarse_pixels`` pixels)
run all their steps in one dispatch of one workgroup, ``flow_coarse``, with a barrier between the steps; the
SOR of the other levels runs as ``flow_refine_tile``, up to ``SOR_STEPS`` red-black iterations a dispatch on
a tile in shared memory, the system folded into the first (``GlFlowConfig.sor``). On a small level each
dispatch leaves a GPU almost idle and costs the CPU a Python call. Oracles: ``luma8`` for ``flow_luma``, the
numpy twins of ``reference.py`` for every other pass (``flow_downsample``, ``flow_upsample``, ``flow_patch``,
``flow_densify``, ``flow_refine_*``, ``level_reference`` and ``coarse_reference`` for ``flow_coarse``).
This is not OpenCV's code: ``tools/bench_gl_flow.py`` measures the end-point error against OpenCV DIS medium
and the true motion.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from engine.core.checks import checked_array, checked_size
from engine.core.colorspace import ENCODE8_BUCKETS
from engine.core.errors import InputError
from engine.geometry.backends.gl.context import LOCAL_SIZE, GlContext, shared_context
from engine.geometry.backends.gl.frame import GlFlow, GlImage, encode8_table_rows

__all__ = ["GlFlowConfig", "GlOpticalFlow", "pyramid_levels", "coarse_level", "dispatch_counts", "PATCH_LANES",
           "SEARCHES", "SORS", "SOR_TILE", "SOR_STEPS", "COARSE_PIXELS", "sor_chunks",
           "refine_level"]

#: Invocations a patch is spread over by the cooperative inverse search (pass ``flow_patch_group``).
PATCH_LANES = 64
#: ``GlFlowConfig.coarse_pixels`` on a GPU: the levels of at most 32 pixels an invocation of ``flow_coarse``'s
#: workgroup (at 1920x1080 levels 4 to 6, 68 x 120 and smaller; the patches of a level at most 4 an invocation).
COARSE_PIXELS = 32 * LOCAL_SIZE
#: Side of the tile of pass ``flow_refine_tile`` (TILE there: a workgroup of ``LOCAL_SIZE`` = TILE^2 pixels).
SOR_TILE = 16
#: Most SOR iterations one ``flow_refine_tile`` dispatch takes: its shared memory (du and weights of the tile and
#: 2 x 4 rings, the systems of 7) is 30 KB, under the 32 KB every GL 4.3 context has.
SOR_STEPS = 4
#: How the refinement's red-black SOR runs: ``passes``, a fixed-point iteration as a ``flow_refine_system``
#: dispatch and two ``flow_refine_sor`` dispatches (red, black) per SOR iteration; ``tile``, one
#: ``flow_refine_tile`` dispatch per up to ``SOR_STEPS`` SOR iterations (``sor_chunks``; in a tile in shared
#: memory, the system folded into the first: the same arithmetic); ``auto``, ``tile`` on a hardware GPU and
#: ``passes`` on a software renderer (where a workgroup's barriers switch between its invocations on one CPU
#: thread: slower there).
SORS = ("auto", "passes", "tile")
#: How the inverse search runs: ``thread``, a patch an invocation (pass ``flow_patch``); ``group``, a patch
#: over ``PATCH_LANES`` invocations with its sums reduced in shared memory (``flow_patch_group``); ``auto``,
#: ``group`` on a hardware GPU and ``thread`` on a software renderer.
SEARCHES = ("auto", "thread", "group")


@dataclass(frozen=True)
class GlFlowConfig:
    """Parameters of ``GlOpticalFlow``. Defaults: DIS medium's patch, stride, finest level and refinement;
    iterations and sweeps chosen on validation sequences (docs/results/2026-11-25-gl-flow.md)."""

    patch_size: int = 8
    """Side of a patch, pixels of its pyramid level."""
    patch_stride: int = 3
    """Distance between neighbouring patches' origins, pixels (1 .. patch_size)."""
    finest_level: int = 1
    """Finest pyramid level searched (0: full resolution; level l is 2^l times smaller per axis); the flow
    there is upsampled bilinearly to the full size."""
    iterations: int = 16
    """Gauss-Newton iterations of the inverse search per patch and sweep."""
    sweeps: int = 4
    """Inverse searches per level; each after the first starts from the best of its patch's and the 4
    neighbouring patches' previous flows."""
    refine_iterations: int = 5
    """Fixed-point iterations of the variational refinement per level (0: none)."""
    sor_iterations: int = 5
    """Red-black SOR iterations per fixed-point iteration."""
    alpha: float = 20.0
    """Refinement: weight of the smoothness term (DIS's default)."""
    delta: float = 5.0
    """Refinement: weight of the colour constancy term (DIS's default)."""
    gamma: float = 10.0
    """Refinement: weight of the gradient constancy term (DIS's default)."""
    omega: float = 1.6
    """Refinement: SOR relaxation factor (0 < omega < 2)."""
    search: str = "auto"
    """How the inverse search runs (``SEARCHES``): the same search, its sums in another order."""
    sor: str = "auto"
    """How the refinement's SOR runs (``SORS``): the same arithmetic in fewer dispatches."""
    coarse_pixels: int | None = None
    """Levels of at most this many pixels, from the coarsest down, run in one dispatch (pass ``flow_coarse``:
    one workgroup of ``LOCAL_SIZE`` invocations, one patch an invocation as ``thread``); 0: every level by its
    passes; None: ``COARSE_PIXELS`` on a hardware GPU, 0 on a software renderer (which runs a workgroup on
    one CPU thread: slower there, docs/results/2026-11-28-gpu-flow-search.md)."""

    def __post_init__(self) -> None:
        for name, low in (("patch_size", 1), ("patch_stride", 1), ("finest_level", 0), ("iterations", 0),
                          ("sweeps", 1), ("refine_iterations", 0), ("sor_iterations", 0), ("coarse_pixels", 0)):
            value = getattr(self, name)
            if name == "coarse_pixels" and value is None:
                continue
            if not isinstance(value, (int, np.integer)) or value < low:
                raise InputError(f"must be an integer >= {low}, got {value!r}", field=name)
        for name in ("alpha", "delta", "gamma", "omega"):
            value = getattr(self, name)
            if not isinstance(value, (int, float, np.floating, np.integer)) or not 0.0 <= value < math.inf:
                raise InputError(f"must be a finite number >= 0, got {value!r}", field=name)
        if not 0.0 < self.omega < 2.0:
            raise InputError(f"must be in (0, 2), got {self.omega!r}", field="omega")
        for name, allowed in (("search", SEARCHES), ("sor", SORS)):
            if getattr(self, name) not in allowed:
                raise InputError(f"must be one of {', '.join(allowed)}, got {getattr(self, name)!r}", field=name)
        if self.patch_stride > self.patch_size:
            raise InputError(f"must be <= patch_size {self.patch_size}, got {self.patch_stride}",
                             field="patch_stride")


def pyramid_levels(shape: tuple[int, int], config: GlFlowConfig) -> tuple[list[tuple[int, int]], int, int]:
    """(sizes of levels 0 .. coarsest, coarsest level, finest level searched) for an image of ``shape`` (H, W).

    Level l + 1 is ceil(level l / 2) per axis. The coarsest level is DIS's choice,
    round(log2(max(H, W) / (4 patch))) capped at floor(log2(min(H, W) / patch)) and at least 0; the finest
    searched is ``config.finest_level`` capped at the coarsest."""
    h, w = shape
    p = config.patch_size
    coarsest = min(int(math.log2(max(h, w) / (4.0 * p)) + 0.5) if max(h, w) >= 4 * p else 0,
                   math.floor(math.log2(min(h, w) / p)) if min(h, w) >= p else 0)
    coarsest = max(coarsest, 0)
    sizes = [(h, w)]
    for _ in range(coarsest):
        sizes.append(((sizes[-1][0] + 1) // 2, (sizes[-1][1] + 1) // 2))
    return sizes, coarsest, min(config.finest_level, coarsest)


def sor_chunks(sor_iterations: int) -> list[int]:
    """The SOR iterations of each ``flow_refine_tile`` dispatch of a fixed-point iteration: ``sor_iterations`` in
    as few dispatches of at most ``SOR_STEPS`` as it takes, as even as they go (5: 3 and 2; a dispatch's shared
    work grows with the square of its tile and rings)."""
    count = -(-sor_iterations // SOR_STEPS)
    return [sor_iterations // count + (1 if k < sor_iterations % count else 0) for k in range(count)]


def resolved_coarse_pixels(config: GlFlowConfig, software: bool) -> int:
    """``config.coarse_pixels``, None resolved: ``COARSE_PIXELS`` on a hardware GPU, 0 on a software renderer."""
    if config.coarse_pixels is not None:
        return int(config.coarse_pixels)
    return 0 if software else COARSE_PIXELS


def coarse_level(sizes: list[tuple[int, int]], coarsest: int, finest: int, coarse_pixels: int) -> int | None:
    """The finest level pass ``flow_coarse`` runs (it runs the coarsest down to it): the finest level >= ``finest``
    of at most ``coarse_pixels`` pixels, None when the coarsest has more."""
    last = None
    for level in range(coarsest, finest - 1, -1):
        if sizes[level][0] * sizes[level][1] > coarse_pixels:
            break
        last = level
    return last


def dispatch_counts(shape: tuple[int, int], config: GlFlowConfig = GlFlowConfig(), software: bool = False
                    ) -> dict[str, int]:
    """Compute dispatches of one ``GlOpticalFlow.estimate`` of an (H, W) pair, per pass (the names
    ``GlContext.pass_timing`` reports; ``clear_words`` clears the coarsest level's initial flow), with ``auto``
    and None settings resolved as on a hardware GPU or, with ``software``, a software renderer. Each dispatch
    costs a GPU a launch and a storage barrier, and the CPU a Python call: on the small levels that is most of
    their time."""
    sizes, coarsest, finest = pyramid_levels(shape, config)
    search = config.search if config.search != "auto" else ("thread" if software else "group")
    patch = "flow_patch" if search == "thread" else "flow_patch_group"
    sor = config.sor if config.sor != "auto" else ("passes" if software else "tile")
    counts = {"flow_luma": 2, "flow_downsample": 2 * coarsest, "flow_upsample": 1}
    last = coarse_level(sizes, coarsest, finest, resolved_coarse_pixels(config, software))
    if last is not None:
        counts["flow_coarse"] = 1
    for level in range(coarsest if last is None else last - 1, finest - 1, -1):
        add = {"clear_words" if level == coarsest else "flow_upsample": 1, patch: config.sweeps, "flow_densify": 1}
        if config.refine_iterations:
            add.update({"flow_refine_warp": 1, "flow_refine_derivs": 1, "flow_refine_apply": 1,
                        "flow_refine_system": config.refine_iterations,
                        "flow_refine_sor": 2 * config.refine_iterations * config.sor_iterations})
            if sor == "tile":
                add["flow_refine_system"] = add["flow_refine_sor"] = 0
                add["flow_refine_tile"] = config.refine_iterations * len(sor_chunks(config.sor_iterations))
        for name, n in add.items():
            counts[name] = counts.get(name, 0) + n
    return {name: n for name, n in counts.items() if n}


def refine_level(gl: GlContext, size: tuple[int, int], uniforms: dict, defines: dict, config: GlFlowConfig,
                 sor: str, increments: list) -> None:
    """The refinement's dispatches on a level of ``size`` (H, W) whose buffers are bound (the pyramids at 1 and 3,
    the flow at 6, work buffers at 10 to 12, ``increments[0]``, the increment, at 9): ``flow_refine_warp``,
    ``flow_refine_derivs``, per fixed-point iteration of ``config`` the SOR (``sor``: ``passes`` or ``tile``;
    ``tile`` alternates ``increments``, two buffers of 8 H W bytes, between bindings 9 and 13), then
    ``flow_refine_apply``. GL thread only."""
    n = size[0] * size[1]
    gl.dispatch(gl.program("flow_refine_warp", defines), n, uniforms)
    gl.dispatch(gl.program("flow_refine_derivs", defines), n, uniforms)
    if sor == "tile":
        increments = list(increments)
        tiles = -(-size[0] // SOR_TILE) * -(-size[1] // SOR_TILE)
        for _ in range(config.refine_iterations):
            for index, steps in enumerate(sor_chunks(config.sor_iterations)):
                increments[0].bind_to_storage_buffer(9)
                increments[1].bind_to_storage_buffer(13)
                program = gl.program("flow_refine_tile", {**defines, "STEPS": steps,
                                                          **({"SYSTEM": 1} if index == 0 else {})})
                gl.dispatch_groups(program, tiles, uniforms)
                increments.reverse()
        increments[0].bind_to_storage_buffer(9)
    else:
        system, step = gl.program("flow_refine_system", defines), gl.program("flow_refine_sor", defines)
        for _ in range(config.refine_iterations):
            gl.dispatch(system, n, uniforms)
            for _ in range(config.sor_iterations):
                for parity in (0, 1):
                    gl.dispatch(step, n, {**uniforms, "parity": parity})
    gl.dispatch(gl.program("flow_refine_apply", defines), n, uniforms)


class GlOpticalFlow:
    """Dense optical flow between two images on a ``GlContext`` (the shared one by default).

    >>> flow = GlOpticalFlow()                                     # doctest: +SKIP
    >>> u = flow.estimate(color_n, warped_n_minus_k)  # (H, W, 2) u(n -> n-k)  # doctest: +SKIP
    """

    def __init__(self, gl: GlContext | None = None, config: GlFlowConfig = GlFlowConfig()) -> None:
        if not isinstance(config, GlFlowConfig):
            raise InputError(f"must be a GlFlowConfig, got {type(config).__name__}", field="config")
        self.gl = shared_context() if gl is None else gl
        self.config = config
        #: the inverse search this estimator runs: ``thread`` or ``group`` (``GlFlowConfig.search``)
        self.search = config.search if config.search != "auto" else ("thread" if self.gl.software else "group")
        #: the refinement's SOR this estimator runs: ``passes`` or ``tile`` (``GlFlowConfig.sor``)
        self.sor = config.sor if config.sor != "auto" else ("passes" if self.gl.software else "tile")
        #: the levels of at most this many pixels run in pass ``flow_coarse`` (``GlFlowConfig.coarse_pixels``)
        self.coarse_pixels = resolved_coarse_pixels(config, self.gl.software)
        self._pool: dict = {}

    def estimate(self, first: np.ndarray | GlImage, second: np.ndarray | GlImage, *,
                 gpu_ms: dict | None = None, as_gl: bool = False) -> np.ndarray | GlFlow:
        """Flow from ``first`` to ``second``: (H, W, 2) float32 pixels, or with ``as_gl`` a ``GlFlow`` (channels
        2) that ``GlFrameWarper.warp_and_fill`` takes. Each image is (H, W, 3) float32 linear RGB or a
        ``GlImage`` (its colour buffer is read, nothing uploaded). With ``gpu_ms``, the GPU milliseconds of the
        stages ``luma``, ``pyramid``, ``search`` and ``readback`` are added to it."""
        sizes: dict = {}
        buffers, owned = [], []
        for name, image in (("first", first), ("second", second)):
            if isinstance(image, GlImage):
                if image.gl is not self.gl:
                    raise InputError("is a GlImage of another GL context", field=name)
                h, w = image.shape
                for dim, n in (("H", h), ("W", w)):
                    if sizes.setdefault(dim, n) != n:
                        raise InputError(f"has {dim} = {n}, expected {dim} = {sizes[dim]} (GlImage of shape "
                                         f"{image.shape})", field=name)
                buffers.append(image.color)
            else:
                color = np.ascontiguousarray(checked_array(image, name, ("H", "W", 3), sizes))
                buffers.append(color)
        shape = (sizes["H"], sizes["W"])

        def run():
            gpu = []
            for buf in buffers:
                if isinstance(buf, np.ndarray):
                    owned.append(self.gl.new_buffer(data=buf))
                    gpu.append(owned[-1])
                else:
                    gpu.append(buf)
            try:
                return self._estimate(gpu[0], gpu[1], shape, gpu_ms, as_gl)
            finally:
                self.gl.discard(owned)
        return self.gl.call(run)

    def luma(self, image: np.ndarray | GlImage) -> np.ndarray:
        """(H, W) uint8 luma of ``image`` ((H, W, 3) float32 linear RGB or a ``GlImage``) as pass ``flow_luma``
        computes it on the GPU: equal to ``engine.predict.dis.luma8``."""
        if isinstance(image, GlImage):
            if image.gl is not self.gl:
                raise InputError("is a GlImage of another GL context", field="image")
            shape, color = image.shape, None
        else:
            color = np.ascontiguousarray(checked_array(image, "image", ("H", "W", 3), {}))
            shape = color.shape[:2]

        n = shape[0] * shape[1]
        values = np.empty(n, np.float32)

        def run():
            buf = image.color if color is None else self.gl.new_buffer(data=color)
            try:
                self._luma(buf, self.gl.buffer(self._pool, "first", 4 * n), n).read_into(values, size=values.nbytes)
            finally:
                if color is not None:
                    self.gl.discard([buf])
        self.gl.call(run)
        return values.reshape(shape).astype(np.uint8)

    def _luma(self, color, luma, n: int):
        """Run pass ``flow_luma``: ``n`` pixels of the colour buffer -> level 0 of the pyramid buffer ``luma``."""
        table = self._pool.get("table")
        if table is None:
            table = self._pool["table"] = self.gl.ctx.buffer(encode8_table_rows())
        table.bind_to_storage_buffer(2)
        color.bind_to_storage_buffer(0)
        luma.bind_to_storage_buffer(1)
        self.gl.dispatch(self.gl.program("flow_luma", {"BUCKETS": ENCODE8_BUCKETS}), n, {"count": n})
        return luma

    def lumas(self) -> tuple:
        """The 8-bit lumas of the last estimate's two images, (H, W) float buffers (level 0 of its pyramids),
        valid until the next estimate; GL thread only (``engine.geometry.backends.gl.trust`` reads them)."""
        return self._pool["first"], self._pool["second"]

    def estimate_buffers(self, first_buffer, second_buffer, shape: tuple[int, int], *,
                         gpu_ms: dict | None = None, as_gl: bool = False) -> np.ndarray | GlFlow:
        """``estimate`` on colour already on the GPU: moderngl buffers of this context holding (H, W, 3) float32
        linear RGB each (e.g. the colour of a ``GlPrediction``: a frame warped and left on the GPU), ``shape`` =
        (H, W). A ``GlImage``'s buffer lives as long as the ``GlImage``: keep it referenced until this returns."""
        h, w = checked_size(shape, "shape")
        for name, buf in (("first_buffer", first_buffer), ("second_buffer", second_buffer)):
            if getattr(buf, "size", -1) < 12 * h * w:
                raise InputError(f"must hold (H, W, 3) float32 = {12 * h * w} bytes for shape {(h, w)}, got "
                                 f"{getattr(buf, 'size', type(buf).__name__)}", field=name)
        return self.gl.call(self._estimate, first_buffer, second_buffer, (h, w), gpu_ms, as_gl)

    def _estimate(self, first_buffer, second_buffer, shape: tuple[int, int], gpu_ms: dict | None, as_gl: bool):
        gl, pool, config = self.gl, self._pool, self.config
        h, w = shape
        n = h * w
        sizes, coarsest, finest = pyramid_levels(shape, config)
        offsets = np.cumsum([0] + [a * b for a, b in sizes]).tolist()
        defines = {"PATCH": config.patch_size}
        with gl.timing(gpu_ms):
            pyramids = [gl.buffer(pool, key, 4 * offsets[-1]) for key in ("first", "second")]
            with gl.gpu_stage("luma"):
                for color, pyramid in zip((first_buffer, second_buffer), pyramids):
                    self._luma(color, pyramid, n)
            with gl.gpu_stage("pyramid"):
                down = gl.program("flow_downsample")
                for pyramid in pyramids:
                    pyramid.bind_to_storage_buffer(1)
                    for level in range(coarsest):
                        gl.dispatch(down, sizes[level + 1][0] * sizes[level + 1][1],
                                    {"src_size": sizes[level], "dst_size": sizes[level + 1],
                                     "src_offset": offsets[level], "dst_offset": offsets[level + 1]})
            largest = max(a * b for a, b in sizes[finest:])
            init, dense = (gl.buffer(pool, key, 8 * largest) for key in ("init", "dense"))
            patch_flows = [gl.buffer(pool, key, 8 * largest) for key in ("patches", "patches_prev")]
            out = gl.new_buffer(8 * n) if as_gl else gl.buffer(pool, "out", 8 * n)
            with gl.gpu_stage("search"):
                pyramids[0].bind_to_storage_buffer(1)
                pyramids[1].bind_to_storage_buffer(3)
                up = gl.program("flow_upsample")
                last = coarse_level(sizes, coarsest, finest, self.coarse_pixels)
                if last is not None:
                    self._coarse(sizes, coarsest, last, defines, init, dense, patch_flows)
                for level in range(coarsest if last is None else last - 1, finest - 1, -1):
                    lh, lw = sizes[level]
                    if level == coarsest:
                        gl.clear_words(init, 8 * lh * lw)
                    else:
                        dense.bind_to_storage_buffer(6)
                        init.bind_to_storage_buffer(7)
                        gl.dispatch(up, lh * lw, {"src_size": sizes[level + 1], "dst_size": (lh, lw), "scale": 2.0})
                    self._search_level(sizes[level], offsets[level], defines, init, dense, patch_flows)
                dense.bind_to_storage_buffer(6)
                out.bind_to_storage_buffer(7)
                gl.dispatch(up, n, {"src_size": sizes[finest], "dst_size": (h, w), "scale": float(2 ** finest)})
            if as_gl:
                result = GlFlow((h, w), 2, out, gl)
            else:
                result = np.empty((h, w, 2), np.float32)
                with gl.gpu_stage("readback"):
                    out.read_into(result, size=result.nbytes)
        return result

    def _coarse(self, sizes: list, coarsest: int, last: int, defines: dict, init, dense, patch_flows) -> None:
        """Pass ``flow_coarse``: levels ``coarsest`` down to ``last`` in one workgroup; their dense flow -> ``dense``
        (level ``last``'s, where the passes of the finer levels read it)."""
        gl, config = self.gl, self.config
        n = sizes[last][0] * sizes[last][1]  # the largest level of the pass
        init.bind_to_storage_buffer(4)
        patch_flows[0].bind_to_storage_buffer(5)
        patch_flows[1].bind_to_storage_buffer(8)
        dense.bind_to_storage_buffer(6)
        self._refine_buffers(n)
        h, w = sizes[0]
        gl.dispatch_groups(gl.program("flow_coarse", defines), 1, {
            "full_size": (h, w), "coarsest": coarsest, "last": last, "stride": config.patch_stride,
            "iterations": config.iterations, "sweeps": config.sweeps, "refine_iterations": config.refine_iterations,
            "sor_iterations": config.sor_iterations, **self._refine_uniforms()})

    def _refine_buffers(self, n: int) -> None:
        """Bind the refinement's work buffers for a level of ``n`` pixels (grown as needed)."""
        for key, binding, nbytes in (("increment", 9, 8 * n), ("average", 10, 8 * n), ("derivs", 11, 32 * n),
                                     ("system", 12, 32 * n)):
            self.gl.buffer(self._pool, key, nbytes).bind_to_storage_buffer(binding)

    def _refine_uniforms(self) -> dict:
        config = self.config
        return {"alpha": float(config.alpha), "delta": float(config.delta), "gamma": float(config.gamma),
                "omega": float(config.omega)}

    def _search_level(self, size: tuple[int, int], offset: int, defines: dict, init, dense, patch_flows) -> None:
        """Inverse search (``sweeps`` times) and densification of one level: ``init`` (H_l, W_l, 2) -> ``dense``."""
        gl, config = self.gl, self.config
        p, s = config.patch_size, config.patch_stride
        rows, cols = ((m - p + s - 1) // s + 1 if m > p else 1 for m in size)
        uniforms = {"size": size, "offset": offset, "stride": s, "iterations": config.iterations}
        init.bind_to_storage_buffer(4)
        current, previous = patch_flows
        name, lanes, extra = "flow_patch", 1, {}
        if self.search == "group":
            name, lanes, extra = "flow_patch_group", PATCH_LANES, {"LANES": PATCH_LANES}
        for sweep in range(config.sweeps):
            current.bind_to_storage_buffer(5)
            previous.bind_to_storage_buffer(8)
            program = gl.program(name, {**defines, **extra, **({"PROPAGATE": 1} if sweep else {})})
            gl.dispatch(program, rows * cols * lanes, uniforms)
            current, previous = previous, current
        previous.bind_to_storage_buffer(5)
        dense.bind_to_storage_buffer(6)
        n = size[0] * size[1]
        gl.dispatch(gl.program("flow_densify", defines), n, uniforms)
        if config.refine_iterations:
            self._refine(size, offset, defines)

    def _refine(self, size: tuple[int, int], offset: int, defines: dict) -> None:
        """Variational refinement of the level's dense flow (bound at 6) in place."""
        n = size[0] * size[1]
        self._refine_buffers(n)
        increments = [self._pool["increment"], self.gl.buffer(self._pool, "increment_next", 8 * n)]
        refine_level(self.gl, size, {"size": size, "offset": offset, **self._refine_uniforms()}, defines,
                     self.config, self.sor, increments)

    def release(self) -> None:
        """Free this estimator's work buffers."""
        self.gl.release_pool(self._pool)
