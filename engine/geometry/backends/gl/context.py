"""The GL backend's context: one headless OpenGL 4.5 context, compute programs loaded from shader files with
``#define`` variants, grow-only GPU buffers and per-stage GPU timer queries.

Shaders live one pass per file in ``shaders/`` (``*.comp``); ``#include "name.glsl"`` lines are replaced by
that file's text (once per program). A program is compiled once per (file, defines) and cached. The context
is created on, and every GL call runs on, the context's own thread (``GlContext.call``): callers on any
thread (a server's workers) share one context safely, one call at a time.
"""
from __future__ import annotations

import collections
import os
import re
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Optional

__all__ = ["SHADERS", "LOCAL_SIZE", "shader_source", "GlContext", "is_software_renderer", "shared_context", "available"]

#: Folder of the compute shaders (one file per pass).
SHADERS = Path(__file__).with_name("shaders")
#: Invocations per workgroup of the one-dimensional passes (``LOCAL_SIZE`` is defined in every program).
LOCAL_SIZE = 256
#: Largest workgroup count along x of one dispatch (the GL minimum of GL_MAX_COMPUTE_WORK_GROUP_COUNT).
MAX_GROUPS_X = 65535
#: The storage binding ``GlContext.clear_words`` binds its buffer to (no pass reads it).
CLEAR_BINDING = 31
#: Most bytes of dropped per-frame buffers a context keeps for reuse (``GlContext.new_buffer``): frames,
#: flows and predictions are made and dropped every rendered frame at the same few sizes, and a reused
#: buffer spares the driver an allocation and the GPU the first touch of new memory.
RECYCLE_BYTES = 512 << 20
#: What every pass starts with: its 1D workgroup and ``invocation()``, the flat index of an invocation of
#: ``GlContext.dispatch`` (which spreads groups beyond ``MAX_GROUPS_X`` over y).
_PRELUDE = """layout(local_size_x = LOCAL_SIZE) in;
uint invocation() {
    return gl_GlobalInvocationID.x + gl_GlobalInvocationID.y * gl_NumWorkGroups.x * gl_WorkGroupSize.x;
}
// NaN and "not finite" read from the bits: NVIDIA's compiler folds !(x > y) into x <= y, so NaN took the
// wrong branch there (measured on an H200); every NaN test of the passes goes through these
bool nan_bits(float x) { return (floatBitsToUint(x) & 0x7fffffffu) > 0x7f800000u; }
bool nonfinite_bits(float x) { return (floatBitsToUint(x) & 0x7f800000u) == 0x7f800000u; }
bool nonfinite_bits(vec2 v) { return nonfinite_bits(v.x) || nonfinite_bits(v.y); }
"""
_INCLUDE = re.compile(r'^\s*#include\s+"([\w.]+)"\s*$', re.MULTILINE)


def shader_source(name: str, defines: Optional[Mapping[str, object]] = None) -> str:
    """The full GLSL text of pass ``name`` (``shaders/<name>.comp``): version, extensions, ``LOCAL_SIZE`` and
    ``defines`` (``{"FRAME": 1}`` -> ``#define FRAME 1``; a value of None defines the bare name), the prelude
    (workgroup size, ``invocation()``, the NaN tests ``nan_bits`` and ``nonfinite_bits``), then the file with
    its ``#include`` lines expanded."""
    seen: set[str] = set()

    def expand(text: str) -> str:
        def one(match: re.Match) -> str:
            include = match.group(1)
            if include in seen:
                return ""
            seen.add(include)
            return expand((SHADERS / include).read_text())
        return _INCLUDE.sub(one, text)

    lines = ["#version 450", "#extension GL_ARB_gpu_shader_int64 : require", f"#define LOCAL_SIZE {LOCAL_SIZE}"]
    for key, value in sorted((defines or {}).items()):
        lines.append(f"#define {key}" if value is None else f"#define {key} {value}")
    return "\n".join(lines) + "\n" + _PRELUDE + expand((SHADERS / f"{name}.comp").read_text())


