"""Every benchmark's ``--quick`` mode runs once and does not crash (no timing asserted).

Parametrised over ``benchmarks/*.py`` as found, so a new benchmark is covered as soon as it is
added (it needs a ``--quick`` flag: tiny sizes, a few seconds). Each runs as its own process from
the repository root (the scripts read ``configs/``), single-threaded, with a timeout of its own.
``benchmarks/no_host_sync.py`` is the CUDA sync-debug check of ``tests/test_no_host_sync.py``: with
a GPU it fails here on a host sync in a hot path; without one it says it was skipped.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = sorted((ROOT / "benchmarks").glob("*.py"))
TIMEOUT_S = 120  # per script; each takes ~5-40 s on the loaded 2-core machine


def test_benchmarks_are_found():
    assert len(SCRIPTS) >= 12


@pytest.mark.parametrize("script", SCRIPTS, ids=[s.stem for s in SCRIPTS])
def test_quick_mode_runs(script: Path):
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    try:
        run = subprocess.run(
            [sys.executable, str(script), "--quick"],
            cwd=ROOT,
            env=env,
            capture_output=True,
            text=True,
            timeout=TIMEOUT_S,
        )
    except subprocess.TimeoutExpired as e:
        out = e.stdout.decode(errors="replace") if isinstance(e.stdout, bytes) else e.stdout
        pytest.fail(f"{script.name} --quick ran over {TIMEOUT_S} s:\n{out or ''}")
    assert run.returncode == 0, (
        f"{script.name} --quick exited {run.returncode}:\n{run.stderr[-4000:]}"
    )
    assert run.stdout.strip(), f"{script.name} --quick printed nothing:\n{run.stderr[-2000:]}"
