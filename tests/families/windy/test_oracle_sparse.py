"""The sparse oracle (successor tables, iterative solves) against the dense one on small layouts,
and the head report on tables that are the optimum by construction."""

from __future__ import annotations

import pytest
import torch

from taskvar_torch.families.windy import WindyOracle
from taskvar_torch.families.windy.dynamics import make_layout
from taskvar_torch.families.windy.sparse_oracle import (
    SparseKernel,
    SparseWindyOracle,
    expect_planes,
    outcome_planes,
)

LAYOUTS = ["default", "middle_exits", make_layout(9, 9, num_exits=3, wind_cells_per_exit=2)]


@pytest.mark.parametrize("layout", LAYOUTS, ids=["default", "middle_exits", "generated9"])
def test_sparse_matches_dense(layout):
    dense, sparse = WindyOracle(layout), SparseWindyOracle(layout, quad_nodes=50)
    assert torch.allclose(dense.averaging_q(), sparse.averaging_q(), atol=1e-8)
    assert torch.allclose(dense.option_q(), sparse.option_q(), atol=1e-8)
    assert torch.allclose(dense.switching_q(), sparse.switching_q(), atol=1e-8)
    assert torch.allclose(dense.max_value(), sparse.max_value(), atol=1e-8)
    assert torch.equal(dense.averaging_policy(), sparse.averaging_policy())
    assert torch.equal(dense.option_policies(), sparse.option_policies())
    assert torch.equal(dense.mu_bar().argmax(-1), sparse.mu_bar())
    pol = dense.averaging_policy()
    assert float(dense.expected_return(pol)) == pytest.approx(
        float(sparse.expected_return(pol)), abs=1e-9
    )
    p, d = torch.tensor([0.0, 0.3, 1.0], dtype=torch.float64), torch.tensor([0, 1, 1])
    assert torch.allclose(
        dense.episode_return(pol, p, d), sparse.episode_return(pol, p, d), atol=1e-9
    )
    assert torch.allclose(
        dense.evaluate(pol, p, d),
        sparse.evaluate_kernel(sparse.kernel(p, d), sparse._env_reward(sparse.kernel(p, d)), pol),
        atol=1e-8,
    )


@pytest.mark.parametrize("K", [1, 2])
def test_expect_planes_is_the_gather_and_sum_bit_for_bit(K):
    # the chains' expectation, one gather per outcome, against gathering every outcome and
    # summing over them (the formula it replaces): the same bits for one or two outcomes
    g = torch.Generator().manual_seed(K)
    B, S, A = 3, 50, 4
    V = torch.randn(B, S, dtype=torch.float64, generator=g)
    succ = torch.randint(0, S, (B, S, A, K), generator=g)
    prob = torch.rand(B, S, A, K, dtype=torch.float64, generator=g)
    prob = prob / prob.sum(-1, keepdim=True)
    summed = (V.gather(1, succ.reshape(B, -1)).view(B, S, A, K) * prob).sum(-1)
    assert torch.equal(expect_planes(V, *outcome_planes(succ, prob)).view(B, S, A), summed)
    assert torch.equal(SparseKernel(succ, prob).expect(V), summed)
    # the mean MDP's five outcomes keep the summed path
    o = SparseWindyOracle("default")
    k = o.mean_kernel
    V1 = torch.randn(1, o.S, dtype=torch.float64, generator=g)
    ref = (V1.gather(1, k.succ.reshape(1, -1)).view(k.succ.shape) * k.prob).sum(-1)
    assert torch.equal(k.expect(V1), ref)


