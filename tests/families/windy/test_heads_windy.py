"""Learnt heads against the exact oracle on the 5x5 windy families (the oracle bounds in
docs/design.md, Training the heads), and the baselines beside them (docs/memory.md).

One training run per layout and session (module fixtures): ``configs/windy.yaml`` (max-value
estimator ``instance``, Definition 1) with a smaller budget (40k frames, about 4.5k updates of
every head), then checks against :class:`~taskvar_torch.oracle.WindyOracle` on the same layout and
training distribution: all four on ``default``, the max-value / interruption check (>= 95%
agreement of the interruption condition on visited (cell, option) pairs) on all three. On
``default`` the recurrent and informed baselines train beside the heads at the same budget, each
on its own stream (docs/memory.md): the informed one must reach the exact per-instance optimum
within a stated bound, the recurrent one be no worse than the averaging head's exact value by more
than a stated bound.
"""

from __future__ import annotations

import pytest
import torch
from torchrl.envs import TransformedEnv

from taskvar_torch.config import load_config
from taskvar_torch.experiments.evaluation import mean_ci95, run_episodes
from taskvar_torch.factory import load_heads, make_env
from taskvar_torch.families.windy import WindyOracle
from taskvar_torch.heads.recurrent import load_baseline
from taskvar_torch.heads.validate import compare_with_oracle
from taskvar_torch.oracle.episodes import optimal_episode_returns
from taskvar_torch.training import train
from taskvar_torch.training.baselines import train_baseline

torch.set_num_threads(1)
pytestmark = [pytest.mark.slow, pytest.mark.timeout(1200)]  # a 4-min fixture under load

BUDGET = ["train.total_frames=40000", "train.eps_decay_frames=20000", "train.checkpoint_every=0"]


INFORMED_BOUND = 0.15
"""Stated bound on the informed baseline's mean regret against the exact per-instance optimum on
the training distribution (measured: 0.009 +- 0.025 on 4000 episodes, seed 0, at this budget, on
its own stream; 0.033 +- 0.028 for the learner's passive head it replaced)."""
RECURRENT_BOUND = 0.5
"""Stated bound on how far the recurrent head's mean return may fall below the averaging head's
exact value on the training distribution at the same budget (measured at this budget, seed 0:
-4.540 +- 0.052 against averaging's exact -5.880; the bound only asks for no worse)."""
EPISODES = 4000


def train_and_compare(layout: str, out) -> dict:
    cfg = load_config("configs/windy.yaml", [*BUDGET, f"env.windy.layout={layout}"])
    result = train(cfg, out, progress=False)
    heads, cfg = load_heads(result["final"])
    oracle = WindyOracle(
        layout, gamma=cfg.train.gamma, horizon=cfg.env.windy.horizon, train_instances="train"
    )
    return compare_with_oracle(heads, oracle)


@pytest.fixture(scope="module")
def default_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("windy_heads")
    report = train_and_compare("default", out)
    cfg = load_config(out / "config.yaml")
    train_baseline(cfg, "recurrent", out)  # the same config: the heads' budget and settings
    train_baseline(cfg, "informed", out)
    return report, out, cfg


@pytest.fixture(scope="module")
def report(default_run):
    return default_run[0]


def _baseline_returns(folder, method: str, cfg):
    """``(returns, optimum)`` of ``folder/<method>.pt`` on fresh training instances (env seed
    ``seed + 1``), with the exact per-instance optimum of each episode."""
    ctrl, _ = load_baseline(folder / f"{method}.pt")
    env = TransformedEnv(make_env(cfg, EPISODES, seed=cfg.seed + 1), ctrl.primer())
    out = run_episodes(env, ctrl, max_steps=cfg.env.windy.horizon)
    inst = {k: out["instance", k].numpy() for k in ("p", "direction")}
    oracle = WindyOracle(cfg.env.windy.layout, horizon=cfg.env.windy.horizon)
    optimum = optimal_episode_returns(oracle, inst, out["start"].numpy())
    return out["return"].double(), torch.as_tensor(optimum)


@pytest.fixture(scope="module", params=["middle_exits", "whole_column_windy"])
def other_layout_report(request, tmp_path_factory):
    return train_and_compare(request.param, tmp_path_factory.mktemp(request.param))


def test_averaging_head_within_half_a_step_of_the_mean_mdp_optimum(report):
    # exact expected return over training instances and start cells (undiscounted steps)
    assert report["averaging_return"] >= report["oracle_averaging_return"] - 0.5, report


def test_each_option_head_within_half_a_step_of_the_oracle_option(report):
    for got, best in zip(report["option_returns"], report["oracle_option_returns"]):
        assert got >= best - 0.5, report


def test_mu_bar_agrees_with_the_oracle_where_option_values_differ(report):
    assert report["mu_bar_cells"] >= 8  # all cells but the tied middle row
    assert report["mu_bar_agreement"] == 1.0, report


def test_max_value_head_near_oracle_and_interruption_condition_agrees(report):
    assert report["max_value_error"] <= 1.0, report
    assert report["interruption_agreement"] >= 0.95, report


def test_interruption_condition_agrees_on_the_other_layouts(other_layout_report):
    # Q_hat within 1.5 of the exact max over instances for the learnt options and mu_bar (the
    # learnt options may take other routes than the mean-MDP ones: oracle.replay_policy)
    r = other_layout_report
    assert r["max_value_error_learnt_options"] <= 1.5, r
    assert r["interruption_agreement"] >= 0.95, r


def test_informed_head_reaches_the_exact_per_instance_optimum(default_run):
    _, folder, cfg = default_run
    returns, optimum = _baseline_returns(folder, "informed", cfg)
    regret, ci = mean_ci95(optimum - returns)
    assert regret < INFORMED_BOUND, (regret, ci)
    assert regret > -3 * ci - 1e-9  # nothing beats the exact optimum beyond sampling noise


def test_recurrent_head_no_worse_than_averaging_beyond_the_bound(default_run):
    report, folder, cfg = default_run
    returns, _ = _baseline_returns(folder, "recurrent", cfg)
    mean, ci = mean_ci95(returns)
    assert mean >= report["averaging_return"] - RECURRENT_BOUND, (mean, ci, report)
