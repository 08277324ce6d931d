"""The attacks of issue 41 against ``interleave serve``: ``python -m tools.attack_server [--json OUT] [--only 2,5]``

Starts servers of its own (Unix sockets in a temporary folder, loopback TCP; nothing leaves the host),
runs each attack of issue 41, items 1-7, as a bounded script, and prints a table: attack, what a sound
server does, what this one did, PASS or FAIL. Every socket has a timeout, every server is stopped at the
end; the whole run takes well under 5 minutes. Exit status 0 when every attack run passed, 1 otherwise.

1. method options that name files (``flow2d[estimator=corr,network=/etc/shadow]``, ``decomp[model=...]``):
   refused with BAD_INPUT before any file is touched, the same answer for an existing and a missing file.
2. file descriptors: a connection cap the open-file limit cannot hold refuses to start (exit 2); a server
   squeezed to no free descriptor refuses a burst of connections and keeps serving its open session.
3. a 10x10 patch of 2e16 in sRGB-float colour (linear float32 overflows from ~1.2e16): refused, never an
   OK frame with non-finite pixels.
4. an opencv pose whose translation times ``meters_per_unit`` is not finite (1e300 x 1e10): refused.
5. another client's segment: a session over a Unix socket leaves nothing of itself in /dev/shm to list,
   open or overwrite; over TCP its named segment is mode 0600.
6. memory: a HELLO over ``--max-memory`` gets OVER_BUDGET and the server stays up; 16 HELLOs of 4K ``mvec``
   under the default budget are not all accepted.
7. motion vectors at 1/2 and 1/4 resolution, sampled where a GPU rendering at that resolution samples
   (the low-resolution pixel centres): ``mvec`` predicts a square (in front of a wall) moving 8 px a frame
   within 0.5 dB of what full-resolution vectors give, at four sub-pixel phases of its edges.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import select
import socket
import stat
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

from engine.runtime import protocol as wire
from engine.runtime.client import Client, ServerError
from engine.runtime.protocol import MotionPlane, Status
from engine.runtime.session import SessionConfig

ROOT = Path(__file__).resolve().parents[1]
SHM = Path("/dev/shm")
#: Seconds any one reply may take; a server start may take this long too.
TIMEOUT = 60.0
W, H = 64, 48
K = np.array([[50.0, 0.0, W / 2], [0.0, 50.0, H / 2], [0.0, 0.0, 1.0]])


@dataclass
class Outcome:
    """One row of the table."""

    item: int
    attack: str
    expected: str
    observed: str
    passed: bool

    def __post_init__(self) -> None:
        self.passed = bool(self.passed)


class Served:
    """An ``interleave serve`` process of this run: started on ``listen`` with ``options``, stopped on exit."""

    def __init__(self, listen: str, *options: str, preexec: Optional[Callable[[], None]] = None) -> None:
        self.log = tempfile.NamedTemporaryFile("w+", prefix="attack-server-", suffix=".log")
        self.proc = subprocess.Popen([sys.executable, "-m", "engine.cli", "serve", "--listen", listen, *options],
                                     cwd=ROOT, stdout=subprocess.PIPE, stderr=self.log, text=True,
                                     preexec_fn=preexec)
        ready, _, _ = select.select([self.proc.stdout], [], [], TIMEOUT)
        line = self.proc.stdout.readline() if ready else ""
        if "listening on" not in line:
            self.proc.kill()
            self.proc.wait()
            text = self.stderr().strip()
            self.stop()
            raise RuntimeError(f"the server did not start: {text or line.strip() or 'no output'}")
        self.address = line.split("listening on ", 1)[1].strip()

    @property
    def pid(self) -> int:
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stderr(self) -> str:
        self.log.flush()
        return Path(self.log.name).read_text()

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()

    def __enter__(self) -> "Served":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def config(**change) -> SessionConfig:
    fields = dict(engine="opencv", width=W, height=H, method="reproject")
    fields.update(change)
    return SessionConfig(**fields)


def wall(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Colour (a smooth pattern) and depth (a wall 2 m away) of a W x H frame."""
    rows, cols = np.mgrid[0:H, 0:W].astype(np.float32)
    color = np.stack([0.5 + 0.4 * np.sin(cols / 5.0 + seed), 0.5 + 0.4 * np.cos(rows / 4.0), np.full_like(rows, 0.3)],
                     axis=-1)
    return color.astype(np.float32), np.full((H, W), 2.0, np.float32)


def pose(x: float = 0.0) -> np.ndarray:
    p = np.eye(4)
    p[0, 3] = -x
    return p


