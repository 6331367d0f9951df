"""``train.logger``: TensorBoard event files hold the CSV files' scalars, a missing logger
package is a one-line error naming the pip extra, and a bad choice is refused by the config."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

import taskvar_torch.training.run_logs as T
from taskvar_torch.cli import main

CONFIG = "configs/windy.yaml"
TINY = [  # as tests/test_train.py: a few seconds of training, four log rows
    "env.num_envs=4",
    "train.frames_per_batch=100",
    "train.total_frames=2000",
    "train.checkpoint_every=0",
    "train.log_every=500",
    "train.init_random_frames=300",
    "train.batch_size=32",
    "train.updates_per_batch=2",
    "train.buffer_size=5000",
]


def read_csv_scalars(folder: Path) -> dict[str, list[tuple[int, float]]]:
    """``{name: [(frame, value), ...]}`` from ``folder/logs/scalars/<name>.csv``."""
    out = {}
    for f in sorted((folder / "logs" / "scalars").glob("*.csv")):
        rows = [line.split(",") for line in f.read_text().splitlines()]
        out[f.stem] = [(int(step), float(value)) for step, value in rows]
    return out


@pytest.mark.slow
def test_tensorboard_events_hold_the_csv_scalars_and_the_log_has_no_carriage_returns(tmp_path):
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out = tmp_path / "run"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "RL_WARNINGS": "False"}
    cmd = [sys.executable, "-m", "taskvar_torch.cli", "train", CONFIG, "--out", str(out)]
    cmd += [*TINY, "train.logger=tensorboard", "--threads", "1"]  # progress on, stderr a pipe
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]

    csv = read_csv_scalars(out)  # the CSV files stay where they always were
    assert {"loss_averaging", "episode_return", "epsilon", "updates"} <= set(csv)
    assert [step for step, _ in csv["epsilon"]] == [500, 1000, 1500, 2000]
    events = list((out / "logs" / "tensorboard").glob("events.out.tfevents.*"))
    assert events, sorted(p.name for p in (out / "logs").rglob("*"))
    acc = EventAccumulator(str(out / "logs" / "tensorboard"), size_guidance={"scalars": 0})
    acc.Reload()
    assert set(acc.Tags()["scalars"]) == set(csv)
    for name, rows in csv.items():
        tb = [(e.step, e.value) for e in acc.Scalars(name)]
        assert [s for s, _ in tb] == [s for s, _ in rows], name
        assert [v for _, v in tb] == pytest.approx([v for _, v in rows], rel=1e-6), name

    # not a terminal: plain progress lines, no carriage-return frames (taskvar_torch/progress.py)
    assert "\r" not in r.stderr
    lines = [line for line in r.stderr.splitlines() if line.startswith("train:")]
    assert 1 <= len(lines) <= 22 and "100%" in lines[-1], r.stderr[-2000:]


@pytest.mark.parametrize("kind", ["tensorboard", "wandb", "mlflow"])
def test_a_missing_logger_package_is_one_line_naming_the_extra(kind, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(T, "_installed", lambda package: False)
    out = tmp_path / "run"
    code = main(
        ["train", CONFIG, "--out", str(out), *TINY, f"train.logger={kind}", "--no-progress"]
    )
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err == (
        f"taskvar train: error: train.logger={kind} needs the {kind} package: "
        f"pip install 'taskvar-torch[{kind}]'"
    )
    assert not out.exists()  # refused before the run folder is made


def test_an_unknown_logger_is_refused_by_the_config(tmp_path, capsys):
    code = main(["train", CONFIG, "--out", str(tmp_path / "run"), "train.logger=neptune"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert "train.logger must be one of ['csv', 'mlflow', 'tensorboard', 'wandb']" in err[0]