def test_sparse_objectives_and_errors():
    o = SparseWindyOracle("default")
    # the optimum's own policies reach the optimum of each objective
    assert torch.allclose(o.option_objective(o.option_policies()), o.option_objective(), atol=1e-7)
    assert torch.allclose(
        o.averaging_objective(o.averaging_policy()), o.averaging_objective(), atol=1e-7
    )
    # a policy that walks into the west border never arrives: -1 / (1 - gamma) in the mean MDP
    west = torch.full((o.S,), 3)
    v = o.averaging_objective(west)[o.start_cells]
    assert torch.allclose(v, torch.full_like(v, -100.0), atol=1e-6)
    with pytest.raises(ValueError, match="gamma"):
        SparseWindyOracle("default", gamma=1.0)
    with pytest.raises(ValueError, match="p must be in"):
        o.kernel(1.5, "north")
    with pytest.raises(ValueError, match="starts"):
        o.expected_return(o.averaging_policy(), starts="corner")


@pytest.mark.parametrize(
    "layout,instances", [("default", "train"), ("whole_column_windy", "south")]
)
def test_controller_returns_match_dense_chains(layout, instances):
    """The sparse (cell, running option) chain of Algorithm 1 gives the dense oracle's exact
    options and interruption returns and firing counts (whole_column_windy, south: it fires)."""
    dense = WindyOracle(layout, train_instances=instances)
    sparse = SparseWindyOracle(layout, quad_nodes=50, train_instances=instances)
    pols, q_mu = sparse.option_policies(), sparse.switching_q()
    for name, q_hat in (("options", None), ("interruption", sparse.max_value())):
        got = sparse.controller_returns(pols, q_mu, q_hat)
        want = float(dense.controller_expected_return(name))
        assert float(got["expected_return"]) == pytest.approx(want, abs=1e-9)
        p, d, w = dense.quadrature()
        fires = float(w @ dense.controller_fire_count(name, p, d, start="uniform"))
        assert float(got["interruptions_per_episode"]) == pytest.approx(fires, abs=1e-9)
    if layout == "whole_column_windy":  # interruption adds something here (paper Figure 2)
        assert float(got["interruptions_per_episode"]) > 0.05
        assert got["expected_return"] > sparse.controller_returns(pols, q_mu)["expected_return"]
    with pytest.raises(ValueError, match="starts"):
        sparse.controller_returns(pols, q_mu, starts="corner")


def test_head_report_of_exact_tables():
    """A bundle of the oracle's own tables scores 0 gap on every head, full agreement of mu_bar
    and of the interruption condition, and the oracle's controller returns."""
    from taskvar_torch import keys
    from taskvar_torch.families.windy.head_report import head_report
    from taskvar_torch.oracle.tables import table_heads

    o = SparseWindyOracle("whole_column_windy", train_instances="south")
    heads = table_heads(
        o.option_names,
        averaging=o.averaging_q(),
        options=o.option_q().permute(1, 0, 2),
        switching=o.switching_q(),
        max_value=o.max_value(),
        in_key=keys.OBSERVATION,
    )
    r = head_report(heads, o, "onehot")
    assert r["averaging"]["rel_gap"] == pytest.approx(0.0, abs=1e-9)
    assert all(abs(x["rel_gap"]) < 1e-9 for x in r["options"].values())
    assert r["mu_bar"]["start_agreement"] == 1.0
    assert r["interruption_condition"]["agreement"] == 1.0
    ctrl = r["interruption_controller"]
    assert ctrl["expected_return"] == pytest.approx(ctrl["oracle_interruption_return"], abs=1e-9)
    assert ctrl["interruptions_per_episode"] > 0
    assert ctrl["oracle_interruption_return"] > ctrl["oracle_options_return"]
    oc = r["options_controller"]
    assert oc["expected_return"] == pytest.approx(oc["oracle_options_return"], abs=1e-9)
    # a max-value head that always says "lower than now" interrupts at every step
    low = table_heads(
        o.option_names,
        averaging=o.averaging_q(),
        options=o.option_q().permute(1, 0, 2),
        switching=o.switching_q(),
        max_value=o.max_value() - 100.0,
        in_key=keys.OBSERVATION,
    )
    r_low = head_report(low, o, "onehot")
    assert r_low["interruption_controller"]["interruptions_per_episode"] > 1.0
    assert r_low["interruption_condition"]["agreement"] < 1.0
