"""Exact oracle: mean MDP, value iteration, option/switching/max values, returns, heads."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from taskvar_torch import keys
from taskvar_torch.families.windy import WindyGridEnv, WindyInstances, WindyOracle
from taskvar_torch.families.windy import dynamics as windy
from taskvar_torch.oracle import TableLookup, gauss_legendre, greedy, solve_mdp

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def oracle() -> WindyOracle:
    return WindyOracle("default")


def first_episode_returns(env: WindyGridEnv, policy_table: torch.Tensor) -> torch.Tensor:
    """Undiscounted return of every sub-environment's first episode under a tabular policy."""
    policy = TensorDictModule(
        TableLookup(policy_table), in_keys=[keys.CELL], out_keys=[keys.ACTION]
    )
    td = env.reset()
    alive = torch.ones(env.num_envs, dtype=torch.bool)
    ret = torch.zeros(env.num_envs, dtype=torch.float64)
    for _ in range(env.horizon):
        out, td = env.step_and_maybe_reset(policy(td))
        ret += out["next", "reward"].squeeze(-1) * alive
        alive &= ~out["next", "done"].squeeze(-1)
    assert not bool(alive.any()), "every first episode must end within the horizon"
    return ret


# ---- mean MDP -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "instances",
    ["train", "south", WindyInstances(points=((0.2, "north"), (0.9, "south"), (1.0, "east")))],
)
def test_mean_mdp_rows_sum_to_one(instances):
    P, R = WindyOracle("default", train_instances=instances).mean_mdp()
    assert P.shape == (25, 4, 25) and R.shape == (25, 4)
    assert torch.allclose(P.sum(-1), torch.ones(25, 4, dtype=torch.float64), atol=1e-12)
    assert bool((P >= 0).all())


def test_mean_mdp_equals_average_of_instance_models_over_the_distribution(oracle):
    # independent of the linearity argument: integrate T(p, dir) numerically over p ~ U[0,1], dir
    x, w = gauss_legendre(8, 0.0, 1.0)
    Ps = [oracle.transition(x, d)[0] for d in ("north", "south")]  # (8, S, A, S) each
    avg = sum(torch.einsum("k,ksat->sat", w, P) for P in Ps) / 2
    P_bar, _ = oracle.mean_mdp()
    assert torch.allclose(P_bar, avg, atol=1e-12)
    # and the mean MDP of a finite set of points is the mean of their models
    pts = ((0.3, "north"), (0.8, "south"))
    o2 = WindyOracle("default", train_instances=WindyInstances(points=pts))
    P2 = (oracle.transition(0.3, "north")[0] + oracle.transition(0.8, "south")[0]) / 2
    assert torch.allclose(o2.mean_mdp()[0], P2[0], atol=1e-12)


# ---- value iteration ------------------------------------------------------------------------


def test_value_iteration_terminates_and_unreachable_exit_is_worth_minus_100(oracle):
    # p = 1, wind south: the north exit's windy cell always pushes the agent away -> unreachable
    q = oracle.optimal_q(1.0, "south", option="exit_north")  # (S, A) subtask-optimal values
    starts = oracle.start_cells
    assert torch.allclose(
        q[starts].max(-1).values, torch.full((5,), -100.0, dtype=torch.float64), atol=1e-6
    )
    # the averaging exit_north option never arrives either: -1/(1-gamma)
    q_m = oracle.instance_option_q(1.0, "south")  # (S, O)
    assert torch.allclose(q_m[starts, 0], torch.full((5,), -100.0, dtype=torch.float64), atol=1e-6)
    # the exit_south option still arrives
    assert bool((q_m[starts, 1] > -10).all())
    # a slower contraction still terminates and gives -1/(1-gamma)
    slow = WindyOracle("default", gamma=0.999)
    q_slow = slow.instance_option_q(1.0, "south")
    assert math.isclose(float(q_slow[0, 0]), -1000.0, abs_tol=1e-4)
    # (there, taking the wrong exit and its -100 penalty is subtask-optimal: about -105 > -1000)
    assert float(slow.optimal_q(1.0, "south", option=0)[0].max()) > -110


