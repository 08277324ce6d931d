"""The attack command of issue 41 (``python -m tools.attack_server``) runs, prints its table and passes the
attacks this branch fixes: file-descriptor exhaustion (item 2), another client's segment (item 5) and memory
over budget (item 6). The other items' probes are run by the command itself (``--only 1,3,4,7``)."""
from __future__ import annotations

import json
import os
import socket
from pathlib import Path

import pytest

from tools import attack_server

pytestmark = pytest.mark.skipif(not Path("/dev/shm").is_dir() or not hasattr(socket, "AF_UNIX")
                                or not hasattr(os, "memfd_create") or not Path("/proc/self/fd").is_dir(),
                                reason="needs Linux: /dev/shm, Unix sockets, memfd, /proc")


def test_the_attacks_on_descriptors_segments_and_memory_pass_and_are_tabled(tmp_path, capsys):
    out = tmp_path / "attack.json"
    assert attack_server.main(["--only", "2,5,6", "--json", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert sorted({r["item"] for r in rows}) == [2, 5, 6] and len(rows) == 6
    assert all(r["passed"] for r in rows), [r for r in rows if not r["passed"]]
    printed = capsys.readouterr().out
    assert printed.count("| PASS |") == 6 and "6 of 6 passed" in printed


def test_a_failed_attack_is_a_fail_row_and_exit_status_1(monkeypatch, capsys):
    """A probe that finds a hole, or breaks, is a FAIL row; the run goes on and exits 1."""
    def broken(server):
        raise OSError("the probe broke")
    monkeypatch.setattr(attack_server, "attack_nonfinite_pose", broken)
    assert attack_server.main(["--only", "4"]) == 1
    printed = capsys.readouterr().out
    assert "probe error OSError: the probe broke" in printed and "| FAIL |" in printed
