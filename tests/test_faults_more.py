"""More faults: the disk filling up during a checkpoint write, a checkpoint from a newer format or
missing an entry, a sweep killed part-way then resumed, a Ray worker killed inside a sweep point.

Faults fire in new processes through ``sitecustomize.py`` (:data:`HOOK`), put on ``PYTHONPATH``:
every Python process of the command (the CLI and, on Ray, each worker) runs it at start-up, and it
patches ``taskvar_torch.training.run_state`` and the windy Figure 2 experiment when they are first imported.
``FAULT=fsize``: once the first checkpoint is written (the next batch), the largest file the
process may write (``RLIMIT_FSIZE``) becomes that checkpoint's size, so the next, larger one
cannot be written (``SIGXFSZ`` ignored: ``write`` fails with ``EFBIG``, as on a full disk).
``FAULT=kill``: a sweep point whose seed is in ``KILL_SEEDS`` SIGKILLs its own process after its
first training batch, once (``KILL_ONCE``) or on every try; each kill appends a line to
``KILL_DIR/seed=<seed>``.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from budgets import CHECKPOINTED, SWEEP_POINT  # tests/budgets.py

from taskvar_torch import cli
from taskvar_torch.checkpoint import (
    FORMAT,
    FORMAT_VERSION,
    RESUME_ENTRIES,
    CheckpointError,
    load_checkpoint,
    require_entries,
)
from taskvar_torch.factory import load_heads

torch.set_num_threads(1)
ROOT = Path(__file__).resolve().parents[1]
WINDY = str(ROOT / "configs" / "windy.yaml")

HOOK = textwrap.dedent(
    """
    import importlib.abc, importlib.util, os, signal, sys

    FAULT = os.environ.get("FAULT", "")

    def patch_train(T):
        epsilon_at = T.epsilon_at
        def hooked(frames, t):
            first = os.path.join(os.environ["FAULT_OUT"], "checkpoint_000001000.pt")
            if frames > 1000 and os.path.exists(first) and not hooked.done:
                import resource
                signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # write fails with EFBIG instead
                size = os.path.getsize(first)
                resource.setrlimit(resource.RLIMIT_FSIZE, (size, resource.RLIM_INFINITY))
                hooked.done = True
            return epsilon_at(frames, t)
        hooked.done = False
        T.epsilon_at = hooked

    def patch_fig2(W):
        import taskvar_torch.training.run_state as T
        train = W.train
        def hooked(cfg, out, **kwargs):
            seeds = [int(s) for s in os.environ["KILL_SEEDS"].split(",")]
            log = os.path.join(os.environ["KILL_DIR"], f"seed={cfg.seed}")
            once = cfg.seed in [int(s) for s in os.environ.get("KILL_ONCE", "").split(",") if s]
            if cfg.seed in seeds and not (once and os.path.exists(log)):
                epsilon_at = T.epsilon_at
                def killer(frames, t):
                    if frames > 0:  # after the first batch: in the middle of the point
                        with open(log, "a") as f:
                            f.write(f"{os.getpid()}\\n")
                        os.kill(os.getpid(), signal.SIGKILL)
                    return epsilon_at(frames, t)
                T.epsilon_at = killer
            return train(cfg, out, **kwargs)
        W.train = hooked

    PATCHES = {"taskvar_torch.training.run_state": patch_train} if FAULT == "fsize" else {}
    if FAULT == "kill":
        PATCHES["taskvar_torch.families.windy.fig2"] = patch_fig2

    class Finder(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path, target=None):
            if name not in PATCHES:
                return None
            sys.meta_path.remove(self)
            try:
                spec = importlib.util.find_spec(name)
            finally:
                sys.meta_path.insert(0, self)
            exec_module, patch = spec.loader.exec_module, PATCHES.pop(name)
            def patched(module):
                exec_module(module)
                patch(module)
            spec.loader.exec_module = patched
            return spec

    if PATCHES:
        sys.meta_path.insert(0, Finder())
    """
)


def taskvar(tmp: Path, *args: str, **env: str) -> subprocess.CompletedProcess:
    """``taskvar ARGS`` in a new single-threaded process with :data:`HOOK` and ``env``."""
    hook_dir = tmp / "hook"
    hook_dir.mkdir(exist_ok=True)
    (hook_dir / "sitecustomize.py").write_text(HOOK)
    path = os.pathsep.join([str(hook_dir), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    full_env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": path, **env}
    full_env.pop("RL_LOGGING_LEVEL", None)
    cmd = [sys.executable, "-m", "taskvar_torch.cli", *args]
    return subprocess.run(cmd, env=full_env, capture_output=True, text=True, timeout=300, cwd=ROOT)


def one_line(stderr: str, *needles: str) -> str:
    lines = [x for x in stderr.splitlines() if x.strip()]
    assert len(lines) == 1, stderr[-3000:]
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


# --------------------------------------------------------------------------------------------
# the disk fills up during a checkpoint write


@pytest.fixture(scope="module")
def disk_full(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    """``taskvar train`` that writes ``checkpoint_000001000.pt``, then cannot write the next."""
    tmp = tmp_path_factory.mktemp("fsize")
    out = tmp / "run"
    r = taskvar(tmp, "train", WINDY, "--out", str(out), *CHECKPOINTED, "--threads", "1",
                "--no-progress", FAULT="fsize", FAULT_OUT=str(out))  # fmt: skip
    return out, r


@pytest.mark.slow
def test_a_full_disk_during_a_checkpoint_write_keeps_the_previous_one(disk_full):
    out, r = disk_full
    assert r.returncode == 2, r.stderr[-3000:]
    one_line(
        r.stderr, "taskvar train: error: cannot use", "checkpoint_000002000.pt", "File too large"
    )
    names = sorted(p.name for p in out.iterdir())
    assert "checkpoint_000001000.pt" in names, names
    assert not [n for n in names if n.endswith(".tmp") or n.startswith("checkpoint_000002")]
    assert "final.pt" not in names
    bundle = load_checkpoint(out / "checkpoint_000001000.pt")  # intact and loadable
    assert bundle["counters"]["frames"] == 1000
    require_entries(bundle, out / "checkpoint_000001000.pt")  # still resumable
    heads, cfg = load_heads(out / "checkpoint_000001000.pt")
    assert cfg.train.total_frames == 3000 and heads is not None


# --------------------------------------------------------------------------------------------
# a checkpoint from a newer format, or missing an entry


def _bundle(disk_full) -> dict:
    out, r = disk_full
    if not (out / "checkpoint_000001000.pt").is_file():
        pytest.skip(f"the disk-full run wrote no first checkpoint: {r.stderr[-500:]}")
    bundle = load_checkpoint(out / "checkpoint_000001000.pt")
    for k in ("format", "format_version", "versions"):
        bundle.pop(k)
    return bundle


def _cli(argv: list[str], capsys) -> tuple[int, str]:
    try:
        status = cli.main(argv)
    except SystemExit as e:
        status = e.code
    return status, capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.parametrize("entry", [*RESUME_ENTRIES, "env", "carrier"])
def test_resuming_a_checkpoint_missing_an_entry_is_one_line(disk_full, tmp_path, capsys, entry):
    from taskvar_torch.checkpoint import save_checkpoint

    bundle = _bundle(disk_full)
    del bundle[entry]
    path = save_checkpoint(tmp_path / "edited.pt", bundle)
    status, err = _cli(["train", "--resume", str(path), "--out", str(tmp_path / "o")], capsys)
    assert status == 2
    one_line(err, "taskvar train: error:", f"has no {entry!r} entry", str(path))
    assert not (tmp_path / "o").exists()  # refused before any work


@pytest.mark.parametrize("command", ["train", "eval"])
@pytest.mark.parametrize(
    "change, needle",
    [
        ({"format_version": FORMAT_VERSION + 1}, f"has format version {FORMAT_VERSION + 1}"),
        ({"format_version": "2"}, "format_version is '2'"),
        ({"format_version": None}, "format_version is None"),
        ({"format": "taskvar_torch.checkpoint.v2"}, "is not a taskvar_torch checkpoint"),
        ({"config": None}, "it has no config dict"),
    ],
    ids=["newer", "str-version", "no-version", "other-format", "no-config"],
)
def test_a_newer_or_broken_format_is_refused_in_one_line(tmp_path, capsys, command, change, needle):
    data = {"format": FORMAT, "format_version": FORMAT_VERSION, "config": {}, "models": {}}
    data.update(change)
    data = {k: v for k, v in data.items() if v is not None}
    path = tmp_path / "c.pt"
    torch.save(data, path)
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path)
    assert "\n" not in str(info.value) and needle in str(info.value)
    argv = ["--resume" if command == "train" else "--checkpoint", str(path)]
    status, err = _cli([command, *argv, "--out", str(tmp_path / "o")], capsys)
    assert status == 2
    one_line(err, f"taskvar {command}: error:", needle)


def test_heads_bundle_is_not_resumable_in_one_line(tmp_path):
    with pytest.raises(CheckpointError) as info:
        require_entries({"config": {}, "models": {}, "heads_spec": {}}, tmp_path / "heads.pt")
    assert "cannot be resumed" in str(info.value) and "'optimizers', 'counters'" in str(info.value)
    assert "\n" not in str(info.value)


# --------------------------------------------------------------------------------------------
# a sweep killed part-way, then resumed


def _rows(out: Path) -> list[dict]:
    with open(out / "summary.csv") as f:
        return list(csv.DictReader(f))


@pytest.mark.slow
def test_a_killed_sweep_resumes_keeping_its_complete_points(tmp_path, capsys):
    out = tmp_path / "sweep"
    kills = tmp_path / "kills"
    kills.mkdir()
    argv = ["sweep", WINDY, "--backend", "local", "--quick", "--out", str(out), "--no-progress"]
    # --no-batch-seeds: each point trains in its own run, which the fault kills (a seed batch
    # trains both seeds in one run, tests/study/test_sweep_seeds.py)
    argv += ["--no-plots", "--no-batch-seeds", "seed=0,1", *SWEEP_POINT]
    r = taskvar(tmp_path, *argv, FAULT="kill", KILL_SEEDS="1", KILL_DIR=str(kills))
    assert r.returncode == -signal.SIGKILL, r.stderr[-3000:]
    assert (out / "seed=0" / "metrics.json").is_file()  # the first point completed
    assert not (out / "seed=1" / "metrics.json").exists() and not (out / "summary.json").exists()
    first = (out / "seed=0" / "metrics.json").read_bytes()

    status, err = _cli(argv, capsys)  # without --resume: refused, nothing touched
    assert status == 2
    one_line(err, "already holds results", "seed=0", "--resume")
    status, err = _cli([*argv, "--resume", "--overwrite"], capsys)
    assert status == 2
    one_line(err, "--resume keeps the completed points and --overwrite replaces them")
    other = [a.replace("eval.batch_size=20", "eval.batch_size=10") for a in argv]
    assert other != argv
    status, err = _cli([*other, "--resume"], capsys)  # another sweep
    assert status == 2
    one_line(err, "holds results of another config", "eval.batch_size differs", "seed=0")

    status = cli.main([*argv, "--resume"])
    printed = capsys.readouterr().out
    assert status == 0
    assert "1 of 2 points complete, running 1" in printed
    assert (out / "seed=0" / "metrics.json").read_bytes() == first  # kept, not run again
    assert (out / "seed=1" / "metrics.json").is_file()
    assert [r["point"] for r in _rows(out)] == ["seed=0", "seed=1"]
    summary = json.loads((out / "summary.json").read_text())
    assert [p["kept"] for p in summary["points"]] == [True, False]
    assert summary["rows"][0]["fraction_no_worse"] == json.loads(first)["fraction_no_worse"]
    assert all(r["fraction_no_worse"] for r in _rows(out))

    # a complete sweep resumed runs nothing and writes the same table
    status = cli.main([*argv, "--resume"])
    assert status == 0 and "2 of 2 points complete, running 0" in capsys.readouterr().out
    rows = json.loads((out / "summary.json").read_text())["rows"]
    drop = ("seconds",)  # a kept point's seconds: its metrics.json's wall time
    assert [{k: v for k, v in r.items() if k not in drop} for r in rows] == [
        {k: v for k, v in r.items() if k not in drop} for r in summary["rows"]
    ]


# --------------------------------------------------------------------------------------------
# a Ray worker killed inside a sweep point


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_a_ray_worker_killed_in_a_point_is_retried_or_reported(tmp_path):
    """Point seed=0's worker is killed once (retried: it completes); seed=1's on every try (after
    RAY_RETRIES retries it is a failed row); the sweep finishes with a row for each."""
    pytest.importorskip("ray")
    from taskvar_torch.study.sweep import RAY_RETRIES

    out = tmp_path / "sweep"
    kills = tmp_path / "kills"
    kills.mkdir()
    argv = ["sweep", WINDY, "--backend", "ray", "--workers", "2", "--quick", "--out", str(out)]
    argv += ["--no-progress", "--no-plots", "--no-batch-seeds", "seed=0,1", *SWEEP_POINT]
    r = taskvar(tmp_path, *argv, FAULT="kill", KILL_SEEDS="0,1", KILL_ONCE="0", KILL_DIR=str(kills))
    assert r.returncode == 0, r.stderr[-3000:]
    assert len((kills / "seed=0").read_text().split()) == 1
    assert len((kills / "seed=1").read_text().split()) == 1 + RAY_RETRIES
    rows = _rows(out)
    assert [row["point"] for row in rows] == ["seed=0", "seed=1"]
    assert rows[0]["error"] == "" and rows[0]["fraction_no_worse"] != ""
    assert rows[1]["error"].startswith("WorkerCrashedError") and rows[1]["fraction_no_worse"] == ""
    assert "seed=1" in r.stdout and "WorkerCrashedError" in r.stdout  # the printed table
    summary = json.loads((out / "summary.json").read_text())
    assert [p["error"] is None for p in summary["points"]] == [True, False]
    assert (out / "seed=0" / "metrics.json").is_file()
    assert not (out / "seed=1" / "metrics.json").exists()
