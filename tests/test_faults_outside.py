"""Faults from outside the package (issue 58): the default config, signals during start-up, a
broken installed plugin, a second writer, Gymnasium constructors and the one-line messages.

Commands run in this process through :func:`taskvar_torch.cli.main` unless the attack is a signal,
an installed plugin or a locale (then ``python -m taskvar_torch.cli``, ~5 s each).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from taskvar_torch import cli

torch.set_num_threads(1)
ROOT = Path(__file__).resolve().parents[1]
TINY = [  # a run of ~2 s
    "env.num_envs=4",
    "train.frames_per_batch=100",
    "train.total_frames=300",
    "train.log_every=300",
    "train.init_random_frames=100",
    "train.batch_size=16",
    "train.updates_per_batch=1",
    "train.buffer_size=1000",
]


def run(argv: list[str], capsys) -> tuple[int, str, list[str]]:
    """``taskvar ARGV`` in this process: ``(status, stdout, stderr lines)``."""
    try:
        status = cli.main(argv)
    except SystemExit as e:
        status = e.code
    out, err = capsys.readouterr()
    return status, out, [line for line in err.splitlines() if line.strip()]


def refused(outcome: tuple[int, str, list[str]], command: str, *needles: str) -> str:
    """One line ``taskvar COMMAND: error: ...`` with every needle, status 2."""
    status, _, lines = outcome
    assert status == 2, lines
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"taskvar {command}: error: "), lines[0]
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def command(*args: str, env: dict | None = None, timeout: int = 120) -> subprocess.CompletedProcess:
    """``python -m taskvar_torch.cli ARGS`` (the command, as its console script starts it)."""
    full = {**os.environ, "OMP_NUM_THREADS": "1", **(env or {})}
    cmd = [sys.executable, "-m", "taskvar_torch.cli", *args]
    return subprocess.run(cmd, env=full, capture_output=True, text=True, timeout=timeout, cwd=ROOT)


# --------------------------------------------------------------------------------------------
# the default config: env.windy.horizon null


@pytest.mark.slow
@pytest.mark.parametrize(
    "text, extra",
    [
        ("", []),
        ("null\n", []),
        ("family: windy\nenv:\n  windy:\n    horizon: 30\n", ["env.windy.horizon=null"]),
    ],
)
def test_an_empty_config_trains_summarises_and_exits_0(text, extra, tmp_path, capsys):
    """The schema defaults (windy, env.windy.horizon null) train, print the oracle summary with
    the layout's default horizon, and exit 0."""
    config = tmp_path / "empty.yaml"
    config.write_text(text)
    out = tmp_path / "run"
    argv = ["train", str(config), "--out", str(out), *TINY, *extra, "--no-progress"]
    status, stdout, lines = run(argv, capsys)
    assert status == 0, lines
    assert (out / "final.pt").is_file()
    assert "learnt heads vs exact oracle" in stdout
    assert "Traceback" not in "\n".join(lines)
    assert "in 100 steps" in stdout or "not learnt" not in stdout  # the 5x5 default horizon


# --------------------------------------------------------------------------------------------
# signals during Python's start-up imports


@pytest.mark.slow
@pytest.mark.parametrize("delay", [0.3, 1.5])
def test_sigterm_during_the_start_up_imports_prints_the_documented_line(delay):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "taskvar_torch.cli", "train", "--help"]
    p = subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    time.sleep(delay)  # within `import torch` (seconds)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 128 + signal.SIGTERM, err
    assert err.decode().strip() == "taskvar train: interrupted by SIGTERM"


def test_a_program_importing_the_package_keeps_its_signal_handlers():
    code = "import signal, taskvar_torch; print(signal.getsignal(signal.SIGTERM) is signal.SIG_DFL)"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert done.stdout.strip() == "True", done.stderr[-2000:]
