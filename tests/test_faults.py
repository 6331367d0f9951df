"""Fault injection: SIGKILL at several points of a short run then ``--resume``; SIGINT
and SIGTERM; a second SIGINT during the checkpoint write; NaN weights; run-folder refusals.

A run is ``taskvar train`` in a new process on the 5x5 windy family (3000 frames, checkpoints
every 1000, a log row every 500). Faults fire at an exact frame through a hook installed before
the CLI starts (``HOOK``): the trainer calls ``epsilon_at(frames, ...)`` once per batch, after the
batch's updates and before its log row and checkpoint, and every file goes through ``torch.save``.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import gymnasium as gym
import pytest
import torch
from budgets import CHECKPOINTED  # tests/budgets.py
from test_train import assert_same  # tests/ is on sys.path (rootdir import mode)

import taskvar_torch.training.run_setup as B
import taskvar_torch.training.run_state as T
from taskvar_torch.checkpoint import load_checkpoint, make_bundle, save_checkpoint
from taskvar_torch.cli import main
from taskvar_torch.config import load_config
from taskvar_torch.run_folder import LOCK_NAME, ResultsFolder
from taskvar_torch.training import train
from taskvar_torch.training.learning import TrainingDiverged

torch.set_num_threads(1)
ROOT = Path(__file__).resolve().parents[1]
CONFIG = str(ROOT / "configs" / "windy.yaml")

HOOK = textwrap.dedent(
    """
    import os, signal, sys
    import torch
    import taskvar_torch.training.run_state as T
    from taskvar_torch.cli import main

    kind, frame = os.environ["FAULT"], int(os.environ["FAULT_FRAME"])
    sig = {"kill": signal.SIGKILL, "int": signal.SIGINT, "term": signal.SIGTERM}

    epsilon_at = T.epsilon_at
    def hooked_epsilon_at(frames, t):
        if frames == frame and kind in sig:  # after the batch's updates, before its log row
            os.kill(os.getpid(), sig[kind])
        return epsilon_at(frames, t)
    T.epsilon_at = hooked_epsilon_at

    save = torch.save
    def hooked_save(obj, f, *args, **kwargs):
        save(obj, f, *args, **kwargs)
        frames = obj.get("counters", {}).get("frames") if isinstance(obj, dict) else None
        if frames == frame and kind == "kill-in-write":  # written, fsync and rename pending
            os.kill(os.getpid(), signal.SIGKILL)
        if frames == frame and kind == "int-int-in-write":  # a second Ctrl-C during the write
            os.kill(os.getpid(), signal.SIGINT)
            sum(range(1000))  # the handler runs between bytecodes: here
    torch.save = hooked_save
    if kind == "int-int-in-write":  # the first Ctrl-C at the same frame
        T.epsilon_at = lambda frames, t: (
            os.kill(os.getpid(), signal.SIGINT) if frames == frame else None
        ) or epsilon_at(frames, t)
    sys.exit(main(sys.argv[1:]))
    """
)


def taskvar(*args: str, fault: str = "none", frame: int = -1) -> subprocess.CompletedProcess:
    """``taskvar ...`` in a new single-threaded process, with a fault at ``frame``."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "FAULT": fault, "FAULT_FRAME": str(frame)}
    env.pop("RL_LOGGING_LEVEL", None)
    cmd = [sys.executable, "-c", HOOK, *args, "--threads", "1", "--no-progress"]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, cwd=ROOT)


def read_logs(folder: Path) -> dict[str, list[str]]:
    """Every logged scalar's rows, except the wall-clock ``seconds``."""
    scalars = folder / "logs" / "scalars"
    return {
        f.stem: f.read_text().splitlines()
        for f in sorted(scalars.glob("*.csv"))
        if f.stem != "seconds"
    }


