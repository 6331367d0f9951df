"""Training options no other test trains (issue 32), each through the real trainer
(:func:`taskvar_torch.training.train`) on a tiny config, checked for the run finishing with finite
heads and for the option taking effect:

* ``train.n_step > 1`` (shipped in configs/windy_xxl.yaml): the replay holds the n-step windows and
  every learner batch carries them;
* ``train.target_update=hard``: the targets equal the online heads exactly every
  ``target_period`` updates, and only then;
* ``train.double_q=false``: the learner's targets differ from double-Q ones;
* ``train.mu_bar=softmax``: the bundle's mu_bar is a softmax at ``mu_bar_temperature``;
* ``train.robustness_threshold=fixed`` (Wargus): the hierarchy uses ``robustness_tau``,
  uncalibrated;
* ``train.option_coverage``: option picks leave mu_bar's greedy choice;
* ``train.max_grad_norm``: every head's gradient norm is clipped to it (``null``: unclipped).

The learner and the run are observed by wrapping what :mod:`taskvar_torch.training.run_setup` builds
(``make_learner``, ``TrainingRun.store``), never by re-implementing the loop.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.objectives import HardUpdate

from taskvar_torch import factory
from taskvar_torch.checkpoint import load_checkpoint
from taskvar_torch.config import load_config
from taskvar_torch.factory import load_heads, make_env, make_method_controller, make_subtasks
from taskvar_torch.heads.learner import MultiHeadLearner
from taskvar_torch.heads.networks import head_network
from taskvar_torch.heads.robustness import RobustnessCalibration
from taskvar_torch.heads.switching import mu_bar_probs
from taskvar_torch.training import run_setup, train
from taskvar_torch.training.run_state import TrainingRun

torch.set_num_threads(1)

ROOT = Path(__file__).resolve().parents[1]
WINDY = ROOT / "configs" / "windy.yaml"
WARGUS = ROOT / "configs" / "wargus.yaml"
TINY = [  # tests/test_families.py's budget, with 2 updates per batch: 8 updates, ~2 s
    "env.num_envs=4",
    "train.frames_per_batch=100",
    "train.total_frames=400",
    "train.checkpoint_every=0",
    "train.log_every=400",
    "train.init_random_frames=100",
    "train.batch_size=16",
    "train.updates_per_batch=2",
    "train.buffer_size=1000",
    "train.compile=false",  # configs/wargus.yaml compiles; a test run does not pay it off
]


def train_tiny(
    out: Path,
    *overrides: str,
    config: Path = WINDY,
    on_learner: Callable[[MultiHeadLearner], None] | None = None,
) -> tuple[dict, MultiHeadLearner]:
    """Train ``config`` with :data:`TINY` and ``overrides`` into ``out``; ``on_learner`` sees the
    learner the trainer builds, before training. Returns ``train``'s result and that learner;
    checks the run finished with finite heads."""
    built = []

    def make_learner(*args, **kwargs):
        learner = original(*args, **kwargs)
        built.append(learner)
        if on_learner is not None:
            on_learner(learner)
        return learner

    original = run_setup.make_learner
    run_setup.make_learner = make_learner
    try:
        result = train(load_config(config, [*TINY, *overrides]), out, progress=False)
    finally:
        run_setup.make_learner = original
    assert result["frames"] == 400 and result["updates"] > 0
    bundle = load_checkpoint(result["final"])
    for name, t in bundle["models"]["heads"].items():
        assert torch.isfinite(t).all(), name
    return result, built[0]


def wrap_losses(learner: MultiHeadLearner, seen: list) -> None:
    """Record every relabelled batch the learner's losses read."""
    losses = learner.losses

    def recording(batch):
        seen.append(batch)
        return losses(batch)

    learner.losses = recording


# --------------------------------------------------------------------------------------------
# n-step targets


def test_n_step_3_fills_the_replay_with_windows_and_the_learner_reads_them(tmp_path):
    """``train.n_step=3``: every replayed transition carries its window (1 to 3 steps, some 3,
    discount gamma^k), and every batch the learner reads has it; ``n_step=1`` has none."""
    seen: list = []
    result, learner = train_tiny(
        tmp_path / "n3", "train.n_step=3", on_learner=lambda lr: wrap_losses(lr, seen)
    )
    replay = load_checkpoint(result["final"])["replay"]["data"]
    window = replay["nstep"]
    steps = window["steps"]
    assert int(steps.min()) >= 1 and int(steps.max()) == 3
    gamma = learner.loss.settings.gamma
    torch.testing.assert_close(window["discount"], gamma ** steps.to(torch.float32))
    assert seen and all(b.nstep is not None for b in seen)
    assert any(bool(b.nstep.averaging_rows.any()) for b in seen)
    assert any(bool(b.nstep.option_rows.any()) for b in seen)
    assert any(bool((b.nstep.discount < gamma - 1e-6).any()) for b in seen)  # windows past 1 step

    seen.clear()
    result, _ = train_tiny(tmp_path / "n1", on_learner=lambda lr: wrap_losses(lr, seen))
    assert "nstep" not in load_checkpoint(result["final"])["replay"]["data"]
    assert seen and all(b.nstep is None for b in seen)