def status_of(call: Callable[[], object]) -> tuple[str, str]:
    """(status name, text) of a client call: OK, an error status, or the connection's fate."""
    try:
        call()
        return "OK", ""
    except ServerError as exc:
        return getattr(exc.status, "name", str(exc.status)), exc.text
    except (ConnectionError, OSError) as exc:
        return "CLOSED", f"{type(exc).__name__}: {exc}"


def served_still(server: Served) -> bool:
    """The server is alive and a new client gets a prediction."""
    if not server.alive():
        return False
    try:
        with Client(server.address, timeout=TIMEOUT) as client:
            client.hello(config())
            client.submit(*wall(), pose(), K, 0.0)
            client.predict(pose(0.01), K, 0.05)
            client.bye()
        return True
    except (ServerError, ConnectionError, OSError):
        return False


# --------------------------------------------------------------------------------------------
# The attacks
# --------------------------------------------------------------------------------------------

def attack_file_options(server: Served) -> list[Outcome]:
    """Item 1: a method option that names a file reaches no file, and the answer says nothing of it."""
    missing = f"/nonexistent-{os.getpid()}/m.onnx"
    rows = []
    for template in ("flow2d[estimator=corr,network={}]", "decomp[model={}]", "decomp[infill_model={}]"):
        answers = {}
        for path in ("/etc/shadow", "/proc/self/environ", "m.onnx", missing):  # m.onnx: the server's own cwd
            def run(method=template.format(path)) -> None:
                with Client(server.address, timeout=TIMEOUT) as client:
                    client.hello(config(method=method))
                    for i in range(2):  # a network loaded lazily would be read by the first prediction
                        client.submit(*wall(i), pose(0.01 * i), K, 0.1 * i)
                    client.predict(pose(0.02), K, 0.15)
            status, text = status_of(run)
            answers[path] = (status, text.replace(path, "PATH"))
        statuses = {a[0] for a in answers.values()}
        same = len(set(answers.values())) == 1
        passed = statuses == {"BAD_INPUT"} and same and server.alive()
        observed = ", ".join(f"{p}: {s}" for p, (s, _) in answers.items())
        rows.append(Outcome(1, template.format("PATH"), "BAD_INPUT at HELLO, the same text for an existing and a "
                                                        "missing file", observed + ("" if same else "; texts differ"),
                            passed))
    return rows


def _hello_once(address: str) -> None:
    with Client(address, timeout=5.0) as client:
        client.hello(config())


def _limit_fds(limit: int) -> Callable[[], None]:
    def preexec() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (limit, limit))
    return preexec


def attack_fd_exhaustion(tmp: Path) -> list[Outcome]:
    """Item 2: the cap against the open-file limit at start; a burst with no descriptor left."""
    rows = []
    try:
        run: Optional[subprocess.CompletedProcess] = subprocess.run(
            [sys.executable, "-m", "engine.cli", "serve", "--listen", f"unix:{tmp / 'cap.sock'}",
             "--max-connections", "600"], cwd=ROOT, capture_output=True, text=True, timeout=20,
            preexec_fn=_limit_fds(256))
    except subprocess.TimeoutExpired:  # it started (and was killed at the timeout)
        run = None
    lines = run.stderr.strip().splitlines() if run is not None else []
    rows.append(Outcome(2, "--max-connections 600 under ulimit -n 256", "refuses to start: exit 2, one line",
                        f"exit {run.returncode}: {lines[-1] if lines else '(nothing on stderr)'}" if run is not None
                        else "started and served (still running after 20 s)",
                        run is not None and run.returncode == 2 and len(lines) == 1))
    with Served(f"unix:{tmp / 'fd.sock'}", "--max-connections", "8", preexec=_limit_fds(128)) as server:
        with Client(server.address, timeout=TIMEOUT) as victim:
            victim.hello(config())
            victim.submit(*wall(), pose(), K, 0.0)
            before = victim.predict(pose(0.01), K, 0.05).color
            used = {int(n) for n in os.listdir(f"/proc/{server.pid}/fd")}
            resource.prlimit(server.pid, resource.RLIMIT_NOFILE, (min(set(range(len(used) + 1)) - used), 128))
            burst = [status_of(lambda: _hello_once(server.address))[0] for _ in range(100)]
            alive = server.alive()
            same = alive and status_of(lambda: np.testing.assert_array_equal(
                victim.predict(pose(0.01), K, 0.05).color, before))[0] == "OK"
            if alive:
                resource.prlimit(server.pid, resource.RLIMIT_NOFILE, (128, 128))
        serves = served_still(server)
        served_in_burst = burst.count("OK")
        rows.append(Outcome(2, "100 connections with no descriptor left (prlimit)",
                            "each refused; the open session predicts the same frame; new sessions once freed",
                            f"{len(burst) - served_in_burst} refused, {served_in_burst} served; server "
                            f"{'alive' if alive else 'DEAD'}; open session {'same frame' if same else 'LOST'}; "
                            f"afterwards {'serves' if serves else 'does not serve'}",
                            alive and same and serves))
    return rows


