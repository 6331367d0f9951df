"""The sparse oracle (successor tables, iterative solves) against the dense one on small layouts,
and the head report on tables that are the optimum by construction."""

from __future__ import annotations

import pytest
import torch

from taskvar_torch.envs.windy import make_layout
from taskvar_torch.oracle import WindyOracle
from taskvar_torch.oracle.sparse import SparseWindyOracle

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