# --------------------------------------------------------------------------------------------
# hard target updates


def test_hard_target_update_copies_the_heads_exactly_every_target_period(tmp_path):
    """``train.target_update=hard``, ``target_period=3``: after updates 3 and 6 the targets equal
    the online heads bit for bit; after every other update they differ."""
    record: list[tuple[int, bool]] = []

    def watch(learner: MultiHeadLearner) -> None:
        assert isinstance(learner.target_updater, HardUpdate)
        update = learner.update

        def recording(sample):
            out = update(sample)
            online = learner.heads.heads.state_dict()
            target = learner.loss.target_heads.state_dict()
            same = all(torch.equal(online[k], target[k]) for k in online)
            record.append((learner.num_updates, same))
            return out

        learner.update = recording

    train_tiny(tmp_path, "train.target_update=hard", "train.target_period=3", on_learner=watch)
    assert [n for n, _ in record] == list(range(1, 9))
    assert [n for n, same in record if same] == [3, 6]


# --------------------------------------------------------------------------------------------
# double Q


def test_double_q_false_reaches_the_learner_and_changes_its_targets(tmp_path):
    """``train.double_q=false``: the learner's settings say so, and on the trained heads the
    same sampled batch gives different losses with double-Q targets (the online argmax) than
    with the plain max of the target network."""
    result, learner = train_tiny(
        tmp_path, "train.double_q=false", "train.lr=0.05", "train.target_tau=0.001"
    )
    loss = learner.loss
    assert loss.settings.double_q is False
    torch.manual_seed(0)
    replay = load_checkpoint(result["final"])["replay"]["data"]
    rows = TensorDict(replay, batch_size=[len(replay["action"])])[:256]
    batch = loss.relabel(rows)
    with torch.no_grad():
        plain = loss.losses(batch)
        loss.settings = dataclasses.replace(loss.settings, double_q=True)
        double = loss.losses(batch)
    assert plain["loss_averaging"] != double["loss_averaging"]
    assert plain["loss_options"] != double["loss_options"]


# --------------------------------------------------------------------------------------------
# softmax mu_bar


def test_softmax_mu_bar_is_saved_in_the_bundle_and_used_by_the_learner(tmp_path):
    """``train.mu_bar=softmax``, ``mu_bar_temperature=0.5``: the learner's switching targets
    use the temperature, and the saved bundle's mu_bar is a softmax at it (a greedy run's is
    one-hot)."""
    result, learner = train_tiny(
        tmp_path / "soft", "train.mu_bar=softmax", "train.mu_bar_temperature=0.5"
    )
    assert learner.loss.settings.mu_bar_temperature == 0.5
    heads, cfg = load_heads(result["final"])
    assert heads.softmax_temperature == 0.5 and cfg.train.mu_bar == "softmax"
    q = torch.tensor([[1.0, 0.0], [0.0, 0.3]])
    torch.testing.assert_close(heads.mu_bar(q), torch.softmax(q / 0.5, dim=-1))

    result, _ = train_tiny(tmp_path / "greedy")
    greedy, _ = load_heads(result["final"])
    assert greedy.softmax_temperature is None
    torch.testing.assert_close(greedy.mu_bar(q), torch.tensor([[1.0, 0.0], [0.0, 1.0]]))


# --------------------------------------------------------------------------------------------
# fixed robustness threshold (Wargus)


def test_fixed_robustness_threshold_uses_robustness_tau_uncalibrated(tmp_path, monkeypatch):
    """A tiny Wargus run with ``train.robustness_threshold=fixed``, ``robustness_tau=3.5``: the
    hierarchy controller of its bundle thresholds every capability at 3.5 and never calibrates;
    the same bundle with ``calibrated`` gets per-capability thresholds."""
    result, _ = train_tiny(
        tmp_path,
        "train.robustness_threshold=fixed",
        "train.robustness_tau=3.5",
        "env.wargus.size=12",
        "env.wargus.horizon=60",
        "heads.hidden=[32]",
        config=WARGUS,
    )
    heads, cfg = load_heads(result["final"])
    assert heads.has("robustness") and cfg.train.robustness_tau == 3.5
    subtasks = make_subtasks(cfg, make_env(cfg, num_envs=1))
    with monkeypatch.context() as m:
        m.setattr(factory, "calibrate", lambda *a, **k: pytest.fail("fixed calibrated"))
        ctrl = make_method_controller(cfg, "hierarchy", heads, subtasks)
    assert ctrl.calibration is None
    assert ctrl.thresholds(torch.device("cpu")) == (3.5, None)

    calibrated = dataclasses.replace(
        cfg, train=dataclasses.replace(cfg.train, robustness_threshold="calibrated")
    )
    ctrl = make_method_controller(calibrated, "hierarchy", heads, subtasks)
    assert isinstance(ctrl.calibration, RobustnessCalibration)
    tau, scale = ctrl.thresholds(torch.device("cpu"))
    assert tau.shape == (len(heads.option_names), 1) and scale is not None


