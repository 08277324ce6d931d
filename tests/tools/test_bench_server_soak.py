"""The server soak benchmark runs and reports what it measured (a short run; the real one is 10,000 frames)."""
import re

from tools.bench_server_soak import main


def test_short_soak_prints_usage_samples_and_the_summary(capsys):
    assert main(["--frames", "120", "--clients", "2", "--every", "20", "--size", "32x24"]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if re.match(r"\| \d+ \| [\d.]+ \| \d+ \| \d+ \|", line)]
    assert len(rows) >= 4  # before, under load, after
    assert "2 clients, 120 frames of 32x24" in out and "median PREDICT round trip" in out
