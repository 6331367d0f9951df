"""Learnt heads against the exact oracle on the 5x5 windy families (the oracle bounds in
docs/design.md, Training the heads).

One training run per layout and session (module fixtures): ``configs/windy.yaml`` (max-value
estimator ``instance``, Definition 1) with a smaller budget (40k frames, about 4.5k updates of
every head), then checks against :class:`~taskvar_torch.oracle.WindyOracle` on the same layout and
training distribution: all four on ``default``, the max-value / interruption check (>= 95%
agreement of the interruption condition on visited (cell, option) pairs) on all three.
"""

from __future__ import annotations

import pytest
import torch

from taskvar_torch.config import load_config
from taskvar_torch.heads.validate import compare_with_oracle
from taskvar_torch.oracle import WindyOracle
from taskvar_torch.train import load_heads, train

torch.set_num_threads(1)
pytestmark = [pytest.mark.slow, pytest.mark.timeout(1200)]  # a 4-min fixture under load

BUDGET = ["train.total_frames=40000", "train.eps_decay_frames=20000", "train.checkpoint_every=0"]


def train_and_compare(layout: str, out) -> dict:
    cfg = load_config("configs/windy.yaml", [*BUDGET, f"env.layout={layout}"])
    result = train(cfg, out, progress=False)
    heads, cfg = load_heads(result["final"])
    oracle = WindyOracle(
        layout, gamma=cfg.train.gamma, horizon=cfg.env.horizon, train_instances="train"
    )
    return compare_with_oracle(heads, oracle)


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    return train_and_compare("default", tmp_path_factory.mktemp("windy_heads"))


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
