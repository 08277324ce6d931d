"""A frame warped and hole-filled on the GPU: ``engine.predict.base.warp_and_fill``'s geometry (one-plane
forward splat, composite, background-biased hole fill) with the frame kept in GPU buffers.

A rendered frame is uploaded once (``GlFrameWarper.upload``: colour (H, W, 3) and depth (H, W), float32), or
adopted without a copy from buffers a renderer on the same context wrote (``adopt``), and warped to any
number of target cameras; an object flow is uploaded once too (``upload_flow``: (H, W, 2|3),
scaled per warp by ``flow_scale``, so an extrapolated flow -s u needs no new upload), or a 3D motion
(``upload_motion``: the moving pixels' velocity and change of velocity, as ``mvec`` estimates them) that each
warp extrapolates s frame intervals ahead on the GPU (``motion_extrapolate``). Each warp runs the
``FRAME`` variants of the splat passes (``engine.geometry.backends.gl.splat``), then the hole fill
(``fill_rows``, ``fill_links``, ``fill_apply``), and reads back the filled colour (float32, or 8-bit sRGB
codes encoded on the GPU: pass ``encode8``) and a packed hole mask, once, or hands them out as GPU buffers
(``readback=False``: ``GlPrediction``). Conventions: those of ``engine.geometry.forward_warp_frame`` (OpenCV
cameras, pixel centres at +0.5, planar depth, +inf sky).
Oracle: ``engine.predict.base.warp_and_fill`` on the CPU (``tests/geometry/test_gl_frame.py``).
"""
from __future__ import annotations

import weakref
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Optional

import numpy as np

from engine.core.checks import checked_array, checked_matrix, checked_sharpness, checked_size
from engine.core.colorspace import ENCODE8_BUCKETS
from engine.core.errors import InputError
from engine.geometry.backends.gl.context import GlContext, shared_context
from engine.geometry.backends.gl.splat import SPLATS, checked_splat, run_splat, splat_uniforms
from engine.geometry.camera import checked_flow, reprojection_matrix
from engine.geometry.encoding import FRAME_ENCODINGS, decode8_lookup, encode8_lookup
from engine.geometry.splat import DEFAULT_SHARPNESS

__all__ = ["GlImage", "GlFlow", "GlMotion", "GlPrediction", "GlFrameWarper", "unpack_holes", "encode8_table_rows"]


@lru_cache(maxsize=1)
def encode8_table_rows() -> np.ndarray:
    """(``ENCODE8_BUCKETS`` + 1, 2) float32 rows (step, level) of ``colorspace.encode8_table``: the table the
    GLSL ``encode8`` (``shaders/encode8_common.glsl``) reads (levels 0..255 are exact in float32)."""
    level, step = encode8_lookup()
    return np.ascontiguousarray(np.stack([step, level.astype(np.float32)], axis=-1), dtype=np.float32)


def _release_later(gl: GlContext, buffers: list) -> None:
    """Free ``buffers`` on the GL thread before its next call (a finalizer runs on any thread, at any point)."""
    gl.discard(buffers)


@dataclass(eq=False)
class GlImage:
    """A frame resident on the GPU: colour (H, W, 3) and depth (H, W) float32 buffers (rows top to bottom),
    freed with the object unless they were adopted (``GlFrameWarper.adopt``: the caller owns them)."""

    shape: tuple[int, int]
    color: object
    depth: object
    gl: GlContext = field(repr=False)
    owned: bool = True

    def __post_init__(self) -> None:
        if self.owned:
            weakref.finalize(self, _release_later, self.gl, [self.color, self.depth])


