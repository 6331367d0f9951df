"""Trainer and ``taskvar train``: exact resume in a new process, divergence handling,
refusals, the final bundle, the CLI."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

import taskvar_torch.training.learning as T
from taskvar_torch import keys
from taskvar_torch.checkpoint import CheckpointError, load_checkpoint
from taskvar_torch.cli import main
from taskvar_torch.config import load_config
from taskvar_torch.factory import load_heads
from taskvar_torch.training import train
from taskvar_torch.training.learning import TrainingDiverged

torch.set_num_threads(1)
CONFIG = "configs/windy.yaml"
TINY = [
    "env.num_envs=4",
    "train.frames_per_batch=100",
    "train.total_frames=2000",
    "train.checkpoint_every=1000",
    "train.log_every=500",
    "train.init_random_frames=300",
    "train.batch_size=32",
    "train.updates_per_batch=2",
    "train.buffer_size=5000",
]


def taskvar(*args: str) -> subprocess.CompletedProcess:
    """``taskvar ...`` in a new single-threaded process."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "RL_WARNINGS": "False"}
    cmd = [sys.executable, "-m", "taskvar_torch.cli", *args, "--threads", "1", "--no-progress"]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)


def assert_same(a, b, path="bundle"):
    """Bit-for-bit equality of two plain-data bundles."""
    if isinstance(a, dict):
        assert set(a) == set(b), f"{path}: keys differ: {set(a) ^ set(b)}"
        for k in a:
            assert_same(a[k], b[k], f"{path}[{k!r}]")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), f"{path}: lengths differ"
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{path}[{i}]")
    elif isinstance(a, torch.Tensor):
        assert torch.equal(a, b), f"{path} differs"
    else:
        assert a == b, f"{path}: {a!r} != {b!r}"


def read_scalars(folder: Path) -> dict[str, list[tuple[int, str]]]:
    out = {}
    for f in sorted((folder / "logs" / "scalars").glob("loss_*.csv")):
        rows = [line.split(",") for line in f.read_text().splitlines()]
        out[f.stem] = [(int(step), value) for step, value in rows]
    return out


@pytest.mark.slow
def test_2k_frames_equal_1k_then_resume_in_a_new_process_for_1k(tmp_path):
    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    r = taskvar("train", CONFIG, "--out", str(straight), *TINY)
    assert r.returncode == 0, r.stderr[-2000:]
    half = straight / "checkpoint_000001000.pt"
    assert half.is_file() and (straight / "final.pt").is_file()
    r = taskvar("train", "--resume", str(half), "--out", str(resumed))
    assert r.returncode == 0, r.stderr[-2000:]

    a = load_checkpoint(straight / "final.pt")
    b = load_checkpoint(resumed / "final.pt")
    assert a["counters"]["frames"] == 2000 and a["counters"]["updates"] > 20
    for k in ("versions",):
        a.pop(k), b.pop(k)
    # heads, targets, optimiser, replay, env state, RNG states, step counters: bit for bit
    assert_same(a, b)
    # the resumed folder's logs: the rows up to the checkpoint, then the same numbers to the last
    # digit as the uninterrupted run's
    la, lb = read_scalars(straight), read_scalars(resumed)
    heads = {"loss_averaging", "loss_options", "loss_switching", "loss_max_value"}
    assert set(la) == heads
    for name, rows in la.items():
        assert any(row[0] > 1000 for row in rows) and rows == lb[name], name


@pytest.mark.slow
def test_resume_refuses_a_changed_config(tmp_path):
    train(load_config(CONFIG, [*TINY, "train.total_frames=1000"]), tmp_path / "a", progress=False)
    ckpt = tmp_path / "a" / "final.pt"
    with pytest.raises(CheckpointError, match="train.lr"):
        train(None, tmp_path / "b", resume=ckpt, overrides=["train.lr=0.5"], progress=False)
    # runtime keys may change: continue the same run for longer
    result = train(
        None, tmp_path / "c", resume=ckpt, overrides=["train.total_frames=1200"], progress=False
    )
    assert result["frames"] == 1200


@pytest.mark.slow
def test_nan_loss_stops_training_and_keeps_the_last_good_checkpoint(tmp_path):
    # lr = 1e30: the first Adam steps overflow the weights, the losses become inf/NaN
    cfg = load_config(CONFIG, [*TINY, "train.init_random_frames=1100", "train.lr=1e9"])
    with pytest.raises(TrainingDiverged, match="non-finite loss"):
        train(cfg, tmp_path, progress=False)
    assert not (tmp_path / "final.pt").exists()
    good = load_checkpoint(tmp_path / "checkpoint_000001000.pt", expected_config=cfg)
    assert good["counters"]["frames"] == 1000
    for t in good["models"]["heads"].values():
        assert torch.isfinite(t).all()
    heads, _ = load_heads(tmp_path / "checkpoint_000001000.pt")  # still a usable bundle


