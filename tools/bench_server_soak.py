"""Soak benchmark of ``interleave serve``: ``python -m tools.bench_server_soak [--frames 10000] [--clients 4]``

Starts a server in its own process, runs ``--clients`` clients at once (threads of this process, each with
its own connection and session), each sending its share of ``--frames`` displayed frames (every k-th one
SUBMITted, the others PREDICTed), and samples the server's resident memory, thread count and open file
descriptors (``/proc/PID``) every ``--every`` frames of client 0. Prints the samples, then the first and last
sample and their growth, and the median ms of a PREDICT round trip. A server that leaks shows it here;
what "flat" means is for the reader: memory settles after the first sessions warm up.
"""
from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Optional, Sequence

from engine.runtime.client import Client, synthetic_stream
from engine.runtime.session import SessionConfig

ROOT = Path(__file__).resolve().parents[1]


def server_usage(pid: int) -> dict[str, int]:
    """Resident memory (KiB), threads and open file descriptors of process ``pid`` (Linux /proc)."""
    status = Path(f"/proc/{pid}/status").read_text().splitlines()
    fields = dict(line.split(":", 1) for line in status if ":" in line)
    return {"rss_kib": int(fields["VmRSS"].split()[0]), "threads": int(fields["Threads"]),
            "fds": len(list(Path(f"/proc/{pid}/fd").iterdir()))}


def run_client(address: str, frames: int, k: int, width: int, height: int, method: str, times: list[float],
               on_frame=None) -> None:
    """One client's session: every k-th frame submitted, the others predicted (times in ms appended)."""
    with Client(address) as client:
        client.hello(SessionConfig(engine="opencv", width=width, height=height, method=method))
        for i, (color, depth, pose, intrinsics, t) in enumerate(synthetic_stream(width, height, frames)):
            if i % k == 0:
                client.submit(color, depth, pose, intrinsics, t)
            else:
                start = time.perf_counter()
                client.predict(pose, intrinsics, t)
                times.append(1e3 * (time.perf_counter() - start))
            if on_frame is not None:
                on_frame(i)


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.bench_server_soak", description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=10_000, help="displayed frames over all clients (10000)")
    parser.add_argument("--clients", type=int, default=4, help="clients at once (4)")
    parser.add_argument("--k", type=int, default=2, help="one submitted frame every k (2)")
    parser.add_argument("--size", default="320x180", help="frame size WxH (320x180)")
    parser.add_argument("--method", default="reproject", help="predictor of every session (reproject)")
    parser.add_argument("--every", type=int, default=500, help="frames of client 0 between samples (500)")
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.lower().split("x"))
    per_client = max(args.frames // args.clients, 1)
    with tempfile.TemporaryDirectory() as tmp:
        sock = Path(tmp) / "soak.sock"
        proc = subprocess.Popen([sys.executable, "-m", "engine.cli", "serve", "--listen", f"unix:{sock}"],
                                cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        try:
            if "listening on" not in proc.stdout.readline():
                print("the server did not start", file=sys.stderr)
                return 1
            samples = [(0, server_usage(proc.pid))]

            def sample(i: int) -> None:
                if (i + 1) % args.every == 0:
                    samples.append(((i + 1) * args.clients, server_usage(proc.pid)))

            times: list[list[float]] = [[] for _ in range(args.clients)]
            threads = [threading.Thread(target=run_client, args=(f"unix:{sock}", per_client, args.k, width, height,
                                                                 args.method, times[c], sample if c == 0 else None))
                       for c in range(args.clients)]
            start = time.perf_counter()
            for thread in threads:
                thread.start()
            for thread in threads:
                thread.join()
            elapsed = time.perf_counter() - start
            samples.append((per_client * args.clients, server_usage(proc.pid)))
        finally:
            proc.terminate()
            proc.wait(timeout=15)
    print("| frames (all clients) | RSS MiB | threads | open fds |\n|---|---|---|---|")
    for frames, usage in samples:
        print(f"| {frames} | {usage['rss_kib'] / 1024:.1f} | {usage['threads']} | {usage['fds']} |")
    first, last = samples[1][1] if len(samples) > 2 else samples[0][1], samples[-1][1]
    rtts = [t for ts in times for t in ts]
    print(f"\n{args.clients} clients, {per_client * args.clients} frames of {width}x{height} ({args.method}, "
          f"k = {args.k}) in {elapsed:.1f} s; from the first sample under load to the last: RSS "
          f"{(last['rss_kib'] - first['rss_kib']) / 1024:+.1f} MiB, threads {last['threads'] - first['threads']:+d}, "
          f"fds {last['fds'] - first['fds']:+d}; median PREDICT round trip "
          f"{statistics.median(rtts) if rtts else float('nan'):.2f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