@dataclass(eq=False)
class GlPrediction:
    """A predicted frame left on the GPU (``warp_and_fill(..., readback=False)``): ``color`` (H, W, 3) float32
    and ``holes``, a packed mask (bit i % 32 of word i // 32 set where pixel i = y W + x is a hole); buffers of
    the shared context, freed with the object. ``read()`` brings both to the host."""

    shape: tuple[int, int]
    color: object
    holes: object
    gl: GlContext = field(repr=False)

    def __post_init__(self) -> None:
        weakref.finalize(self, _release_later, self.gl, [self.color, self.holes])

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        """(colour (H, W, 3) float32, holes (H, W) bool) on the host."""
        h, w = self.shape
        color, mask = np.empty((h, w, 3), np.float32), np.empty(-(-h * w // 32), np.uint32)

        def read():
            self.color.read_into(color, size=color.nbytes)
            self.holes.read_into(mask, size=mask.nbytes)
        self.gl.call(read)
        return color, unpack_holes(mask, self.shape)


def unpack_holes(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool of a packed hole mask (see ``GlPrediction``)."""
    h, w = shape
    return np.unpackbits(mask.view(np.uint8), bitorder="little")[:h * w].reshape(h, w).astype(bool)


@dataclass(eq=False)
class GlFlow:
    """An object flow resident on the GPU: (H, W, channels) float32, channels 2 (du, dv) or 3 (du, dv, dz)."""

    shape: tuple[int, int]
    channels: int
    buffer: object
    gl: GlContext = field(repr=False)

    def __post_init__(self) -> None:
        weakref.finalize(self, _release_later, self.gl, [self.buffer])

    def read(self) -> np.ndarray:
        """The flow on the host, (H, W, channels) float32."""
        out = np.empty(self.shape + (self.channels,), np.float32)
        self.gl.call(lambda: self.buffer.read_into(out, size=out.nbytes))
        return out

    def copy(self) -> "GlFlow":
        """A copy on the GPU (nothing crosses the bus)."""
        def run() -> GlFlow:
            buf = self.gl.new_buffer(self.buffer.size)
            self.gl.ctx.copy_buffer(buf, self.buffer)
            return GlFlow(self.shape, self.channels, buf, self.gl)
        return self.gl.call(run)


@dataclass(eq=False)
class GlMotion:
    """The 3D motion of a frame's moving pixels resident on the GPU (``engine.geometry.motion.extrapolated_flow``'s
    inputs): ``count`` flat pixel indices, their velocity (count, 3) and, with ``has_acceleration``, their change
    of velocity (count, 3), scene units per frame interval in the frame's camera axes."""

    shape: tuple[int, int]
    count: int
    has_acceleration: bool
    buffers: list = field(repr=False)
    gl: GlContext = field(repr=False)

    def __post_init__(self) -> None:
        weakref.finalize(self, _release_later, self.gl, list(self.buffers))


class GlFrameWarper:
    """Uploads frames and flows, and warps + fills them on a ``GlContext`` (the shared one by default), the
    warp by one of ``engine.geometry.backends.gl.splat.SPLATS`` (the same results; the default binned one).

    >>> warper = GlFrameWarper()                                             # doctest: +SKIP
    >>> image = warper.upload(frame.color, frame.depth)                      # doctest: +SKIP
    >>> color, holes = warper.warp_and_fill(image, K, T_src, K, T_dst)       # doctest: +SKIP
    """

    def __init__(self, gl: Optional[GlContext] = None, splat: str = SPLATS[0]) -> None:
        self.gl = shared_context() if gl is None else gl
        self.splat_kind = checked_splat(splat)
        self._pool: dict = {}

    def upload(self, color: np.ndarray, depth: np.ndarray) -> GlImage:
        """Upload a frame: colour (H, W, 3) linear RGB and planar depth (H, W) (+inf sky)."""
        sizes: dict = {}
        depth = np.ascontiguousarray(checked_array(depth, "depth", ("H", "W"), sizes))
        color = np.ascontiguousarray(checked_array(color, "color", ("H", "W", 3), sizes))
        return self.gl.call(lambda: GlImage(depth.shape, self.gl.new_buffer(data=color),
                                            self.gl.new_buffer(data=depth), self.gl))

    def upload_codes(self, codes: np.ndarray, depth: np.ndarray) -> GlImage:
        """Upload a frame whose colour came as 8-bit sRGB: ``codes`` (H, W, 3|4) uint8 (alpha ignored) cross the
        bus as they are (a quarter or a third of the float colour's bytes) and are decoded on the GPU (pass
        ``frame_from_codes``) to what ``upload(encoding.decode8(codes[..., :3]), depth)`` holds, bit for bit."""
        sizes: dict = {}
        depth = np.ascontiguousarray(checked_array(depth, "depth", ("H", "W"), sizes))
        codes = np.asarray(codes)
        if codes.dtype != np.uint8:
            raise InputError(f"must be uint8 sRGB codes, got dtype {codes.dtype}", field="codes")
        codes = np.ascontiguousarray(checked_array(codes, "codes", ("H", "W", "C"), sizes, np.uint8, floating=False))
        channels = codes.shape[2]
        if channels not in (3, 4):
            raise InputError(f"must have 3 or 4 channels, got {channels}", field="codes")
        n = depth.size

        def decode() -> GlImage:
            gl = self.gl
            table = self._pool.get("decode8_table")
            if table is None:
                table = self._pool["decode8_table"] = gl.ctx.buffer(decode8_lookup())
            raw = gl.buffer(self._pool, "codes_in", 4 * -(-codes.nbytes // 4))
            raw.write(codes)
            color = gl.new_buffer(12 * n)
            for binding, buf in enumerate((raw, table, color)):
                buf.bind_to_storage_buffer(binding)
            gl.dispatch(gl.program("frame_from_codes"), n, {"count": n, "channels": channels})
            return GlImage(depth.shape, color, gl.new_buffer(data=depth), gl)
        return self.gl.call(decode)

    def adopt(self, color, depth, shape: tuple[int, int]) -> GlImage:
        """A frame already on the GPU, without a copy: ``color`` (H, W, 3) and ``depth`` (H, W) float32
        moderngl buffers of the shared context (a renderer that runs on it through ``GlContext.call``, e.g.
        with ``Framebuffer.read_into(buffer)``), rows top to bottom, planar depth, +inf sky. The caller keeps
        owning them and must not change them while predictions use the image."""
        h, w = checked_size(shape, "shape")
        self._check_buffer(color, 12 * h * w, "color")
        self._check_buffer(depth, 4 * h * w, "depth")
        return GlImage((h, w), color, depth, self.gl, owned=False)

    def _check_buffer(self, buf, nbytes: int, field: str) -> None:
        """InputError naming ``field`` unless ``buf`` is a buffer of this context of at least ``nbytes``."""
        if getattr(buf, "size", -1) < nbytes or getattr(buf, "ctx", None) is not self.gl.ctx:
            raise InputError(f"must be a buffer of this context of at least {nbytes} bytes", field=field)

    def from_rgbd(self, rgbd, shape: tuple[int, int]) -> GlImage:
        """A frame from a buffer of the shared context holding (H, W, 4) float32 (r, g, b linear, planar depth
        with +inf sky) per pixel, rows top to bottom: what ``engine.fields.gl.GlFieldRenderer.render_to_buffer``
        leaves. Split on the GPU (pass ``frame_from_rgbd``) into a colour and a depth buffer that the returned
        image owns, so the source may be overwritten at once; nothing crosses the bus."""
        h, w = checked_size(shape, "shape")
        n = h * w
        self._check_buffer(rgbd, 16 * n, "rgbd")

        def split() -> GlImage:
            color, depth = self.gl.new_buffer(12 * n), self.gl.new_buffer(4 * n)
            for binding, buf in enumerate((rgbd, color, depth)):
                buf.bind_to_storage_buffer(binding)
            self.gl.dispatch(self.gl.program("frame_from_rgbd"), n, {"count": n})
            return GlImage((h, w), color, depth, self.gl)
        return self.gl.call(split)

    def upload_flow(self, flow: np.ndarray) -> GlFlow:
        """Upload an object flow (H, W, 2) (du, dv) pixels or (H, W, 3) (du, dv, dz), in the frame's view."""
        flow = np.ascontiguousarray(checked_flow(flow, {}))
        return self.gl.call(lambda: GlFlow(flow.shape[:2], flow.shape[2], self.gl.new_buffer(data=flow), self.gl))

    def upload_motion(self, shape: tuple[int, int], moving: np.ndarray, velocity: np.ndarray,
                      acceleration: Optional[np.ndarray] = None) -> GlMotion:
        """Upload the motion of a (H, W) = ``shape`` frame's moving pixels: ``moving`` (M,) flat indices,
        ``velocity`` (M, 3) and optional ``acceleration`` (M, 3) (see ``GlMotion``)."""
        h, w = (int(v) for v in shape)
        moving = np.asarray(moving)
        if moving.ndim != 1 or (moving.size and (moving.min() < 0 or moving.max() >= h * w)):
            raise InputError(f"must be flat pixel indices in [0, {h * w}), got shape {moving.shape}", field="moving")
        sizes = {"M": moving.size}
        velocity = np.ascontiguousarray(checked_array(velocity, "velocity", ("M", 3), sizes))
        arrays = [moving.astype(np.uint32), velocity]
        if acceleration is not None:
            arrays.append(np.ascontiguousarray(checked_array(acceleration, "acceleration", ("M", 3), sizes)))

        def make():
            buffers = [self.gl.new_buffer(data=a if a.size else np.zeros(4, np.float32)) for a in arrays]
            return GlMotion((h, w), moving.size, acceleration is not None, buffers, self.gl)
        return self.gl.call(make)

    def warp_and_fill(self, image: GlImage, K_src: np.ndarray, T_src: np.ndarray, K_dst: np.ndarray,
                      T_dst: np.ndarray, flow: Optional[GlFlow] = None, flow_scale: float = 1.0,
                      sharpness: float = DEFAULT_SHARPNESS, gpu_ms: Optional[dict] = None,
                      motion: Optional[GlMotion] = None, readback: bool = True, with_depth: bool = False,
                      encoding: str = "linear"):
        """Forward-warp ``image`` to the destination camera, its points moved by ``flow_scale * flow`` or by
        ``motion`` extrapolated ``flow_scale`` frame intervals ahead (``K_src`` projects it), and fill the
        holes; returns (colour (H, W, 3) float32, holes (H, W) bool: where the warp left no surface), or with
        ``readback=False`` a ``GlPrediction`` that stays on the GPU (a GPU-side copy). ``with_depth`` (read
        back only) adds the filled planar depth (H, W) float32 as ``engine.predict.base.warp_fill_depth``'s
        (+inf where nothing was left to fill from): (colour, holes, depth). ``encoding="srgb8"`` (read back
        only) encodes the colour on the GPU (pass ``encode8``) and reads back (H, W, 3) uint8 codes, equal to
        ``engine.geometry.encoding.encode8`` of the float colour: a quarter of the bytes. With ``gpu_ms``, the
        GPU milliseconds of the stages (``motion``,) ``warp``, ``fill``, (``encode``,) ``readback`` are added."""
        if not isinstance(image, GlImage):
            raise InputError(f"must be a GlImage from GlFrameWarper.upload, got {type(image).__name__}", field="image")
        if flow is not None and (not isinstance(flow, GlFlow) or flow.shape != image.shape):
            got = flow.shape if isinstance(flow, GlFlow) else type(flow).__name__
            raise InputError(f"must be a GlFlow of the frame's size {image.shape}, got {got}", field="flow")
        if motion is not None and (not isinstance(motion, GlMotion) or motion.shape != image.shape
                                   or flow is not None):
            got = motion.shape if isinstance(motion, GlMotion) else type(motion).__name__
            raise InputError(f"must be a GlMotion of the frame's size {image.shape}, without a flow, got {got}",
                             field="motion")
        scale = float(flow_scale)
        if not np.isfinite(scale):
            raise InputError(f"must be finite, got {flow_scale!r}", field="flow_scale")
        if with_depth and not readback:
            raise InputError("the depth is read back only: with_depth needs readback=True", field="with_depth")
        if encoding not in FRAME_ENCODINGS:
            raise InputError(f"must be one of {', '.join(FRAME_ENCODINGS)}, got {encoding!r}", field="encoding")
        if encoding != "linear" and not readback:
            raise InputError(f"a prediction left on the GPU is linear: encoding {encoding!r} needs readback=True",
                             field="encoding")
        k_src = checked_matrix(K_src, "K_src", 3)
        matrix = reprojection_matrix(k_src, checked_matrix(T_src, "T_src", 4), checked_matrix(K_dst, "K_dst", 3),
                                     checked_matrix(T_dst, "T_dst", 4))
        return self.gl.call(self._warp_and_fill, image, matrix, flow, scale, checked_sharpness(sharpness), gpu_ms,
                            motion, k_src, readback, with_depth, encoding)

    def _extrapolate(self, image: GlImage, motion: GlMotion, step: float, k: np.ndarray) -> None:
        """Pass ``motion_extrapolate``: the flow (H, W, 3) of ``motion`` ``step`` intervals ahead into the pool's
        ``motion_flow`` buffer, bound to 3."""
        gl, (h, w) = self.gl, image.shape
        flow = gl.buffer(self._pool, "motion_flow", 12 * h * w)
        gl.clear_words(flow, 12 * h * w)
        flow.bind_to_storage_buffer(3)
        image.depth.bind_to_storage_buffer(1)
        # velocity stands in at 18 without an acceleration (the pass does not read it then)
        for binding, buf in zip((16, 17, 18), motion.buffers + motion.buffers[1:2]):
            buf.bind_to_storage_buffer(binding)
        k_inv = np.linalg.inv(k)
        gl.dispatch(gl.program("motion_extrapolate"), motion.count, {
            "num_moving": motion.count, "width": w, "has_acceleration": int(motion.has_acceleration),
            "step": float(step), "k_row0": tuple(float(v) for v in k[0]), "k_row1": (float(k[1, 1]), float(k[1, 2])),
            "kinv_row0": tuple(float(v) for v in k_inv[0]), "kinv_row1": (float(k_inv[1, 1]), float(k_inv[1, 2]))})

    def _warp_and_fill(self, image: GlImage, matrix, flow: Optional[GlFlow], scale: float, sharpness: float,
                       gpu_ms: Optional[dict], motion: Optional[GlMotion] = None, k_src: Optional[np.ndarray] = None,
                       readback: bool = True, with_depth: bool = False, encoding: str = "linear"):
        gl, pool = self.gl, self._pool
        h, w = image.shape
        n = h * w
        words = -(-n // 32)
        with gl.timing(gpu_ms):
            moved = None
            if motion is not None:
                with gl.gpu_stage("motion"):
                    self._extrapolate(image, motion, scale, k_src)
                moved, scale = (pool["motion_flow"], 3), 1.0
            elif flow is not None:
                moved = (flow.buffer, flow.channels)
            with gl.gpu_stage("warp"):
                self.splat(image, matrix, sharpness, moved, scale)
            for key, binding, nbytes in (("rowsrc", 11, 4 * n), ("rowinfo", 12, 4 * h), ("links", 13, 8 * h),
                                         ("filled", 14, 12 * n), ("mask", 15, 4 * words)):
                gl.buffer(pool, key, nbytes).bind_to_storage_buffer(binding)
            with gl.gpu_stage("fill"):  # fill_apply writes every word of the mask
                sizes = {"size": (h, w)}
                gl.dispatch_groups(gl.program("fill_rows"), h, sizes)
                gl.dispatch_groups(gl.program("fill_links"), 1, sizes)
                if with_depth:
                    gl.buffer(pool, "filled_depth", 4 * n).bind_to_storage_buffer(19)
                gl.dispatch(gl.program("fill_apply", {"WITH_DEPTH": None} if with_depth else None), n, sizes)
            if readback:
                if encoding == "srgb8":
                    with gl.gpu_stage("encode"):
                        source = self._encode8(pool["filled"], n)
                    color = np.empty((h, w, 3), np.uint8)
                else:
                    color, source = np.empty((h, w, 3), np.float32), pool["filled"]
                mask = np.empty(words, np.uint32)
                with gl.gpu_stage("readback"):
                    source.read_into(color, size=color.nbytes)
                    pool["mask"].read_into(mask, size=mask.nbytes)
                    if with_depth:
                        depth = np.empty((h, w), np.float32)
                        pool["filled_depth"].read_into(depth, size=depth.nbytes)
            else:  # copies on the GPU: the work buffers are the next warp's
                out = GlPrediction((h, w), gl.new_buffer(12 * n), gl.new_buffer(4 * words), gl)
                gl.ctx.copy_buffer(out.color, pool["filled"], 12 * n)
                gl.ctx.copy_buffer(out.holes, pool["mask"], 4 * words)
        if not readback:
            return out
        return (color, unpack_holes(mask, (h, w)), depth) if with_depth else (color, unpack_holes(mask, (h, w)))

    def splat(self, image: GlImage, matrix: np.ndarray, sharpness: float = DEFAULT_SHARPNESS,
              moved: Optional[tuple] = None, flow_scale: float = 1.0) -> tuple:
        """The forward splat of ``image`` (``engine.geometry.forward_warp_frame`` without the fill) through the
        float64 reprojection ``matrix`` (``reprojection_matrix``) onto a destination of the image's size, its
        points moved by ``flow_scale`` x ``moved`` = (a (H, W, channels) float32 buffer, channels) when given.
        Returns this warper's ``warped`` ((H, W, 4): r, g, b, depth; 0, 0, 0, +inf on holes) and ``holes`` ((H, W)
        uint 0 / 1) buffers, bound to 8 and 10, overwritten by its next warp. GL thread only."""
        gl, pool = self.gl, self._pool
        h, w = image.shape
        n = h * w
        if moved is None:
            gl.buffer(pool, "no_flow", 16).bind_to_storage_buffer(3)
        else:
            moved[0].bind_to_storage_buffer(3)
        image.color.bind_to_storage_buffer(0)
        image.depth.bind_to_storage_buffer(1)
        for key, binding, nbytes in (("alpha", 2, 16), ("mids", 4, 16), ("index", 9, 16), ("warped", 8, 16 * n),
                                     ("holes", 10, 4 * n)):
            gl.buffer(pool, key, nbytes).bind_to_storage_buffer(binding)
        defines = {"FRAME": 1, "FLOW_CHANNELS": 3 if moved is None else moved[1]}
        uniforms = splat_uniforms(matrix, (1, h, w), (h, w), sharpness, moved is not None, flow_scale)
        uniforms.update(num_points=n, use_index=0)
        run_splat(gl, pool, defines, uniforms, n, n, self.splat_kind)
        return pool["warped"], pool["holes"]

    def encode8(self, color, shape: tuple[int, int]) -> np.ndarray:
        """The (H, W, 3) uint8 8-bit sRGB codes (``engine.geometry.encoding.encode8``'s, bit for bit) of a
        (H, W, 3) float32 linear colour buffer of this context (e.g. a ``GlPrediction``'s), encoded on the GPU;
        only the codes are read back."""
        h, w = checked_size(shape, "shape")
        self._check_buffer(color, 12 * h * w, "color")
        out = np.empty((h, w, 3), np.uint8)

        def run():
            self._encode8(color, h * w).read_into(out, size=out.nbytes)
        self.gl.call(run)
        return out

    def _encode8(self, color, n: int):
        """Pass ``encode8``: the float colour of ``n`` pixels in buffer ``color`` as packed 8-bit sRGB codes in
        the pool's ``codes`` buffer, which it returns (the table is uploaded on first use, kept in the pool)."""
        gl, pool = self.gl, self._pool
        table = pool.get("encode8_table")
        if table is None:
            table = pool["encode8_table"] = gl.ctx.buffer(encode8_table_rows())
        count = 3 * n
        codes = gl.buffer(pool, "codes", 4 * -(-count // 4))
        color.bind_to_storage_buffer(0)
        table.bind_to_storage_buffer(1)
        codes.bind_to_storage_buffer(2)
        gl.dispatch(gl.program("encode8", {"BUCKETS": ENCODE8_BUCKETS}), -(-count // 4), {"count": count})
        return codes

    def release(self) -> None:
        """Free this warper's work buffers (uploaded images and flows free themselves)."""
        self.gl.release_pool(self._pool)