def test_solve_mdp_rejects_gamma_one():
    P = torch.ones(1, 1, 1, dtype=torch.float64)
    with pytest.raises(ValueError, match="gamma"):
        solve_mdp(P, torch.zeros(1, 1, dtype=torch.float64), 1.0)


def test_averaging_q_satisfies_the_bellman_optimality_equation(oracle):
    P, R = oracle.mean_mdp()
    Q = oracle.averaging_q()
    target = R + oracle.gamma * torch.einsum("sat,t->sa", P, Q.max(-1).values)
    assert torch.allclose(Q, target, atol=1e-8)
    # and no deterministic policy does better from any state (checked on random policies)
    g = torch.Generator().manual_seed(0)
    V_star = Q.max(-1).values
    for _ in range(20):
        pi = torch.randint(0, 4, (25,), generator=g)
        V = oracle._evaluate(P[None], R[None], pi)[0]
        assert bool((V <= V_star + 1e-8).all())


def test_option_q_satisfies_its_subtask_bellman_equation(oracle):
    P, _ = oracle.mean_mdp()
    Qo = oracle.option_q()  # (O, S, A)
    r = oracle.subtask_reward_table  # (O, S, S')
    cont = 1.0 - oracle.termination_table.T  # (O, S')
    for o in range(oracle.O):
        target = torch.einsum("sat,st->sa", P, r[o]) + oracle.gamma * torch.einsum(
            "sat,t->sa", P, cont[o] * Qo[o].max(-1).values
        )
        live = ~oracle.is_goal
        assert torch.allclose(Qo[o][live], target[live], atol=1e-8)


def test_option_policies_reach_their_own_exit_without_wind(oracle):
    model, pol = oracle.model, oracle.option_policies()  # (O, S)
    for o, exit_cells in enumerate(oracle.layout.exit_cells):
        for start in oracle.start_cells.tolist():
            cell, last = start, None
            for _ in range(20):
                if bool(model.is_goal[cell]):
                    break
                last = cell
                cell = int(model.move[cell, pol[o, cell]])
            assert bool(model.is_goal[cell]) and last in exit_cells, (o, start)
    # from the middle start cell both exits are 5 steps away
    assert float(oracle.episode_return(pol[0], 0.0, "north", start=(2, 0))) == -5.0


# ---- switching and max-values ----------------------------------------------------------------


def test_switching_q_is_the_mean_mdp_value_of_each_option_policy(oracle):
    P, R = oracle.mean_mdp()
    Q_mu = oracle.switching_q()  # (S, O)
    for o, pi in enumerate(oracle.option_policies()):
        V = oracle._evaluate(P[None], R[None], pi)[0]
        assert torch.allclose(Q_mu[:, o], V, atol=1e-8)
    mu = oracle.mu_bar()
    assert torch.allclose(mu.sum(-1), torch.ones(25, dtype=torch.float64))
    assert torch.equal(mu.argmax(-1), greedy(Q_mu))


@pytest.mark.parametrize(
    "instances",
    [None, WindyInstances(p_low=0.2, p_high=0.7), ([0.1, 0.9, 0.5], ["north", "south", "south"])],
)
def test_max_value_dominates_every_instance_value_in_the_set(oracle, instances):
    q_hat = oracle.max_value(instances)  # (S, O)
    p, d = oracle.instance_set(instances)
    q_m = oracle.instance_option_q(p, d)  # (M, S, O)
    assert bool((q_hat.unsqueeze(0) >= q_m - 1e-9).all())
    # ... and is attained: it is the max, not just an upper bound
    assert torch.allclose(q_m.max(0).values, q_hat, atol=1e-9)


