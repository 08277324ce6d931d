"""Memory of ``interleave serve`` per session: ``python -m tools.bench_server_memory [--size 1280x720]``

For each method, starts a fresh server process, warms it up with one small session of that method (imports,
compiled kernels and network files are loaded once per process, not per session) and closes it, then opens
``--sessions`` sessions of ``--size`` one after the other, each submitting ``--frames`` rendered frames (with
full-resolution motion vectors for ``mvec``) and predicting between them, all left open. The
server's resident memory (``VmRSS``) is read after the warm-up and after each session; a session's cost is the
growth over all of them divided by their number, in bytes per frame pixel. ``auto`` gets vectors with every
other frame, so that it runs (and keeps the state of) both ``mvec`` and ``flow2d``. The shared-memory segment is not in
the server's RSS (the server never maps it): its size (``Layout.shm_size``) is listed beside.

Prints a Markdown table (method, first session's growth, growth per session, B/px, segment B/px) and, with
``--json OUT``, writes the samples. ``engine.runtime.server.METHOD_BYTES_PER_PIXEL`` holds the figures of
docs/results/2026-11-28-server-memory.md, which this command measured.
"""
from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from engine.runtime.client import Client, synthetic_stream
from engine.runtime.protocol import MotionPlane
from engine.runtime.session import SessionConfig

ROOT = Path(__file__).resolve().parents[1]
METHODS = ("repeat", "reproject", "flow2d", "mvec", "auto", "decomp", "decomp2d")


def rss_bytes(pid: int) -> int:
    """Resident memory of process ``pid`` in bytes (``/proc/PID/status`` VmRSS)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError(f"no VmRSS for process {pid}")


def open_session(address: str, method: str, width: int, height: int, frames: int) -> Client:
    """A client whose session has submitted ``frames`` frames and predicted between them; left open."""
    vectors = method in ("mvec", "auto")
    cfg = SessionConfig(engine="opencv", width=width, height=height, method=method)
    client = Client(address, timeout=600.0)
    layout = client.hello(cfg, motion=MotionPlane() if vectors else None)
    zero = np.zeros((height, width, 2), np.float32)
    stream = synthetic_stream(width, height, 2 * frames)
    for i, (color, depth, pose, k, t) in enumerate(stream):
        if i % 2 == 0:  # auto: vectors with every other frame, so that both of its predictors hold a state
            with_vectors = vectors and i > 0 and (method != "auto" or i % 4 == 2)
            client.submit(color, depth, pose, k, t, motion_vectors=zero if with_vectors else None)
        else:
            client.predict(pose, k, t)
    client.shm_size = layout.shm_size  # type: ignore[attr-defined]
    return client


def measure(method: str, width: int, height: int, sessions: int, frames: int) -> dict:
    """RSS samples of a fresh server: after the warm-up, then after each of ``sessions`` sessions."""
    with tempfile.TemporaryDirectory() as tmp:
        sock = Path(tmp) / "memory.sock"
        proc = subprocess.Popen([sys.executable, "-m", "engine.cli", "serve", "--listen", f"unix:{sock}",
                                 "--max-memory", str(1 << 50), "--max-connections", str(sessions + 2)],
                                cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        clients: list[Client] = []
        try:
            if "listening on" not in proc.stdout.readline():
                raise RuntimeError("the server did not start")
            address = f"unix:{sock}"
            warm = open_session(address, method, 64, 48, frames)
            warm.bye()
            time.sleep(0.2)
            samples = [rss_bytes(proc.pid)]
            start = time.perf_counter()
            for _ in range(sessions):
                clients.append(open_session(address, method, width, height, frames))
                samples.append(rss_bytes(proc.pid))
            seconds = time.perf_counter() - start
            segment = clients[0].shm_size  # type: ignore[attr-defined]
        finally:
            for client in clients:
                client.close()
            proc.terminate()
            proc.wait(timeout=30)
    pixels = width * height
    per_session = (samples[-1] - samples[0]) / sessions
    return {"method": method, "width": width, "height": height, "sessions": sessions, "frames": frames,
            "rss_bytes": samples, "first_session_bytes": samples[1] - samples[0], "per_session_bytes": per_session,
            "bytes_per_pixel": per_session / pixels, "segment_bytes": segment, "segment_bytes_per_pixel":
            segment / pixels, "seconds": seconds}


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.bench_server_memory", description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", default="1280x720", help="frame size WxH of the measured sessions (1280x720)")
    parser.add_argument("--methods", default=",".join(METHODS), help=f"methods ({','.join(METHODS)})")
    parser.add_argument("--sessions", type=int, default=3, help="sessions opened per method (3)")
    parser.add_argument("--frames", type=int, default=4, help="frames each session submits (4; mvec keeps 3)")
    parser.add_argument("--json", type=Path, default=None, help="write the samples here")
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.lower().split("x"))
    rows = [measure(m.strip(), width, height, args.sessions, args.frames) for m in args.methods.split(",") if m.strip()]
    print(f"| method | first session MiB | per session MiB | B/px | segment B/px |  ({width}x{height}, "
          f"{args.sessions} sessions)\n|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['method']} | {r['first_session_bytes'] / 2**20:.0f} | {r['per_session_bytes'] / 2**20:.0f} | "
              f"{r['bytes_per_pixel']:.0f} | {r['segment_bytes_per_pixel']:.0f} |")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"command": "python -m tools.bench_server_memory " + " ".join(
            argv if argv is not None else sys.argv[1:]), "host": platform.platform(), "python": sys.version.split()[0],
            "rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