def attack_inf_srgb(server: Served) -> list[Outcome]:
    """Item 3: sRGB-float colour that decodes to inf."""
    rows = []
    for method in ("reproject", "flow2d"):
        color, depth = wall()
        color[10:20, 10:20] = 2e16
        nonfinite: list[int] = []

        def run() -> None:
            with Client(server.address, timeout=TIMEOUT) as client:
                client.hello(config(color_in="srgb", method=method))
                client.submit(*wall(), pose(), K, 0.0)
                client.submit(color, depth, pose(0.01), K, 0.1)
                out = client.predict(pose(0.015), K, 0.15)
                nonfinite.append(int(np.count_nonzero(~np.isfinite(out.color))))
        status, text = status_of(run)
        observed = f"SUBMIT {status}" + (f"; PREDICT OK with {nonfinite[0]} non-finite values" if nonfinite else "")
        rows.append(Outcome(3, f"10x10 patch of 2e16, color_in=srgb, {method}", "SUBMIT BAD_INPUT naming 'color'",
                            observed, status == "BAD_INPUT" and "'color'" in text))
    return rows


def attack_nonfinite_pose(server: Served) -> list[Outcome]:
    """Item 4: an opencv translation that is finite until scaled by meters_per_unit (the depth, 2 units, stays
    finite in metres: only the pose overflows)."""
    view = pose()
    view[0, 3] = 1e300

    def run() -> None:
        with Client(server.address, timeout=TIMEOUT) as client:
            client.hello(config(meters_per_unit=1e10))
            client.submit(*wall(), view, K, 0.0)
            client.predict(view, K, 0.05)
    status, text = status_of(run)
    return [Outcome(4, "opencv translation 1e300 x meters_per_unit 1e10", "SUBMIT BAD_INPUT naming 'view'",
                    f"{status}: {text[:90]}" if text else status, status == "BAD_INPUT" and "'view'" in text)]


def attack_shared_segments(server: Served, tcp: Served) -> list[Outcome]:
    """Item 5: list /dev/shm for another client's segment, read its prediction, paint what it displays red."""
    rows = []
    with Client(server.address, timeout=TIMEOUT) as victim:
        layout = victim.hello(config())
        victim.submit(*wall(), pose(), K, 0.0)
        shown = victim.predict(pose(0.01), K, 0.05, copy=False).color  # shared memory, valid until the next request
        expected = shown.copy()
        found = sorted(p for p in SHM.iterdir() if p.name.startswith(f"interleave-{server.pid}-"))
        read = False
        red = np.tile(np.array([1.0, 0.0, 0.0], np.float32), W * H).tobytes()
        for path in found:  # what the attacker did: read the victim's prediction, then paint it red
            with open(path, "r+b") as f:
                f.seek(layout.color_out_offset)
                read |= np.array_equal(np.frombuffer(f.read(W * H * 12), np.float32).reshape(H, W, 3), expected)
                f.seek(layout.color_out_offset)
                f.write(red)
        intact = bool(np.array_equal(shown, expected))
        rows.append(Outcome(5, "Unix socket: list /dev/shm, read another client's prediction, paint it red",
                            "nothing of the session in /dev/shm: not read, what it displays unchanged",
                            f"{len(found)} segment(s) listed; prediction {'READ' if read else 'not read'}; "
                            f"displayed frame {'unchanged' if intact else 'PAINTED'}", not found and intact))
        del shown
        victim.bye()
    with Client(tcp.address, timeout=TIMEOUT) as victim:
        layout = victim.hello(config())
        path = SHM / layout.shm_name.lstrip("/")
        info = path.stat() if layout.shm_name and path.exists() else None
        ok = info is not None and stat.S_IMODE(info.st_mode) == 0o600 and info.st_uid == os.getuid()
        rows.append(Outcome(5, "TCP: the named segment's permissions",
                            "named /dev/shm/interleave-PID-RANDOM, mode 0600 (documented: same-user reachable)",
                            f"{path}: mode {oct(stat.S_IMODE(info.st_mode)) if info else 'MISSING'}", ok))
        victim.bye()
    return rows