def test_default_q_hat_set_is_p_grid_times_training_directions(oracle):
    p, d = oracle.instance_set()
    assert p.numel() == 2 * 21
    assert set(d.tolist()) == {windy.direction_index("north"), windy.direction_index("south")}
    assert float(p.min()) == 0.0 and float(p.max()) == 1.0


# ---- returns -----------------------------------------------------------------------------


def test_quadrature_over_p_is_exact_for_returns(oracle):
    pi = oracle.averaging_policy()
    finer = WindyOracle("default", quad_nodes=oracle.quad_nodes + 17)
    assert torch.allclose(
        oracle.expected_return(pi, starts=None), finer.expected_return(pi, starts=None), atol=1e-10
    )


def test_expected_return_is_not_the_mean_mdp_return(oracle):
    pi = oracle.averaging_policy()
    held = oracle.expected_return(pi, starts=(0, 0))
    redrawn = oracle.mean_mdp_return(pi, start=(0, 0))
    assert float(redrawn) - float(held) > 1.0  # a held high-p south wind traps the agent


def test_episode_return_of_a_policy_that_never_arrives_is_minus_horizon(oracle):
    west = torch.full((25,), windy.ACTIONS.index("west"))
    assert float(oracle.episode_return(west, 0.5, "north", start=(2, 0))) == -100.0


@pytest.mark.slow
def test_mean_mdp_optimal_value_from_each_start_cell_matches_monte_carlo(oracle):
    """Acceptance: exact expected return of pi_bar over p~U[0,1], dir in {N,S}, per start
    cell, against 20000 independent WindyGridEnv episodes per cell, within 4 standard errors."""
    pi = oracle.averaging_policy()
    exact = oracle.expected_return(pi, "train", starts=None)  # (S,)
    n = 20000
    for k, cell in enumerate(oracle.start_cells.tolist()):
        env = WindyGridEnv(num_envs=n, instances="train", start=divmod(cell, 5), seed=100 + k)
        ret = first_episode_returns(env, pi)
        se = ret.std() / math.sqrt(n)
        assert abs(float(ret.mean() - exact[cell])) < 4 * float(se) + 1e-9, (
            cell,
            float(ret.mean()),
            float(exact[cell]),
        )


def test_episode_return_matches_monte_carlo_in_a_fixed_instance(oracle):
    pi = oracle.averaging_policy()
    exact = oracle.episode_return(pi, 0.6, "south", start="uniform")
    n = 20000
    env = WindyGridEnv(num_envs=n, instances=WindyInstances.fixed(0.6, "south"), seed=7)
    ret = first_episode_returns(env, pi)
    assert abs(float(ret.mean() - exact)) < 4 * float(ret.std()) / math.sqrt(n)


# ---- heads ---------------------------------------------------------------------------------


def test_heads_gather_rows_of_the_tables(oracle):
    heads = oracle.heads()
    cells = torch.tensor([0, 10, 22, 3])
    td = heads(TensorDict({keys.CELL: cells}, batch_size=[4]))
    assert torch.equal(td[keys.ACTION_VALUE], oracle.averaging_q()[cells])
    assert torch.equal(td[keys.OPTION_ACTION_VALUE], oracle.option_q()[:, cells].transpose(0, 1))
    assert torch.equal(td[keys.OPTION_VALUE], oracle.switching_q()[cells])
    assert torch.equal(td[keys.MAX_VALUE], oracle.max_value()[cells])
    assert td[keys.OPTION_ACTION_VALUE].shape == (4, 2, 4)
    # one-hot observations work the same way
    obs_heads = oracle.heads(in_key=keys.OBSERVATION)
    td2 = obs_heads(oracle.observation_td()[cells])
    assert torch.equal(td2[keys.MAX_VALUE], td[keys.MAX_VALUE])


def test_q_hat_below_v_mu_bar_somewhere_on_whole_column_windy():
    """The layout where offline interruption (Definition 1) can fire."""
    o = WindyOracle("whole_column_windy")
    fires = o.max_value() < o.v_mu_bar().unsqueeze(-1)  # (S, O)
    assert bool(fires.any())


