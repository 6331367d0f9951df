"""Taxi's per-step regret (``TaxiOracle.step_regret``; docs/evaluation.md): on Gymnasium's own
dynamics (``envs/taxi.step``), an episode's steps sum to its regret against the per-instance
optimum, exactly where the instance is deterministic and in expectation under rain and a fickle
passenger; ``taskvar eval`` writes ``regret_by_step`` for a Taxi test point with few instances and
skips it (unless ``--exact``) for a continuous range."""

from __future__ import annotations

import pytest
import torch

from taskvar_torch.families.taxi import dynamics as taxi
from taskvar_torch.families.taxi.dynamics import TaxiInstances
from taskvar_torch.families.taxi.oracle import TaxiOracle
from taskvar_torch.oracle.mdp import greedy

torch.set_num_threads(1)


def _rollouts(oracle, policy, q, f, n, seed):
    """``n`` Taxi-v4 episodes of a stationary ``policy (500,)`` in instance ``(q, f)`` from the
    start states in turn (the passenger armed with probability f, as Taxi-v4's reset): cells,
    actions, alive ``(n, H)``, returns and start states."""
    g = torch.Generator().manual_seed(seed)
    m, H = oracle.model, oracle.horizon
    s = oracle.start_cells[torch.arange(n) % oracle.start_cells.numel()].clone()
    start = s.clone()
    armed = torch.rand(n, generator=g, dtype=torch.float64) < f
    cells = torch.zeros(n, H, dtype=torch.int64)
    actions = torch.zeros(n, H, dtype=torch.int64)
    alive = torch.zeros(n, H, dtype=torch.bool)
    live = torch.ones(n, dtype=torch.bool)
    ret = torch.zeros(n, dtype=torch.float64)
    qs = torch.full((n,), q, dtype=torch.float64)
    for t in range(H):
        a = policy[s]
        cells[:, t], actions[:, t], alive[:, t] = s, a, live
        outcome = taxi.rain_outcome(torch.rand(n, generator=g, dtype=torch.float64), qs)
        redraw = torch.randint(0, 3, (n,), generator=g)
        s2, r, term, armed = taxi.step(m, s, a, outcome, armed, redraw)
        ret += torch.where(live, r.double(), 0.0)
        live = live & ~term
        s = torch.where(alive[:, t], s2, s)
    return cells, actions, alive, ret, start


def test_steps_sum_to_the_regret_exactly_on_a_deterministic_instance():
    oracle = TaxiOracle()
    g = torch.Generator().manual_seed(0)
    q, f = 1.0, 0.0  # dry and never fickle: every episode is deterministic
    best = oracle.optimal_return(q, f)  # (500,)
    for trial in range(3):  # the optimal greedy policy (delivers), then random ones (mostly not)
        if trial == 0:
            policy = greedy(oracle.optimal_q(q, f))[: oracle.S]
        else:
            policy = torch.randint(0, oracle.A, (oracle.S,), generator=g)
        cells, actions, alive, ret, start = _rollouts(oracle, policy, q, f, 60, trial)
        n = len(ret)
        gap = oracle.step_regret(torch.full((n,), q), torch.full((n,), f), cells, actions, alive)
        assert float(gap.min()) >= -1e-9
        assert torch.allclose(gap.sum(1), best[start] - ret, atol=1e-7, rtol=0), trial
        assert not bool(gap[~alive].any())
        if trial == 0:
            assert float(gap.abs().max()) < 1e-9 and not bool(alive[:, -1].any())
    with pytest.raises(ValueError, match="one instance per episode"):
        oracle.step_regret(torch.ones(2), torch.zeros(2), cells[:3], actions[:3])


@pytest.mark.parametrize("q, f", [(1.0, 1.0), (0.8, 0.5)])
def test_steps_sum_to_the_regret_in_expectation_under_rain_and_a_fickle_passenger(q, f):
    """The pending fickle status read off the trace makes the values the optimum's belief MDP:
    the mean summed step regret equals the policy's exact regret within a few standard errors."""
    oracle = TaxiOracle()
    g = torch.Generator().manual_seed(3)
    policy = greedy(oracle.optimal_q(1.0, 0.0))[: oracle.S]  # dry-optimal, a fifth of it random
    off = torch.rand(oracle.S, generator=g) < 0.2
    policy = torch.where(off, torch.randint(0, oracle.A, (oracle.S,), generator=g), policy)
    n = 1500
    cells, actions, alive, ret, start = _rollouts(oracle, policy, q, f, n, 11)
    gap = oracle.step_regret(torch.full((n,), q), torch.full((n,), f), cells, actions, alive)
    point = TaxiInstances(points=((q, f),))
    best = oracle.optimal_return(q, f)[start]
    mine = oracle.expected_return(policy, point, None)[start]  # the policy's exact return
    exact = best - mine
    per_episode = gap.sum(1)
    se = float(per_episode.std()) / n**0.5
    assert float(exact.mean()) > 0.05  # the policy does lose to the optimum here
    assert abs(float(per_episode.mean()) - float(exact.mean())) < 4 * se + 1e-9
    assert float(gap.min()) >= -1e-9
    # the rollouts are the oracle's model: sampled returns agree with the exact ones
    assert abs(float(ret.mean()) - float(mine.mean())) < 4 * float(ret.std()) / n**0.5 + 1e-9


def test_step_regret_is_gated_by_the_number_of_distinct_instances():
    from taskvar_torch.experiments.regret_steps import step_regret_affordable

    oracle = TaxiOracle()
    few = {"rainy_probability": [0.8] * 100, "fickle_probability": [0.3] * 100}
    many = {
        "rainy_probability": torch.linspace(0.7, 0.9, 100).numpy(),
        "fickle_probability": [0.3] * 100,
    }
    assert step_regret_affordable(oracle, few) and not step_regret_affordable(oracle, many)
    assert oracle.step_solves([0.8, 0.8, 0.7], [0.3, 0.2, 0.3]) == 3


def test_eval_writes_taxi_regret_by_step_where_few_instances_are_played(tmp_path):
    """``taskvar eval`` on a Taxi bundle: one test point of one instance (``gymnasium``: q 0.8,
    f 0.3) gets ``regret_by_step``, whose total is each method's regret within the CIs; the
    training distribution (a continuous rain range) does not, unless ``exact=True``."""
    from taskvar_torch.config import load_config
    from taskvar_torch.experiments.bundle_eval import eval_bundle
    from taskvar_torch.factory import build_heads, make_env, make_subtasks, write_heads

    cfg = load_config("configs/taxi.yaml", ["env.num_envs=4"])
    env = make_env(cfg, 1)
    write_heads(tmp_path / "heads.pt", build_heads(cfg, env, make_subtasks(cfg, env)), cfg)
    m = eval_bundle(tmp_path / "heads.pt", "averaging", "gymnasium", episodes=60, progress=False)
    data = m["regret_by_step"]["methods"]["averaging"]
    r = m["points"][0]["methods"]["averaging"]
    band = 2 * (r["regret_ci95"] + sum(data["ci95"])) + 1e-9  # the steps are correlated
    assert abs(data["total"] - r["regret_mean"]) < band and min(data["mean"]) >= -1e-9
    train_point = eval_bundle(
        tmp_path / "heads.pt", "averaging", "train", episodes=60, progress=False
    )
    assert "regret_by_step" not in train_point
