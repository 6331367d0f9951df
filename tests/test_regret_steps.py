"""Regret against the step within the episode (issue 31, item 3; docs/evaluation.md): the windy
oracle's ``step_regret`` (``V*_{H-t}(s_t) - Q*_{H-t}(s_t, a_t)``), whose sum over an episode's
steps is its regret against the per-instance optimum (performance-difference identity), and
``taskvar eval``'s ``regret_by_step`` and ``regret_by_step.png``."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from taskvar_torch.experiments.bundle_eval import eval_bundle, format_table
from taskvar_torch.families.windy.oracle import WindyOracle
from taskvar_torch.oracle.mdp import greedy

torch.set_num_threads(1)


def _rollouts(oracle, policy, p, d, n, seed):
    """``n`` episodes of a stationary deterministic ``policy (S,)`` in instance ``(p, d)`` from the
    start cells in turn, by the oracle's own tables: cells, actions, alive ``(n, H)``, returns."""
    g = torch.Generator().manual_seed(seed)
    m, H = oracle.model, oracle.horizon
    s = oracle.start_cells[torch.arange(n) % oracle.start_cells.numel()].clone()
    start = s.clone()
    cells = torch.zeros(n, H, dtype=torch.int64)
    actions = torch.zeros(n, H, dtype=torch.int64)
    alive = torch.zeros(n, H, dtype=torch.bool)
    live = torch.ones(n, dtype=torch.bool)
    ret = torch.zeros(n, dtype=torch.float64)
    for t in range(H):
        a = policy[s]
        cells[:, t], actions[:, t], alive[:, t] = s, a, live
        moved = m.move[s, a]
        gust = torch.rand(n, generator=g, dtype=torch.float64) < p
        s = torch.where(gust, m.push[moved, d], moved)
        ret -= live.double()
        live = live & ~oracle.is_goal[s]
    return cells, actions, alive, ret, start


@pytest.mark.parametrize("layout", ["default", "whole_column_windy"])
def test_step_regret_sums_to_the_regret_against_the_optimum(layout):
    oracle = WindyOracle(layout)
    g = torch.Generator().manual_seed(1)
    for p, d in ((1.0, 1), (0.0, 0), (1.0, 0)):  # deterministic: exactly, episode by episode
        for trial in range(4):  # random stationary policies (most trapped to the horizon), and
            policy = torch.randint(0, 4, (oracle.S,), generator=g)  # one that reaches an exit
            if trial == 0:
                policy = greedy(oracle.optimal_q(p, d))
            cells, actions, alive, ret, start = _rollouts(oracle, policy, p, d, 24, trial)
            n = len(ret)
            gap = oracle.step_regret(
                torch.full((n,), p), torch.full((n,), d), cells, actions, alive
            )
            best = oracle.optimal_return(p, d)[start]
            assert float(gap.min()) >= -1e-12
            assert torch.allclose(gap.sum(1), best - ret, atol=1e-9, rtol=0), (p, d, trial)
            assert trial > 0 or not bool(alive[:, -1].any())
    # a gusty instance: the episodes' mean sum is the exact regret of the policy (a few SEs)
    p, d, n = 0.4, 1, 6000
    policy = torch.randint(0, 4, (oracle.S,), generator=g)
    cells, actions, alive, ret, start = _rollouts(oracle, policy, p, d, n, 7)
    gap = oracle.step_regret(torch.full((n,), p), torch.full((n,), d), cells, actions, alive)
    exact = oracle.optimal_return(p, d)[start] - oracle.episode_return(policy, p, d)[start]
    per_episode = gap.sum(1)
    se = float(per_episode.std()) / n**0.5
    assert abs(float(per_episode.mean()) - float(exact.mean())) < 4 * se + 1e-9
    assert not bool(gap[~alive].any())  # nothing after an episode ended


def test_eval_regret_by_step_sums_to_the_regret_column(windy_tiny_bundle, tmp_path):
    """Under whole-strength winds (p = 1: every instance deterministic) each method's per-step
    regret summed over the steps is its ``regret_mean`` to float tolerance; the plot and the
    existing keys are written beside it."""
    m = eval_bundle(
        windy_tiny_bundle,
        "all",
        "train",
        shifts=["env.instances.p=1.0"],
        episodes=40,
        out_dir=tmp_path,
        progress=False,
    )
    data = m["regret_by_step"]
    per = m["points"][0]["methods"]
    assert set(data["methods"]) == set(per) == set(m["methods"])
    for name, d in data["methods"].items():
        assert len(d["mean"]) == len(d["ci95"]) == len(d["live"]) == data["steps"]
        assert abs(sum(d["mean"]) - per[name]["regret_mean"]) < 1e-9, name
        assert abs(d["total"] - per[name]["regret_mean"]) < 1e-9, name
        assert d["live"][0] == 1.0 and min(d["mean"]) >= -1e-12
        live = [v for v in d["live_mean"] if v is not None]
        assert len(live) == sum(f > 0 for f in d["live"])
    assert (tmp_path / "regret_by_step.png").exists() and "regret_by_step.png" in m["figures"]
    assert "regret_by_instance" in m and "regret.png" in m["figures"]  # unchanged beside it
    table = format_table(m)
    assert "optimum" in table and f"{m['points'][0]['optimum_mean_return']:9.3f}" in table


def test_eval_regret_by_step_on_the_training_winds(windy_tiny_bundle, tmp_path):
    """Gusty instances: the steps' sum is the regret in expectation (within the CIs); a shift curve
    (several test points) writes no per-step regret."""
    m = eval_bundle(windy_tiny_bundle, "averaging,options", "train", episodes=400, progress=False)
    for name, d in m["regret_by_step"]["methods"].items():
        r = m["points"][0]["methods"][name]
        band = 2 * (r["regret_ci95"] + np.sum(d["ci95"])) + 1e-9  # the steps are correlated
        assert abs(d["total"] - r["regret_mean"]) < band, name
    curve = eval_bundle(
        windy_tiny_bundle,
        "averaging",
        "train",
        shifts=["env.instances.p=0.2,0.8"],
        episodes=20,
        progress=False,
    )
    assert "regret_by_step" not in curve
