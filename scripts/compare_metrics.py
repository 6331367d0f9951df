"""Compare two results folders' ``metrics.json`` numbers exactly; exit 1 on any difference.

Timing (wall-clock seconds and rates) and file locations (``checkpoint``) are skipped; every other leaf must be equal, floats bit for
bit. Used to show that a restructuring changed no behaviour: run the quick experiments at the old
and the new commit and compare, e.g.::

    taskvar experiment windy-fig2 --quick --no-plots --out /tmp/old/windy   # at the old commit
    taskvar experiment windy-fig2 --quick --no-plots --out /tmp/new/windy   # at the new commit
    python scripts/compare_metrics.py /tmp/old/windy /tmp/new/windy
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

TIMING = ("seconds", "timing", "per_s", "wall")  # key fragments of wall-clock figures
LOCATIONS = ("checkpoint",)  # keys holding where a run wrote its files, not what it measured


def _is_timing(key: str) -> bool:
    return any(t in key.lower() for t in TIMING) or key in LOCATIONS


def differences(a: Any, b: Any, path: str = "") -> list[str]:
    """Every leaf where ``a`` and ``b`` differ (``path: a != b``), timing keys skipped."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = [f"{path}/{k}: only in one" for k in sorted(set(a) ^ set(b), key=str)]
        for k in a.keys() & b.keys():
            if not _is_timing(str(k)):
                out += differences(a[k], b[k], f"{path}/{k}")
        return out
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{path}: {len(a)} vs {len(b)} items"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in differences(x, y, f"{path}[{i}]")]
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return []
    if a == b and type(a) is type(b):
        return []
    return [f"{path}: {repr(a)[:60]} != {repr(b)[:60]}"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("old", type=Path, help="results folder (or metrics.json)")
    parser.add_argument("new", type=Path, help="results folder (or metrics.json)")
    args = parser.parse_args(argv)
    docs = []
    for p in (args.old, args.new):
        f = p / "metrics.json" if p.is_dir() else p
        docs.append(json.loads(f.read_text()))
    diff = differences(*docs)
    for d in diff[:50]:
        print(d)
    print(f"{len(diff)} difference(s)" if diff else "identical (timing skipped)")
    return 1 if diff else 0


if __name__ == "__main__":
    sys.exit(main())