def assert_equals_reference(folder: Path, reference: Path) -> None:
    """Same files, same final bundle (weights, optimiser, replay, RNG, env...), same logs."""
    names = sorted(p.name for p in folder.iterdir())
    assert names == sorted(p.name for p in reference.iterdir()), names
    a, b = load_checkpoint(folder / "final.pt"), load_checkpoint(reference / "final.pt")
    a.pop("versions"), b.pop("versions")
    for x in (a, b):  # two processes: their unseeded global numpy and python RNGs (never drawn
        x["rng"].pop("numpy"), x["rng"].pop("python")  # from by the trainer) differ
    assert_same(a, b)
    assert read_logs(folder) == read_logs(reference)


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    """The uninterrupted run."""
    out = tmp_path_factory.mktemp("reference") / "run"
    r = taskvar("train", CONFIG, "--out", str(out), *CHECKPOINTED)
    assert r.returncode == 0, r.stderr[-2000:]
    return out, r


# ---- SIGKILL, then resume: equal to the uninterrupted run ----------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize(
    "fault, frame, resume_from",
    [
        (
            "kill",
            1700,
            "checkpoint_000001000.pt",
        ),  # between checkpoints, log rows past the last one
        ("kill-in-write", 2000, "checkpoint_000001000.pt"),  # during a periodic checkpoint write
        ("kill-in-write", 3000, "checkpoint_000002000.pt"),  # during the final write
    ],
)
def test_sigkill_then_resume_equals_the_uninterrupted_run(
    tmp_path, reference, fault, frame, resume_from
):
    out = tmp_path / "run"
    r = taskvar("train", CONFIG, "--out", str(out), *CHECKPOINTED, fault=fault, frame=frame)
    assert r.returncode == -signal.SIGKILL, r.stderr[-2000:]
    if fault == "kill-in-write":  # the killed write left its temporary file, not a partial one
        assert any(p.name.endswith(".tmp") for p in out.iterdir())
        assert not (out / f"checkpoint_{frame:09d}.pt").exists() and not (out / "final.pt").exists()
    r = taskvar("train", "--resume", str(out / resume_from), "--out", str(out))
    assert r.returncode == 0, r.stderr[-2000:]
    assert_equals_reference(out, reference[0])  # no temp file, no lock file left either


# ---- SIGINT / SIGTERM --------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("fault, status", [("int", 130), ("term", 143)])
def test_signal_writes_a_checkpoint_and_the_resume_line(tmp_path, reference, fault, status):
    out = tmp_path / "run"
    r = taskvar("train", CONFIG, "--out", str(out), *CHECKPOINTED, fault=fault, frame=1300)
    assert r.returncode == status, r.stderr[-2000:]
    ckpt = out / "checkpoint_000001300.pt"  # mid logging interval: pending loss sums are saved
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    command = f"taskvar train --resume {ckpt} --out {out}"
    assert lines[0].endswith(f"continue with: {command}"), lines[0]
    assert load_checkpoint(ckpt)["counters"]["frames"] == 1300
    assert not (out / "checkpoint_000001000.pt").exists()  # the newest checkpoint is kept
    if fault == "term":
        return  # the resume below is the same for both signals
    r = taskvar(*command.split()[1:])  # the printed command, as printed
    assert r.returncode == 0, r.stderr[-2000:]
    assert_equals_reference(out, reference[0])


@pytest.mark.slow
def test_second_sigint_during_the_write_aborts_without_a_partial_file(tmp_path):
    out = tmp_path / "run"
    r = taskvar(
        "train", CONFIG, "--out", str(out), *CHECKPOINTED, fault="int-int-in-write", frame=1300
    )
    assert r.returncode == 130, r.stderr[-2000:]
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "aborted by a second signal" in lines[0], r.stderr
    assert "checkpoint_000001000.pt" in lines[0]
    assert sorted(p.name for p in out.iterdir()) == [
        "checkpoint_000001000.pt",
        "config.yaml",
        "logs",
    ]
    load_checkpoint(out / "checkpoint_000001000.pt")  # intact


