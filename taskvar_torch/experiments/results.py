"""Results-folder files: CSV and JSON written atomically (temporary file, then rename)."""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from taskvar_torch.config import atomic_write


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