def attack_memory(tmp: Path) -> list[Outcome]:
    """Item 6: a HELLO over --max-memory; 4K mvec sessions under the default budget."""
    rows = []
    try:
        from engine.runtime.server import session_footprint
        one = session_footprint("reproject", wire.make_layout("", W, H, 3, "linear", "linear"))
        options: tuple[str, ...] = ("--max-memory", str(int(1.5 * one)))
    except ImportError:  # a server without a memory budget
        options = ("--max-memory", str(1 << 20))
    try:
        with Served(f"unix:{tmp / 'memory.sock'}", *options) as server:
            with Client(server.address, timeout=TIMEOUT) as first, Client(server.address, timeout=TIMEOUT) as second:
                first.hello(config())
                status, _ = status_of(lambda: second.hello(config()))
                first.bye()
                after, _ = status_of(lambda: second.hello(config()))
                second.bye()
            alive = served_still(server)
            observed = f"second HELLO {status}; after the first's BYE {after}; server {'up' if alive else 'DOWN'}"
            passed = status == "OVER_BUDGET" and after == "OK" and alive
    except RuntimeError as exc:
        observed, passed = str(exc).splitlines()[-1][:120], False
    rows.append(Outcome(6, "a HELLO over --max-memory (room for one 64x48 reproject session)",
                        "OVER_BUDGET; accepted once the first session ends; server up", observed, passed))
    with Served(f"unix:{tmp / 'memory4k.sock'}", "--max-connections", "20") as server:
        clients, statuses = [], []
        try:
            for _ in range(16):  # HELLO only: a session's arrays are made by its frames, none is sent
                client = Client(server.address, timeout=TIMEOUT)
                clients.append(client)
                statuses.append(status_of(lambda c=client: c.hello(config(width=3840, height=2160, method="mvec"),
                                                                   motion=MotionPlane()))[0])
        finally:
            for client in clients:
                client.close()
        accepted = statuses.count("OK")
        try:
            from engine.runtime.server import ServerLimits, session_footprint
            budget = ServerLimits().memory_budget()
            per_session = session_footprint("mvec", wire.make_layout("", 3840, 2160, 3, "linear", "linear",
                                                                     MotionPlane()))
            fits = budget // per_session
            expected = (f"at most {fits} accepted (a budget of {budget / 2**30:.1f} GiB, {per_session / 1e9:.2f} GB "
                        f"each), the rest OVER_BUDGET")
        except ImportError:  # a server without a memory budget
            fits, expected = 0, "some refused with OVER_BUDGET"
        rows.append(Outcome(6, "16 HELLOs of 3840x2160 mvec, default budget", expected,
                            f"{accepted} accepted, {statuses.count('OVER_BUDGET')} OVER_BUDGET",
                            0 < accepted <= fits and accepted + statuses.count("OVER_BUDGET") == 16))
    return rows


#: Top edge of the square (full-resolution pixels; not on a pixel boundary, so no sample sits on an edge).
SQUARE_TOP = 36.3