# ---- NaN weights are never written -------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("frame, group", [(2000, "heads"), (3000, "optimizer")])
def test_nan_weights_are_never_written(tmp_path, monkeypatch, frame, group):

    learners = []
    make_learner = B.make_learner
    monkeypatch.setattr(
        B, "make_learner", lambda *a: learners.append(make_learner(*a)) or learners[-1]
    )
    epsilon_at = T.epsilon_at

    def inject(frames, t):  # after the batch's updates: its losses were finite
        if frames == frame:
            learner = learners[-1]
            if group == "heads":
                next(learner.heads.parameters()).data[0] = float("nan")
            else:
                state = next(iter(learner.optimizer.state.values()))
                state["exp_avg"].view(-1)[0] = float("inf")
        return epsilon_at(frames, t)

    monkeypatch.setattr(T, "epsilon_at", inject)
    cfg = load_config(CONFIG, CHECKPOINTED)
    with pytest.raises(
        TrainingDiverged, match=f"non-finite values in the {group} at frame {frame}"
    ):
        train(cfg, tmp_path, progress=False)
    last = "checkpoint_000001000.pt" if frame == 2000 else "checkpoint_000002000.pt"
    assert sorted(p.name for p in tmp_path.iterdir()) == [last, "config.yaml", "logs"]
    bundle = load_checkpoint(tmp_path / last)
    for name in ("heads", "targets"):
        assert all(torch.isfinite(v).all() for v in bundle["models"][name].values())


@pytest.mark.slow
def test_eval_and_resume_refuse_a_bundle_with_non_finite_heads(reference, tmp_path, capsys):
    bundle = load_checkpoint(reference[0] / "final.pt")
    bundle.pop("format"), bundle.pop("format_version")
    name = next(iter(bundle["models"]["heads"]))
    bundle["models"]["heads"][name].view(-1)[0] = float("nan")
    bad = save_checkpoint(tmp_path / "nan.pt", bundle)
    for argv in (
        ["eval", "--checkpoint", str(bad), "--episodes", "5", "--no-progress"],
        ["train", "--resume", str(bad), "--out", str(tmp_path / "resumed"), "--no-progress"],
    ):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "non-finite heads" in err[0], err
    assert not (tmp_path / "resumed").exists()


# ---- the run folder ----------------------------------------------------------------------------


def _one_line_error(capsys, *needles: str) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "error" in err[0], err
    for n in needles:
        assert n in err[0], err[0]
    return err[0]


def _copy_run(src: Path, dst: Path) -> Path:

    shutil.copytree(src, dst)
    return dst


@pytest.mark.slow
def test_a_folder_holding_a_run_is_refused_and_left_as_it_was(reference, tmp_path, capsys):
    out = _copy_run(reference[0], tmp_path / "run")
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    argv = [
        "train",
        CONFIG,
        "--out",
        str(out),
        *CHECKPOINTED,
        "train.total_frames=400",
        "--no-progress",
    ]
    assert main(argv) == 2
    _one_line_error(capsys, "already holds a run", f"--resume {out / 'final.pt'}", "--overwrite")
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before


@pytest.mark.slow
def test_overwrite_removes_the_old_run_first(reference, tmp_path, capsys):
    out = _copy_run(reference[0], tmp_path / "run")
    (out / ".final.pt.0123456789ab.tmp").write_bytes(b"left by a SIGKILL")
    (out / "notes.txt").write_text("not a run file: kept")
    argv = ["train", CONFIG, "--out", str(out), *CHECKPOINTED, "train.total_frames=400",
            "train.checkpoint_every=0", "--overwrite", "--no-progress"]  # fmt: skip
    assert main(argv) == 0
    assert sorted(p.name for p in out.iterdir()) == [
        "config.yaml",
        "final.pt",
        "heads.pt",
        "logs",
        "notes.txt",
    ]
    assert load_checkpoint(out / "final.pt")["counters"]["frames"] == 400
    assert all(int(row.split(",")[0]) <= 400 for rows in read_logs(out).values() for row in rows)