# --------------------------------------------------------------------------------------------
# option coverage


def _picks_off_mu_bar(tmp_path: Path, coverage: float) -> tuple[int, int]:
    """Train with options-only behaviour, epsilon 0 and ``option_coverage``; over every episode
    start, count the option picks and those that are not mu_bar's greedy pick (the heads that
    acted are the learner's, untouched between collection and ``store``)."""
    counts = [0, 0]
    store = TrainingRun.store

    def counting(run, batch):
        start = batch.get("is_init").squeeze(-1) & (batch.get("behaviour") >= 0)  # (N, T)
        td = batch[start]
        if td.numel():
            with torch.no_grad():
                q_mu = head_network(run.learner.heads.heads["switching"])(td.get("observation"))
                init = run.learner.loss.subtasks.initiation(td)
                greedy = mu_bar_probs(q_mu, init).argmax(-1)
            counts[0] += td.numel()
            counts[1] += int((td.get("behaviour") != greedy).sum())
        return store(run, batch)

    TrainingRun.store = counting
    try:
        train_tiny(
            tmp_path,
            f"train.option_coverage={coverage}",
            "train.option_behaviour_prob=1.0",
            "train.eps_start=0.0",
            "train.eps_end=0.0",
            "train.init_random_frames=0",  # epsilon is 1 during the random frames
            "env.num_envs=10",
            "env.windy.horizon=10",
        )
    finally:
        TrainingRun.store = store
    return counts[0], counts[1]


def test_option_coverage_makes_the_behaviour_run_options_mu_bar_does_not_pick(tmp_path):
    """With epsilon 0, ``option_coverage=0`` picks mu_bar's greedy option at every episode start;
    ``option_coverage=1`` picks uniformly (2 exits: about half are not mu_bar's)."""
    picks, off = _picks_off_mu_bar(tmp_path / "c0", 0.0)
    assert picks >= 30 and off == 0
    picks, off = _picks_off_mu_bar(tmp_path / "c1", 1.0)
    assert picks >= 30 and 0.2 * picks <= off <= 0.8 * picks


# --------------------------------------------------------------------------------------------
# gradient clipping


def _head_grad_norms(learner: MultiHeadLearner) -> torch.Tensor:
    """Each head's gradient norm (one per stacked member, or per head's parameter group)."""
    if learner._stacked:
        grads = [p.grad for p in learner._groups[0] if p.grad is not None]
        return torch.stack([g.pow(2).flatten(1).sum(1) for g in grads]).sum(0).sqrt()
    return torch.stack(
        [
            torch.linalg.vector_norm(torch.stack([p.grad.norm() for p in g if p.grad is not None]))
            for g in learner._groups
        ]
    )


def _grad_norms_at_step(tmp_path: Path, max_grad_norm: str) -> list[torch.Tensor]:
    """Every head's gradient norm as the optimiser steps, for each update of a tiny run."""
    norms: list[torch.Tensor] = []

    def watch(learner: MultiHeadLearner) -> None:
        step = learner.optimizer.step

        def recording(*args, **kwargs):
            norms.append(_head_grad_norms(learner).detach().clone())
            return step(*args, **kwargs)

        learner.optimizer.step = recording

    train_tiny(tmp_path, f"train.max_grad_norm={max_grad_norm}", on_learner=watch)
    return norms


def test_max_grad_norm_clips_every_heads_gradient_and_null_does_not(tmp_path):
    """``train.max_grad_norm=0.001``: at every optimiser step each head's gradient norm is at
    most 0.001; with ``null`` the same run's first step has heads far above it."""
    clipped = _grad_norms_at_step(tmp_path / "clip", "0.001")
    assert len(clipped) == 8
    for norms in clipped:
        assert float(norms.max()) <= 0.001 * (1 + 1e-4)
    free = _grad_norms_at_step(tmp_path / "free", "null")
    assert len(free) == 8 and float(free[0].max()) > 0.01
    assert math.isclose(float(clipped[0].max()), 0.001, rel_tol=1e-3)  # it did clip


# --------------------------------------------------------------------------------------------
# behaviour without options


def test_option_behaviour_prob_0_labels_every_transition_the_averaging_policys(tmp_path):
    """With ``option_behaviour_prob=0`` every episode is the averaging policy's: every replayed
    transition carries behaviour mode -1 (after resets too), so the per-option return log and
    per-option sampling see no option episodes."""
    result, _ = train_tiny(tmp_path, "train.option_behaviour_prob=0")
    modes = load_checkpoint(result["final"])["replay"]["data"]["behaviour"]
    assert modes.numel() > 100 and bool((modes == -1).all()), modes.unique()
    assert not (tmp_path / "logs" / "scalars" / "episode_return_options.csv").exists()