def _square_scene(x: float, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Colour and depth: a red 24 px square 1.5 m away, its left edge at column ``x``, in front of a static
    textured wall 2 m away."""
    h, w = size
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float32)
    color = np.stack([0.3 + 0.2 * np.sin(cols / 3.0), 0.4 + 0.2 * np.cos(rows / 3.0 + cols / 7.0),
                      0.5 + 0.2 * np.sin(rows / 2.0)], axis=-1)
    inside = (cols + 0.5 >= x) & (cols + 0.5 < x + 24) & (rows + 0.5 >= SQUARE_TOP) & (rows + 0.5 < SQUARE_TOP + 24)
    color[inside] = (0.9, 0.1, 0.1)
    return color.astype(np.float32), np.where(inside, 1.5, 2.0).astype(np.float32)


def _square_vectors(x: float, step: float, size: tuple[int, int], plane: tuple[int, int]) -> np.ndarray:
    """Vectors of the square scene as a GPU rendering at the ``plane``'s (h, w) resolution writes them:
    sampled at its pixel centres, in its pixels, pointing to where the point was in the previous frame (the
    square moved ``step`` px to the right)."""
    (big_h, big_w), (h, w) = size, plane
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    fx, fy = (cols + 0.5) * big_w / w, (rows + 0.5) * big_h / h  # full-resolution point of each sample
    inside = (fx >= x) & (fx < x + 24) & (fy >= SQUARE_TOP) & (fy < SQUARE_TOP + 24)
    vectors = np.zeros((h, w, 2), np.float32)
    vectors[inside, 0] = -step * w / big_w
    return vectors


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(1.0 / mse)


def attack_low_res_vectors(server: Served) -> list[Outcome]:
    """Item 7: mvec with vectors at 1/1, 1/2 and 1/4 of 128x96 on a square moving 8 px a frame, its left
    edge at four sub-pixel phases (where a sample falls next to an edge differs from phase to phase)."""
    size, step = (96, 128), 16.0  # rendered every other frame: 16 px between rendered frames
    k = np.array([[100.0, 0.0, 64.0], [0.0, 100.0, 48.0], [0.0, 0.0, 1.0]])
    cfg = config(width=size[1], height=size[0], method="mvec", motion_units="pixels", motion_direction="previous",
                 motion_y_up=False)
    losses: dict[int, list[float]] = {2: [], 4: []}
    for x0 in (13.3, 14.3, 15.3, 16.3):
        scores = {}
        for factor in (1, 2, 4):
            plane = (size[0] // factor, size[1] // factor)
            with Client(server.address, timeout=TIMEOUT) as client:
                client.hello(cfg, motion=MotionPlane(plane[1], plane[0]))
                for i in range(3):
                    x = x0 + step * i
                    client.submit(*_square_scene(x, size), pose(), k, float(i),
                                  motion_vectors=_square_vectors(x, step, size, plane) if i else None)
                out = client.predict(pose(), k, 2.5)  # half-way to the next rendered frame: 8 px further
                scores[factor] = _psnr(out.color, _square_scene(x0 + 2.5 * step, size)[0])
                client.bye()
        for factor in losses:
            losses[factor].append(scores[1] - scores[factor])
    return [Outcome(7, f"mvec, vectors at 1/{factor} resolution, a square moving 8 px a frame (4 phases)",
                    "within 0.5 dB of full-resolution vectors at every phase",
                    "dB lost: " + ", ".join(f"{loss:+.2f}" for loss in found), max(found) <= 0.5)
            for factor, found in losses.items()]


# --------------------------------------------------------------------------------------------
# The run
# --------------------------------------------------------------------------------------------

def run_attacks(items: Sequence[int] = (1, 2, 3, 4, 5, 6, 7)) -> list[Outcome]:
    """Run the attacks of ``items`` against servers of this run; one row per probe, errors as FAIL rows."""
    rows: list[Outcome] = []
    with tempfile.TemporaryDirectory(prefix="attack-") as folder:
        tmp = Path(folder)
        with Served(f"unix:{tmp / 'main.sock'}") as server, Served("tcp:0") as tcp:
            plan: list[tuple[int, str, Callable[[], list[Outcome]]]] = [
                (1, "file-naming method options", lambda: attack_file_options(server)),
                (2, "file-descriptor exhaustion", lambda: attack_fd_exhaustion(tmp)),
                (3, "inf sRGB-float patch", lambda: attack_inf_srgb(server)),
                (4, "non-finite opencv pose", lambda: attack_nonfinite_pose(server)),
                (5, "another client's segment", lambda: attack_shared_segments(server, tcp)),
                (6, "memory over budget", lambda: attack_memory(tmp)),
                (7, "low-resolution motion vectors", lambda: attack_low_res_vectors(server)),
            ]
            for item, name, attack in plan:
                if item not in items:
                    continue
                try:
                    rows += attack()
                except Exception as exc:  # noqa: BLE001 - a probe that breaks is a failed row, not a dead run
                    rows.append(Outcome(item, name, "(the probe runs)", f"probe error {type(exc).__name__}: {exc}",
                                        False))
            if not server.alive():
                rows.append(Outcome(0, "the shared server after all attacks", "alive", "DEAD", False))
    return rows


def table(rows: Sequence[Outcome]) -> str:
    lines = ["| item | attack | expected | observed | result |", "|---|---|---|---|---|"]
    lines += [f"| {r.item} | {r.attack} | {r.expected} | {r.observed} | {'PASS' if r.passed else 'FAIL'} |"
              for r in rows]
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.attack_server", description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", default="1,2,3,4,5,6,7", help="items of issue 41 to run (default: all, 1-7)")
    parser.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = parser.parse_args(argv)
    items = tuple(int(v) for v in args.only.split(",") if v.strip())
    start = time.perf_counter()
    rows = run_attacks(items)
    print(table(rows))
    failed = sum(not r.passed for r in rows)
    print(f"\n{len(rows) - failed} of {len(rows)} passed in {time.perf_counter() - start:.0f} s")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"rows": [asdict(r) for r in rows]}, indent=1) + "\n")
    return 0 if failed == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