def test_a_second_run_on_a_locked_folder_is_refused(tmp_path, capsys):
    held = ResultsFolder(tmp_path / "run", staged=False)
    held.acquire()
    try:
        argv = ["train", CONFIG, "--out", str(tmp_path / "run"), *CHECKPOINTED, "--no-progress"]
        assert main(argv) == 2
        _one_line_error(capsys, "in use by another taskvar run", f"pid {os.getpid()}")
        assert sorted(p.name for p in (tmp_path / "run").iterdir()) == [LOCK_NAME]
    finally:
        held.commit()
    assert not (tmp_path / "run" / LOCK_NAME).exists()


@pytest.mark.parametrize(
    "case, needle",
    [
        ("out_is_a_file", "is a file, not a folder"),
        ("bad_resume", "truncated or corrupt"),
        ("yaml", "is not valid YAML: line 2, column 8: mapping values are not allowed"),
        ("cuda", "device='cuda' needs CUDA"),
    ],
)
def test_bad_input_is_one_line_and_leaves_nothing(tmp_path, capsys, case, needle):
    if case == "cuda" and torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    out = tmp_path / "run"
    argv = ["train", CONFIG, "--out", str(out), *CHECKPOINTED, "--no-progress"]
    if case == "out_is_a_file":
        out.write_text("a file")
    elif case == "bad_resume":
        (tmp_path / "random.pt").write_bytes(os.urandom(4096))
        argv = ["train", "--resume", str(tmp_path / "random.pt"), "--out", str(out)]
    elif case == "yaml":
        (tmp_path / "bad.yaml").write_text("seed: 1\n  train: 2\n")
        argv[1] = str(tmp_path / "bad.yaml")
    else:
        argv.append("device=cuda")
    inputs = sorted(p.name for p in tmp_path.iterdir())  # what the test made, nothing else
    assert main(argv) == 2
    _one_line_error(capsys, needle)
    assert sorted(p.name for p in tmp_path.iterdir()) == inputs


@pytest.mark.slow
def test_experiment_checkpoint_mismatches_are_refused_before_any_work(reference, tmp_path, capsys):
    wargus = load_config(ROOT / "configs" / "wargus.yaml")
    save_checkpoint(tmp_path / "wargus.pt", make_bundle(wargus, models={}))
    out = tmp_path / "out"
    for argv, needle in (
        (["--checkpoint", str(tmp_path / "wargus.pt")], "is a 'wargus' bundle"),
        (["--checkpoint", str(reference[0] / "final.pt"), "env.windy.layout=middle_exits"],
         "cannot apply with --checkpoint"),
        (["--checkpoint", str(reference[0] / "final.pt"), str(ROOT / "configs" / "windy.yaml")],
         "cannot apply with --checkpoint"),
    ):  # fmt: skip
        assert main(["experiment", "windy-fig2", "--out", str(out), *argv, "--no-progress"]) == 2
        _one_line_error(capsys, needle)
        assert not out.exists()