def test_invalid_arguments_raise_value_error(oracle):
    with pytest.raises(ValueError, match="p must be in"):
        oracle.instance_option_q(1.5, "north")
    with pytest.raises(ValueError, match="direction"):
        oracle.evaluate(oracle.averaging_policy(), 0.5, "up")
    with pytest.raises(ValueError, match="gamma"):
        WindyOracle("default", gamma=1.0)


# ---- the reference the learnt heads converge to (docs/oracle.md) ---------------------------


@pytest.fixture(scope="module")
def wcw() -> WindyOracle:
    return WindyOracle("whole_column_windy")


def test_visit_probability_matches_monte_carlo_in_a_fixed_instance(wcw):
    torch.manual_seed(0)
    behaviour = torch.softmax(torch.randn(wcw.S, wcw.A) * 2.0, -1)  # (S, A) stochastic
    want = wcw.visit_probability(behaviour, 0.7, "north")[0]  # (S, A)
    N = 4000
    env = WindyGridEnv(
        layout="whole_column_windy",
        num_envs=N,
        instances=WindyInstances(points=((0.7, "north"),)),
        seed=3,
    )
    td = env.reset()
    alive = torch.ones(N, dtype=torch.bool)
    seen = torch.zeros(N, wcw.S, wcw.A, dtype=torch.bool)
    for _ in range(env.horizon):
        cell = td[keys.CELL]
        action = torch.multinomial(behaviour[cell].float(), 1).squeeze(-1)
        seen[torch.arange(N)[alive], cell[alive], action[alive]] = True
        td.set(keys.ACTION, action)
        out, td = env.step_and_maybe_reset(td)
        alive &= ~out["next", "done"].squeeze(-1)
    got = seen.double().mean(0)
    assert (got - want).abs().max() < 0.03, (got - want).abs().max()


@pytest.mark.slow
def test_learnt_fixed_points_beat_the_mean_mdp_options_on_whole_column_windy(wcw):
    """Fixed-instance episodes, not the mean MDP: the exit options a first-visit Q-learner reaches
    (and the best Markov options for E_m[V^{m, pi}]) avoid the windy column, 1.5 steps better."""
    for option in wcw.option_names:
        mean_mdp = wcw.option_policies()[wcw.subtasks.index(option)]
        ref_mean = float(wcw.expected_return(mean_mdp))
        for pol in (wcw.replay_policy(option), wcw.fixed_instance_policy(option)):
            assert float(wcw.expected_return(pol)) > ref_mean + 1.0, option
    # the averaging head's replay fixed point is the mean-MDP optimum; the fixed-instance
    # optimum of a memoryless policy is better still (what Q-learning cannot represent)
    pi_bar = wcw.averaging_policy()
    ret = float(wcw.expected_return(pi_bar))
    assert float(wcw.expected_return(wcw.replay_policy())) == pytest.approx(ret, abs=1e-6)
    best = wcw.fixed_instance_policy()
    assert float(wcw.expected_return(best)) > ret + 0.2
    v_best, v_bar = wcw.fixed_instance_value(best), wcw.fixed_instance_value(pi_bar)
    assert float(v_best[wcw.start_cells].mean()) > float(v_bar[wcw.start_cells].mean())


def test_replay_mdp_is_the_mean_mdp_under_a_behaviour_every_instance_visits_alike():
    """With p in {0} only the instances do not differ: the replay MDP is the mean MDP."""
    o = WindyOracle(
        "default", train_instances=WindyInstances(points=((0.0, "north"), (0.0, "south")))
    )
    b = torch.full((o.S, o.A), 1.0 / o.A, dtype=torch.float64)
    P, R = o.replay_mdp(b)
    Pm, Rm = o.mean_mdp()
    assert torch.allclose(P, Pm) and torch.allclose(R, Rm)
    assert torch.allclose(P.sum(-1), torch.ones(o.S, o.A, dtype=torch.float64))
