"""Results-folder files: CSV and JSON written atomically (temporary file, then rename)."""

from __future__ import annotations

import csv
import functools
import io
import json
import math
import subprocess
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from taskvar_torch.io import atomic_write


@functools.lru_cache(maxsize=1)
def code_version() -> dict[str, Any]:
    """The code a results folder was computed with, for ``metrics.json``'s ``code``
    (docs/report.md): the package ``version`` and its git ``commit`` (``-dirty`` where tracked files
    differ; ``None`` outside a checkout).
    """
    import taskvar_torch

    root = Path(taskvar_torch.__file__).resolve().parents[1]
    commit = None
    try:
        head = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "--show-toplevel", "HEAD"],
            capture_output=True, text=True, timeout=10, check=True,
        ).stdout.split()  # fmt: skip
        if len(head) == 2 and Path(head[0]).resolve() == root:  # the package's own checkout
            dirty = subprocess.run(
                ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                capture_output=True, text=True, timeout=10, check=True,
            ).stdout.strip()  # fmt: skip
            commit = head[1] + ("-dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        commit = None
    return {"version": str(taskvar_torch.__version__), "commit": commit}


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