@pytest.mark.slow
def test_eval_test_names(reference, tmp_path, capsys):
    ckpt = str(reference[0] / "final.pt")
    argv = ["eval", "--checkpoint", ckpt, "--episodes", "5", "--no-progress", "--out"]
    assert main([*argv, str(tmp_path / "a"), "--test", "test"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["taskvar eval: --test test is deprecated: it is the training distribution; "
                   "use --test train"]  # fmt: skip
    assert main([*argv, str(tmp_path / "b"), "--test", "train"]) == 0
    assert capsys.readouterr().err == ""
    a, b = ((tmp_path / d / "metrics.json").read_text() for d in "ab")
    assert a == b and '"test": "train"' in a


# ---- a quiet main job ----------------------------------------------------------------------------


@pytest.mark.slow
def test_train_output_has_no_third_party_noise(reference):
    r = reference[1]
    text = r.stdout + r.stderr
    assert "[torchrl][INFO]" not in text and "Warning" not in text, text[-2000:]


def test_progress_bar_ends_at_its_total(tmp_path, capsys):
    cfg = load_config(CONFIG, [*CHECKPOINTED, "train.total_frames=450", "train.checkpoint_every=0"])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = train(cfg, tmp_path, progress=True)
    assert result["frames"] == 500  # TorchRL collects whole batches
    err = capsys.readouterr().err
    assert "450/450" in err and "500/450" not in err
    assert not [w for w in caught if "divisible" in str(w.message)]  # TorchRL's note, silenced


# ---- Gymnasium envs: the same clear messages in both families ------------------------------------


def _gym_envs():

    import taskvar_torch  # noqa: F401  (registers the ids)

    return {
        "windy": gym.make("taskvar/WindyGrid-v0").unwrapped,
        "wargus": gym.make("taskvar/Wargus-v0").unwrapped,
    }


@pytest.mark.parametrize("family", ["windy", "wargus"])
def test_gym_step_before_reset_raises(family):
    with pytest.raises(RuntimeError, match=r"call reset\(\) before step\(\)"):
        _gym_envs()[family].step(0)


@pytest.mark.parametrize("family", ["windy", "wargus"])
@pytest.mark.parametrize("action", [float("nan"), None, [1], "1", 2.5, True, 99, -1])
def test_gym_malformed_action_is_one_message(family, action):
    env = _gym_envs()[family]
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"^action must be in \[0, \d\] \(an integer\), got "):
        env.step(action)


@pytest.mark.parametrize("family", ["windy", "wargus"])
@pytest.mark.parametrize(
    "options, needle",
    [
        ([1], "reset options must be a dict"),
        ({"wind": 1}, "unknown reset option"),
        ({"start": (1,)}, "start must be a (row, col) pair of integers"),
        ({"start": "ab"}, "start must be a (row, col) pair of integers"),
        ({"start": (1.5, 0)}, "start must be a (row, col) pair of integers"),
        ({"start": (99, 0)}, "start must be a (row, col) inside"),
        ({"instance": [1]}, 'options["instance"] must be a dict'),
        ({"instance": {"bogus": 1}}, "unknown instance field"),
    ],
)
def test_gym_failed_reset_changes_nothing(family, options, needle):
    env = _gym_envs()[family]
    obs, info = env.reset(seed=3)
    env.step(1)
    state = {k: v for k, v in vars(env).items() if not k.startswith("np_random")}
    snapshot = repr(sorted((k, repr(v)) for k, v in state.items()))
    with pytest.raises(ValueError) as e:
        env.reset(seed=7, options=options)
    assert needle in str(e.value)
    assert repr(sorted((k, repr(v)) for k, v in vars(env).items()
                       if not k.startswith("np_random"))) == snapshot  # fmt: skip
    # and the next episode is the one an unrefused run would have had
    fresh = _gym_envs()[family]
    fresh.reset(seed=3)
    fresh.step(1)
    a, _ = env.reset()
    b, _ = fresh.reset()
    assert (a == b).all()


@pytest.mark.parametrize(
    "family, instance, needle",
    [
        ("windy", {"p": float("nan")}, "instance p must be in [0, 1]"),
        ("windy", {"p": None}, "instance p must be in [0, 1]"),
        ("windy", {"direction": "up"}, "direction must be one of"),
        ("wargus", {"seed": None}, "instance seed must be an integer"),
        ("wargus", {"seed": -3}, "instance seed must be an integer"),
    ],
)
def test_gym_malformed_instance_is_a_clear_message(family, instance, needle):
    env = _gym_envs()[family]
    env.reset(seed=0)
    with pytest.raises(ValueError) as e:
        env.reset(options={"instance": instance})
    assert needle in str(e.value)
