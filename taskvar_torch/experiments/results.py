"""Results-folder files: CSV and JSON written atomically (temporary file, then rename)."""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from taskvar_torch.io import atomic_write


def write_csv(path: Path, rows: Sequence[dict[str, Any]], fields: Sequence[str]) -> None:
    """``rows`` as CSV with columns ``fields`` (extra keys ignored, missing ones empty)."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(fields), extrasaction="ignore", restval="")
    w.writeheader()
    w.writerows(rows)
    data = buf.getvalue().encode()
    atomic_write(path, lambda f: f.write(data))


def _finite(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def write_json(path: Path, obj: Any, indent: int = 2) -> None:
    """JSON with non-finite floats written as ``null`` (strict JSON)."""
    data = json.dumps(_finite(obj), indent=indent).encode()
    atomic_write(path, lambda f: f.write(data))


RESULT_NAMES = ("metrics.json", "summary.json", "per_trial.csv", "episodes.csv", "cells")
"""What an experiment or sweep folder holds once it has run (rep*/ and point folders aside)."""


def refuse_existing_results(out: Path, overwrite: bool, command: str) -> None:
    """A one-line ``ValueError`` when ``out`` already holds an experiment's results and
    ``overwrite`` is not set: no command silently replaces a user's results."""
    out = Path(out)
    if overwrite or not out.is_dir():
        return
    found = [n for n in RESULT_NAMES if (out / n).exists()]
    found += sorted(p.name for p in out.glob("rep*/final.pt"))
    if found:
        raise ValueError(
            f"--out {str(out)!r} already holds results ({', '.join(found)}); replace them with "
            f"--overwrite, or choose another --out ({command})"
        )
