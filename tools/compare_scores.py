"""Are two evaluation runs score-identical? ``python -m tools.compare_scores A.json B.json``

Reads two JSON files written by ``interleave eval --json`` or ``interleave demo`` (``results.json``) and
compares every score of every (sequence, method, k) record, the per-step scores included, exactly (NaN equals
NaN); times (``ms_per_frame``, ``stages_ms``) are ignored. Prints each difference and a summary line; exits 1
if any score differs or a record is missing from one side. Used to check that a refactor changed no score.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any, Optional, Sequence

#: Record fields that are timings, not scores.
TIMING_FIELDS = ("ms_per_frame", "stages_ms")


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    return a == b


def load_records(path: Path) -> dict[tuple, dict]:
    """The records of an eval/demo JSON keyed by (sequence, method, k)."""
    doc = json.loads(Path(path).read_text())
    return {(r["sequence"], r["method"], r["k"]): r for r in doc["records"]}


def score_differences(a: dict[tuple, dict], b: dict[tuple, dict]) -> list[str]:
    """One line per record missing from one side and per score field that differs."""
    out = [f"{key}: only in {'the first' if key in a else 'the second'}" for key in sorted(set(a) ^ set(b), key=str)]
    for key in sorted(set(a) & set(b), key=str):
        for name in sorted((set(a[key]) | set(b[key])) - set(TIMING_FIELDS)):
            if not _same(a[key].get(name), b[key].get(name)):
                out.append(f"{key} {name}: {a[key].get(name)!r} != {b[key].get(name)!r}")
    return out


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.compare_scores", description=__doc__.split("\n\n")[0])
    parser.add_argument("first", type=Path, help="eval --json output or a demo's results.json")
    parser.add_argument("second", type=Path, help="the same for the other run")
    args = parser.parse_args(argv)
    a, b = load_records(args.first), load_records(args.second)
    lines = score_differences(a, b)
    for line in lines:
        print(line)
    print(f"{len(set(a) & set(b))} records compared, {len(lines)} differences")
    return 1 if lines else 0


if __name__ == "__main__":
    sys.exit(main())