def test_cli_reports_divergence_in_one_line(tmp_path, capsys):
    status = main(["train", CONFIG, "--out", str(tmp_path), *TINY, "train.lr=1e9", "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2
    assert err[-1].startswith("taskvar train: error: non-finite loss")


def test_cli_rejects_a_misspelt_key_in_one_line(tmp_path, capsys):
    status = main(["train", CONFIG, "--out", str(tmp_path), "train.lrr=0.1", "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1 and "train.lrr" in err[0]


@pytest.mark.parametrize("command", ["train", "eval", "experiment", "plot"])
def test_cli_help(command, capsys):
    with pytest.raises(SystemExit) as e:
        main([command, "--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    assert f"usage: taskvar {command}" in text
    if command == "train":
        assert "--resume" in text and "train.total_frames" in text


def test_train_help_shows_the_user_keys_and_help_all_every_key(capsys):
    """``taskvar train --help`` lists at most 35 keys (config/help.py ``USER_KEYS``); ``--help-all``
    lists every key of the schema, grouped by section, with each registered family's own."""
    from taskvar_torch.config import Config, config_help
    from taskvar_torch.config.help import USER_KEYS, count_keys

    with pytest.raises(SystemExit):
        main(["train", "--help"])
    short = capsys.readouterr().out
    listed = [k for k in USER_KEYS if f"  {k} (" in short]
    assert listed == list(USER_KEYS) and count_keys(short) == len(USER_KEYS) <= 35
    with pytest.raises(SystemExit) as e:
        main(["train", "--help-all"])
    assert e.value.code == 0
    full = capsys.readouterr().out
    assert count_keys(full) == count_keys(config_help()) > len(USER_KEYS)
    for key in ("train.target_tau", "env.wargus.sight (int, default 8)", "env.taxi.horizon"):
        assert f"  {key}" in full, key
    assert "heads:" in full and "env.taxi:" in full and Config().train.lr == 0.001


@pytest.mark.slow
def test_final_bundle_without_replay_evaluates_but_does_not_resume(tmp_path):
    """keep_replay=False (the scale experiment's cells): final.pt without the replay buffer, the
    same heads, smaller; resuming from it is refused."""
    cfg = load_config(CONFIG, [*TINY, "train.total_frames=600", "train.checkpoint_every=0"])
    train(cfg, tmp_path / "with", progress=False)
    train(cfg, tmp_path / "without", progress=False, keep_replay=False)
    with_replay = load_checkpoint(tmp_path / "with" / "final.pt")
    bundle = load_checkpoint(tmp_path / "without" / "final.pt")
    assert "replay" not in bundle and with_replay["replay"]["size"] > 0
    for name, t in with_replay["models"]["heads"].items():
        assert torch.equal(t, bundle["models"]["heads"][name]), name
    heads, _ = load_heads(tmp_path / "without" / "final.pt")
    assert (tmp_path / "without" / "final.pt").stat().st_size < (
        tmp_path / "with" / "final.pt"
    ).stat().st_size
    with pytest.raises(CheckpointError, match="holds no replay buffer"):
        train(None, tmp_path / "again", resume=tmp_path / "without" / "final.pt", progress=False)
    assert not (tmp_path / "again").exists()


def test_final_bundle_reloads_the_trained_heads(tmp_path):
    cfg = load_config(CONFIG, [*TINY, "train.total_frames=600", "train.checkpoint_every=0"])
    train(cfg, tmp_path, progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "config.yaml",
        "final.pt",
        "heads.pt",
        "logs",
    ]
    bundle = load_checkpoint(tmp_path / "final.pt")
    assert bundle["replay"]["size"] > 0 and bundle["counters"]["updates"] > 0
    # a partly filled replay is saved as its rows, not its whole preallocated storage
    n, obs = bundle["replay"]["size"], bundle["replay"]["data"][keys.OBSERVATION]
    assert n < cfg.train.buffer_size and obs.shape[0] == n
    assert obs.untyped_storage().nbytes() == obs.numel() * obs.element_size()
    heads, cfg2 = load_heads(tmp_path / "final.pt")
    assert cfg2 == cfg
    for name, t in heads.state_dict().items():
        assert torch.equal(t, bundle["models"]["heads"][name]), name
    td = heads(TensorDict({keys.OBSERVATION: torch.eye(25)}, [25]))
    assert td[keys.OPTION_ACTION_VALUE].shape == (25, 2, 4) and td[keys.MAX_VALUE].shape == (25, 2)
    assert (td[keys.MAX_VALUE] >= td[keys.OPTION_VALUE]).all()


@pytest.mark.slow
def test_lr_schedule_decays_linearly_to_lr_end(tmp_path):
    """``train.lr_end``: lr until ``lr_decay_start_frames``, then linear to ``lr_end`` at
    ``total_frames``; the saved optimiser ends at lr_end; bad values are refused in one line."""
    over = ["train.lr=0.001", "train.lr_end=0.0001", "train.lr_decay_start_frames=1000"]
    t = load_config(CONFIG, over).train
    assert T.lr_at(0, t) == T.lr_at(1000, t) == pytest.approx(1e-3)
    mid = 1000 + (t.total_frames - 1000) // 2
    assert T.lr_at(mid, t) == pytest.approx(5.5e-4, rel=1e-3)
    assert T.lr_at(t.total_frames, t) == T.lr_at(10 * t.total_frames, t) == pytest.approx(1e-4)
    plain = load_config(CONFIG).train
    assert T.lr_at(10**9, plain) == plain.lr  # null lr_end: constant
    cfg = load_config(
        CONFIG,
        [*TINY, "train.total_frames=1000", "train.checkpoint_every=0", "train.lr_end=0.0002"],
    )
    train(cfg, tmp_path, progress=False)
    groups = load_checkpoint(tmp_path / "final.pt")["optimizers"]["adam"]["param_groups"]
    assert all(g["lr"] == pytest.approx(2e-4) for g in groups)  # the last phase: 1000 frames
    for bad in ("train.lr_end=0.5", "train.lr_end=0", "train.lr_decay_start_frames=-1"):
        with pytest.raises(ValueError, match=bad.split("=")[0]):
            load_config(CONFIG, [bad])


@pytest.mark.slow
def test_eval_ema_tau_bundles_hold_the_polyak_average(tmp_path):
    """``train.eval_ema_tau``: final.pt keeps the online heads (for resuming) and the average
    (``eval_heads``), which ``load_heads``, heads.pt and the heads_every snapshots hold; resuming
    continues the average bit for bit; bad values and wargus-fig4 are refused in one line (the
    average's update rule: tests/test_heads.py)."""
    cfg = load_config(
        CONFIG, [*TINY, "train.eval_ema_tau=0.25", "train.heads_every=1000", "seed=3"]
    )
    straight = train(cfg, tmp_path / "straight", progress=False)
    bundle = load_checkpoint(straight["final"])
    assert set(bundle["models"]) == {"heads", "targets", "eval_heads"}
    online_sd, ema_sd = bundle["models"]["heads"], bundle["models"]["eval_heads"]
    assert any(not torch.equal(online_sd[k], ema_sd[k]) for k in online_sd)
    for path in (straight["final"], tmp_path / "straight" / "heads.pt"):
        heads, _ = load_heads(path)
        for k, v in heads.state_dict().items():
            assert torch.equal(v, ema_sd[k]), (path, k)
    snapshot, _ = load_heads(tmp_path / "straight" / "heads" / "heads_000001000.pt")
    half = load_checkpoint(tmp_path / "straight" / "checkpoint_000001000.pt")
    assert all(
        torch.equal(v, half["models"]["eval_heads"][k]) for k, v in snapshot.state_dict().items()
    )
    resumed = train(
        None,
        tmp_path / "resumed",
        resume=tmp_path / "straight" / "checkpoint_000001000.pt",
        progress=False,
    )
    assert_same(load_checkpoint(resumed["final"])["models"], bundle["models"])

    for bad in ("train.eval_ema_tau=0", "train.eval_ema_tau=1.5"):
        with pytest.raises(ValueError, match=r"train.eval_ema_tau must be in \(0, 1\] or null"):
            load_config(CONFIG, [bad])
    from taskvar_torch.families.wargus.fig4 import default_config_path, wargus_fig4

    wcfg = load_config(default_config_path(), ["train.eval_ema_tau=0.01"], quick=True)
    with pytest.raises(ValueError, match="wargus-fig4 tests the live heads"):
        wargus_fig4(wcfg, tmp_path / "fig4", progress=False)
    assert not (tmp_path / "fig4").exists()


@pytest.mark.slow
def test_a_checkpoint_written_before_train_logger_existed_resumes(tmp_path):
    """A checkpoint whose config has no ``train.logger`` (written before the key existed) and
    still has ``train.switching`` (removed since, config/migration.py ``REMOVED_KEYS``) resumes, with
    one deprecation line; the logger may change on resume (it is a runtime key)."""
    from taskvar_torch.checkpoint import save_checkpoint

    train(load_config(CONFIG, [*TINY, "train.total_frames=1000"]), tmp_path / "a", progress=False)
    bundle = load_checkpoint(tmp_path / "a" / "final.pt")
    del bundle["config"]["train"]["logger"]
    bundle["config"]["train"]["switching"] = "intra"
    old = save_checkpoint(
        tmp_path / "old.pt", {k: v for k, v in bundle.items() if not k.startswith("format")}
    )
    with pytest.warns(FutureWarning, match="train.switching is dropped"):
        result = train(
            None, tmp_path / "b", resume=old, overrides=["train.total_frames=1200"], progress=False
        )
    assert result["frames"] == 1200