def is_software_renderer(renderer: str) -> bool:
    """True for Mesa's CPU rasterisers (llvmpipe, softpipe, swrast): a GL context that runs on the CPU."""
    name = renderer.lower()
    return any(s in name for s in ("llvmpipe", "softpipe", "swrast", "software"))


class GlContext:
    """A headless EGL context with the backend's programs, buffers and timers.

    >>> gl = GlContext()                                   # doctest: +SKIP
    >>> program = gl.program("splat_key", {"FRAME": 1})    # doctest: +SKIP
    >>> with gl.gpu_stage("warp"): gl.dispatch(program, n) # doctest: +SKIP
    """

    def __init__(self) -> None:
        self._pid = os.getpid()
        self._thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix="interleave-gl")
        try:
            self._thread.submit(self._create).result()
        except BaseException:
            self._thread.shutdown(wait=False)
            raise
        self._programs: dict = {}
        self._garbage: collections.deque = collections.deque()  # GL objects to free on the GL thread
        self._free: dict[int, list] = {}  # size in bytes -> dropped buffers kept for reuse
        self._pass_names: dict[int, str] = {}  # id(program) -> its pass name (``pass_timing``)
        self._pass_queries: Optional[list] = None
        self.recycle_bytes = RECYCLE_BYTES
        self._queries: list = []
        self._open: list[tuple[str, object]] = []
        self._timing = False

    def _create(self) -> None:
        import moderngl

        self._ident = threading.get_ident()
        # ask for 4.5: without ``require`` moderngl asks EGL for 3.3, which NVIDIA's driver gives exactly (Mesa
        # gives its highest)
        self.ctx = moderngl.create_standalone_context(backend="egl", require=450)
        if self.ctx.version_code < 450 or "GL_ARB_gpu_shader_int64" not in self.ctx.extensions:
            version = self.ctx.info.get("GL_VERSION", "?")
            self.ctx.release()
            raise RuntimeError(f"the GL backend needs OpenGL 4.5 with GL_ARB_gpu_shader_int64, the context has "
                               f"{version}")
        self.renderer = str(self.ctx.info.get("GL_RENDERER", ""))
        self.software = is_software_renderer(self.renderer)

    def call(self, fn: Callable[..., Any], *args, **kwargs) -> Any:
        """Run ``fn(*args, **kwargs)`` on the context's thread (where the context is current, made so once
        when it was created: nothing else runs GL there); returns its result (exceptions propagate)."""
        if os.getpid() != self._pid:  # a forked child: the context and its thread stayed in the parent
            raise RuntimeError("this GL context belongs to process %d; make a new one in this process" % self._pid)
        if threading.get_ident() == self._ident:
            self._collect()
            return fn(*args, **kwargs)
        return self._thread.submit(self._collected, fn, *args, **kwargs).result()

    def discard(self, objects) -> None:
        """Free GL ``objects`` (buffers, ...) later, on the GL thread, before its next call: safe from any thread
        and from a garbage-collection finalizer, which may run while another thread pool holds the lock that
        submitting work takes (so a finalizer must not wait on the GL thread). Buffers are kept for
        ``new_buffer`` up to ``recycle_bytes`` in all."""
        self._garbage.extend(objects)

    def _collect(self) -> None:
        """Free the discarded objects; buffers go to the reuse lists while they hold under ``recycle_bytes``.
        Runs before every call on the GL thread: with nothing discarded it returns at once."""
        if not self._garbage:
            return
        import moderngl

        kept = sum(size * len(bufs) for size, bufs in self._free.items())
        while self._garbage:
            try:
                obj = self._garbage.popleft()
            except IndexError:
                break
            size = obj.size if isinstance(obj, moderngl.Buffer) else None
            if size is not None and kept + size <= self.recycle_bytes:
                self._free.setdefault(size, []).append(obj)
                kept += size
            else:
                obj.release()

    def new_buffer(self, nbytes: int = 0, data=None):
        """A buffer of exactly ``nbytes`` (contents undefined), or holding ``data`` (bytes-like, e.g. a
        contiguous array): a dropped one of that size when one was kept (see ``discard``), else a new one.
        GL thread only."""
        if data is not None:
            data = memoryview(data).cast("B")
            nbytes = data.nbytes
        kept = self._free.get(int(nbytes))
        if kept:
            buf = kept.pop()
            if data is not None:
                buf.write(data)
            return buf
        return self.ctx.buffer(data) if data is not None else self.ctx.buffer(reserve=int(nbytes))

    def _collected(self, fn, *args, **kwargs):
        self._collect()
        return fn(*args, **kwargs)

    def program(self, name: str, defines: Optional[Mapping[str, object]] = None):
        """The compiled compute program of pass ``name`` with ``defines`` (cached)."""
        key = (name, tuple(sorted((defines or {}).items())))
        program = self._programs.get(key)
        if program is None:
            program = self._programs[key] = self.ctx.compute_shader(shader_source(name, defines))
            self._pass_names[id(program)] = name
        return program

    def buffer(self, pool: dict, key: str, nbytes: int):
        """A grow-only buffer of at least ``nbytes`` kept in ``pool[key]`` (contents undefined after growth)."""
        nbytes = max(int(nbytes), 16)
        buf = pool.get(key)
        if buf is None or buf.size < nbytes:
            if buf is not None:
                buf.release()
            buf = pool[key] = self.ctx.buffer(reserve=nbytes)
        return buf

    def clear_words(self, buffer, nbytes: int, value: int = 0) -> None:
        """Set the first ``nbytes`` (a multiple of 4) of ``buffer`` to the 32-bit ``value`` with a compute pass,
        then a storage barrier. moderngl's ``Buffer.clear`` maps the buffer and writes it from the CPU, which
        on a GPU waits for the work in flight and sends every byte over the bus (measured on an H200: most of
        the splat's GPU time). GL thread only."""
        count = int(nbytes) // 4
        if count <= 0:
            return
        buffer.bind_to_storage_buffer(CLEAR_BINDING)
        self.dispatch(self.program("clear_words", {"CLEAR_BINDING": CLEAR_BINDING}), count,
                      {"count": count, "value": int(value) & 0xFFFFFFFF})

    def dispatch(self, program, count: int, uniforms: Optional[Mapping[str, object]] = None) -> None:
        """Run ``program`` over ``count`` invocations (1D, ``LOCAL_SIZE`` a group; groups beyond
        ``MAX_GROUPS_X`` go to y: passes index with ``invocation()``), then a storage barrier."""
        self.dispatch_groups(program, -(-int(count) // LOCAL_SIZE), uniforms)

    @contextmanager
    def timing(self, into: Optional[dict[str, float]]) -> Iterator[None]:
        """Add the GPU milliseconds of the ``gpu_stage`` blocks run inside to ``into`` (when the block ends:
        reading a query waits for the GPU); None times nothing."""
        self._timing, self._open = into is not None, []
        try:
            yield
        finally:
            self._timing = False
            for name, query in self._open:
                into[name] = into.get(name, 0.0) + query.elapsed * 1e-6
                self._queries.append(query)
            self._open = []

    @contextmanager
    def pass_timing(self, into: dict) -> Iterator[None]:
        """Profile: time every dispatch run inside (on any thread, through ``call``) with a query of its own and
        add ``into[pass name] = (dispatches, GPU ms)``. Stage queries (``gpu_stage``) are off meanwhile, as GL
        times one query at a time; a query per dispatch adds waits of its own, so use this to see where the GPU
        time goes, not as the time of a frame. On a software renderer (whose queries read 0) each dispatch is
        timed on the clock instead, from a ``finish`` before it to one after it: the CPU's ms of the pass. Not
        from the GL thread."""
        self._pass_queries = []
        try:
            yield
        finally:
            def read() -> None:
                for name, query in self._pass_queries:
                    calls, ms = into.get(name, (0, 0.0))
                    if isinstance(query, float):  # a software renderer's clock time
                        into[name] = (calls + 1, ms + query)
                        continue
                    into[name] = (calls + 1, ms + query.elapsed * 1e-6)
                    self._queries.append(query)
                self._pass_queries = None
            self.call(read)

    @contextmanager
    def gpu_stage(self, name: str) -> Iterator[None]:
        """Time the GL commands of the block with a GL_TIME_ELAPSED query (only inside ``timing``, and not while
        ``pass_timing`` runs; blocks do not nest: GL allows one elapsed-time query at a time)."""
        if not self._timing or self._pass_queries is not None:
            yield
            return
        query = self._take_query()
        with query:
            yield
        self._open.append((name, query))

    def _take_query(self):
        """A GL_TIME_ELAPSED query: a finished one back from ``timing`` / ``pass_timing``, else a new one."""
        return self._queries.pop() if self._queries else self.ctx.query(time=True)

    def dispatch_groups(self, program, groups: int, uniforms: Optional[Mapping[str, object]] = None) -> None:
        """Run ``program`` as ``groups`` workgroups (one per row, column, ...: passes index them with
        ``gl_WorkGroupID.x + gl_WorkGroupID.y * gl_NumWorkGroups.x``), then a storage barrier."""
        for name, value in (uniforms or {}).items():
            member = program.get(name, None)  # a pass declares only the uniforms it reads
            if member is not None:
                member.value = value
        groups = max(1, int(groups))
        gx = min(groups, MAX_GROUPS_X)
        if self._pass_queries is None:
            program.run(gx, -(-groups // gx), 1)
        elif self.software:
            self.ctx.finish()
            start = time.perf_counter()
            program.run(gx, -(-groups // gx), 1)
            self.ctx.finish()
            self._pass_queries.append((self._pass_names.get(id(program), "?"), 1e3 * (time.perf_counter() - start)))
        else:
            query = self._take_query()
            with query:
                program.run(gx, -(-groups // gx), 1)
            self._pass_queries.append((self._pass_names.get(id(program), "?"), query))
        self.ctx.memory_barrier()

    def release_pool(self, pool: dict) -> None:
        """Free the buffers of a ``buffer`` pool (from any thread) and empty it."""
        def free():
            for buf in pool.values():
                buf.release()
            pool.clear()
        self.call(free)

    def release(self) -> None:
        """Free the programs, queries and the context, and stop its thread."""
        def free():
            self._collect()
            for buffers in self._free.values():
                for buf in buffers:
                    buf.release()
            self._free.clear()
            for program in self._programs.values():
                program.release()
            self._programs.clear()
            for query in self._queries:
                query.release()
            self._queries.clear()
        self.call(free)
        self._thread.submit(self.ctx.release).result()
        self._thread.shutdown()


_SHARED: Optional[GlContext] = None
_FAILED: Optional[str] = None
_SHARED_LOCK = threading.Lock()


def shared_context() -> GlContext:
    """The process-wide ``GlContext``, created on first use; raises RuntimeError (with the first failure's
    reason, remembered) when no EGL context with OpenGL 4.5 compute and 64-bit integers can be made, and in a
    child forked after the context was made (a GL context and its thread do not cross a fork, and a new one made
    there can hang in the driver: start workers with the 'spawn' method)."""
    global _SHARED, _FAILED
    with _SHARED_LOCK:
        if _SHARED is not None and _SHARED._pid != os.getpid():
            raise RuntimeError(f"the GL context was made in process {_SHARED._pid}, before this process forked "
                               f"from it; use the 'spawn' start method for workers that use the GL backend")
        if _SHARED is None:
            if _FAILED is not None:
                raise RuntimeError(_FAILED)
            try:
                _SHARED = GlContext()
            except Exception as exc:  # no moderngl, no EGL, no GL 4.5 / int64
                _FAILED = f"no OpenGL 4.5 compute context: {type(exc).__name__}: {exc}"
                raise RuntimeError(_FAILED) from None
        return _SHARED


def available() -> bool:
    """True when ``shared_context()`` can be made (on this machine at all: llvmpipe counts)."""
    try:
        shared_context()
        return True
    except RuntimeError:
        return False
