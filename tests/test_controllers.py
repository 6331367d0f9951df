"""Controllers: the paper's Algorithms 1 and 2 on hand-built heads, batched vs looped,
sampled returns against the oracle's exact ones, TorchRL rollout/Collector and Gymnasium."""

from __future__ import annotations

import math
import warnings
from statistics import NormalDist

import gymnasium as gym
import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.envs import TransformedEnv
from torchrl.modules.utils import get_primers_from_module

import taskvar_torch  # noqa: F401  (registers the gym ids)
from taskvar_torch import keys
from taskvar_torch.controllers import (
    AveragingController,
    FusedHeads,
    HierarchyController,
    InterruptionController,
    OptionsController,
    argmax0,
    base,
    make_controller,
    select0,
)
from taskvar_torch.families.windy import WindyGridEnv, WindyInstances, WindyOracle
from taskvar_torch.families.windy import dynamics as windy
from taskvar_torch.heads.bundle import Heads
from taskvar_torch.heads.networks import make_head
from taskvar_torch.oracle import table_heads
from taskvar_torch.subtasks import Hierarchy, Subtasks

torch.set_num_threads(1)

A = 4  # actions


def td_of(cells, running=None) -> TensorDict:
    cells = torch.as_tensor(cells, dtype=torch.int64)
    td = TensorDict({keys.CELL: cells}, batch_size=cells.shape)
    if running is not None:
        td.set(keys.RUNNING_OPTION, torch.as_tensor(running, dtype=torch.int64).expand(cells.shape))
    return td


def alg1_heads(q_mu, q_hat, q_opt=None, temperature=None):
    """Heads over one 'situation' (cell 0): hand-built Q_mu (O,), Q_hat (O,), Q_o (O, A)."""
    if q_opt is None:
        q_opt = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 2.0, 0.0]])  # pi^0 = 0, pi^1 = 2
    return table_heads(
        ("o0", "o1"),
        options=torch.as_tensor(q_opt, dtype=torch.float64).unsqueeze(0),
        switching=torch.tensor([q_mu], dtype=torch.float64),
        max_value=torch.tensor([q_hat], dtype=torch.float64),
        softmax_temperature=temperature,
    )


# ---- Algorithm 1 on hand-built head values ----------------------------------------------------


def test_interruption_fires_when_q_hat_of_running_option_is_below_v_mu_bar():
    # V^{mu_bar} = max Q_mu = -3 (greedy); Q_hat(s, o_run=0) = -4 < -3: switch to argmax = o1
    ctrl = InterruptionController(alg1_heads(q_mu=[-5.0, -3.0], q_hat=[-4.0, -1.0]))
    td = ctrl(td_of([0], running=[0]))
    assert td[keys.INTERRUPTED].tolist() == [True]
    assert td[keys.OPTION].tolist() == [1]
    assert td[keys.NEXT, keys.RUNNING_OPTION].tolist() == [1]
    assert td[keys.ACTION].tolist() == [2]  # greedy in Q_{o1}


@pytest.mark.parametrize("q_hat_run", [-3.0, -2.0])
def test_interruption_does_not_fire_when_q_hat_is_not_strictly_below_v_mu_bar(q_hat_run):
    ctrl = InterruptionController(alg1_heads(q_mu=[-5.0, -3.0], q_hat=[q_hat_run, -1.0]))
    td = ctrl(td_of([0], running=[0]))
    assert td[keys.INTERRUPTED].tolist() == [False]
    assert td[keys.OPTION].tolist() == [0]  # o0 keeps running although mu_bar prefers o1
    assert td[keys.ACTION].tolist() == [0]


def test_options_controller_never_interrupts_a_running_option():
    ctrl = OptionsController(alg1_heads(q_mu=[-5.0, -3.0], q_hat=[-4.0, -1.0]))
    td = ctrl(td_of([0, 0], running=[0, 1]))
    assert td[keys.OPTION].tolist() == [0, 1]
    assert td[keys.INTERRUPTED].tolist() == [False, False]


def test_episode_start_picks_argmax_q_mu_even_with_a_softmax_mu_bar():
    # line 4 is an argmax: with an almost uniform softmax mu_bar, every start still picks o1
    ctrl = InterruptionController(
        alg1_heads(q_mu=[-3.1, -3.0], q_hat=[0.0, 0.0], temperature=100.0), seed=1
    )
    td = ctrl(td_of([0] * 1000, running=[-1] * 1000))
    assert bool((td[keys.OPTION] == 1).all())
    assert not bool(td[keys.INTERRUPTED].any())


def test_softmax_interruption_draws_the_new_option_from_mu_bar():
    # interruption fires for every env; the new option is drawn from softmax(Q_mu / T)
    T, n = 1.0, 20000
    q_mu = torch.tensor([-3.0, -2.0], dtype=torch.float64)
    ctrl = InterruptionController(alg1_heads(q_mu.tolist(), [-10.0, -10.0], temperature=T), seed=3)
    td = ctrl(td_of([0] * n, running=[1] * n))
    assert bool(td[keys.INTERRUPTED].all())
    p1 = float(torch.softmax(q_mu / T, -1)[1])
    freq = float((td[keys.OPTION] == 1).double().mean())
    assert abs(freq - p1) < 4 * math.sqrt(p1 * (1 - p1) / n)
    # seeded: the same seed gives the same draws, another seed different ones
    again = InterruptionController(alg1_heads(q_mu.tolist(), [-10.0] * 2, temperature=T), seed=3)
    other = InterruptionController(alg1_heads(q_mu.tolist(), [-10.0] * 2, temperature=T), seed=4)
    assert torch.equal(again(td_of([0] * n, running=[1] * n))[keys.OPTION], td[keys.OPTION])
    assert not torch.equal(other(td_of([0] * n, running=[1] * n))[keys.OPTION], td[keys.OPTION])


class _TerminateEverywhere(Subtasks):
    names = ("o0", "o1")

    def termination(self, td):
        return torch.ones(*td.batch_size, 2, dtype=torch.bool)


def test_terminated_running_option_is_replaced_by_argmax_q_mu():
    heads = alg1_heads(q_mu=[-5.0, -3.0], q_hat=[0.0, 0.0])  # no interruption possible
    for cls in (OptionsController, InterruptionController):
        td = cls(heads, _TerminateEverywhere())(td_of([0], running=[0]))
        assert td[keys.OPTION].tolist() == [1]
        assert td[keys.INTERRUPTED].tolist() == [False]


def test_controller_without_its_state_key_raises_a_clear_error():
    ctrl = InterruptionController(alg1_heads([-5.0, -3.0], [0.0, 0.0]))
    with pytest.raises(KeyError, match="primer"):
        ctrl(td_of([0]))


def test_controller_refuses_a_bundle_without_its_heads():
    heads = table_heads(("o0", "o1"), switching=torch.zeros(1, 2))
    with pytest.raises(ValueError, match="max_value"):
        InterruptionController(heads)
    with pytest.raises(ValueError, match="one of"):
        make_controller("flat", heads)


# ---- batched equals per-environment loop -----------------------------------------------------


def random_tables(S: int, seed: int, num_options: int = 3):
    """Integer-valued tables: ties are frequent, so tie-breaking is exercised too."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *shape: torch.randint(-4, 1, shape, generator=g).to(torch.float64)  # noqa: E731
    k = num_options
    return dict(options=r(S, k, A), switching=r(S, k), max_value=r(S, k), robustness=r(S, k, A))


@pytest.mark.parametrize("K", [2, 3, 4, 20])
def test_option_first_kernels_equal_reductions(K):
    g = torch.Generator().manual_seed(K)
    x = torch.randint(-2, 2, (K, 4, 1000), generator=g).to(torch.float32)  # many ties
    assert torch.equal(argmax0(x), x.movedim(0, -1).argmax(-1))
    idx = torch.randint(0, K, (1000,), generator=g)
    assert torch.equal(select0(x, idx), x[idx, :, torch.arange(1000)].T)
    assert torch.equal(select0(x[:, 0], idx), x[idx, 0, torch.arange(1000)])


@pytest.mark.parametrize("name", ["averaging", "options", "interruption", "hierarchy"])
def test_batched_decisions_equal_a_per_environment_loop(name):
    S, B = 25, 600
    t = random_tables(S, seed=1)
    names = ("root", "a", "b")
    heads = table_heads(names, averaging=t["options"][:, 0], **t)
    tree = Hierarchy(root="root", children={"root": ("a", "b")})
    ctrl = make_controller(name, heads, hierarchy=tree, tau=-2.0)
    g = torch.Generator().manual_seed(2)
    cells = torch.randint(0, S, (B,), generator=g)
    running = torch.randint(-1, 3, (B,), generator=g)
    batched = ctrl(td_of(cells, running))
    out_keys = [keys.ACTION, *ctrl.trace_keys]
    for i in range(B):
        one = ctrl(td_of(cells[i : i + 1], running[i : i + 1]))
        for k in out_keys:
            assert one[k].item() == batched[k][i].item(), (k, i)
        # the real-time scalar path decides the same
        scalar = ctrl.act_one({keys.CELL: cells[i : i + 1]}, int(running[i]))
        for k in out_keys:
            assert scalar[k] == batched[k][i].item(), ("scalar", k, i)


@pytest.mark.slow
def test_batched_rollout_equals_single_environment_rollouts():
    oracle = WindyOracle("whole_column_windy", train_instances="south")
    ctrl = InterruptionController(oracle.heads(), oracle.subtasks)
    kw = dict(layout="whole_column_windy", instances="north", seed=5)
    n, T = 8, 50
    env = TransformedEnv(WindyGridEnv(num_envs=n, **kw), ctrl.primer())
    batched = env.rollout(T, ctrl, break_when_any_done=False)
    assert bool(batched[keys.INTERRUPTED].any())  # the case where interruption matters
    for i in range(n):
        single = TransformedEnv(WindyGridEnv(num_envs=1, index_offset=i, **kw), ctrl.primer())
        one = single.rollout(T, ctrl, break_when_any_done=False)
        for k in (keys.ACTION, keys.OPTION, keys.INTERRUPTED, keys.CELL, keys.RUNNING_OPTION):
            assert torch.equal(one[k][0], batched[k][i]), (k, i)


def mlp_heads(num_options: int = 3, seed: int = 0):

    torch.manual_seed(seed)
    k, d = num_options, 25
    return Heads(
        ("root", "a", "b")[:k],
        averaging=make_head(keys.ACTION_VALUE, d, A),
        options=make_head(keys.OPTION_ACTION_VALUE, d, (k, A)),
        switching=make_head(keys.OPTION_VALUE, d, k),
        max_value=make_head(keys.MAX_VALUE, d, k),
        robustness=make_head(keys.ROBUSTNESS, d, (k, A)),
    )


@pytest.mark.parametrize("name", ["averaging", "options", "interruption", "hierarchy"])
def test_fused_mlp_heads_scalar_path_matches_the_tensordict_path(name):
    heads = mlp_heads()
    tree = Hierarchy(root="root", children={"root": ("a", "b")})
    ctrl = make_controller(name, heads, hierarchy=tree, tau=0.0)
    fused = ctrl.fuse()
    assert isinstance(fused, FusedHeads)
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(200, 25, generator=g)
    running = torch.randint(-1, 3, (200,), generator=g)
    with torch.inference_mode():
        parts = fused.split(fused(obs))
        separate = ctrl.head_values({keys.OBSERVATION: obs})
        for k, v in separate.items():
            assert torch.allclose(parts[k], v, atol=1e-5)
        td = TensorDict({keys.OBSERVATION: obs, keys.RUNNING_OPTION: running}, [200])
        batched = ctrl(td)
    for i in range(200):
        one = ctrl.act_one({keys.OBSERVATION: obs[i : i + 1]}, int(running[i]))
        for k in [keys.ACTION, *ctrl.trace_keys]:
            assert one[k] == batched[k][i].item(), (k, i)


# ---- Algorithm 2 on a hand-built three-level tree -----------------------------------------------

# root -> (A, B); A -> (A1, A2). Option index: root 0, A 1, B 2, A1 3, A2 4.
TREE = Hierarchy(root="root", children={"root": ("A", "B"), "A": ("A1", "A2")})
NAMES = ("root", "A", "B", "A1", "A2")
TAU = 0.0
# each option's greedy action is its own: root->0, A->1, B->2, A1->3, A2->0
OWN_ACTION = [0, 1, 2, 3, 0]


def tree_heads(robust_rows: list[dict[str, dict[int, float]]], averaging=None) -> object:
    """Robustness R(o, s, a) per situation s: default -1 (below tau), overridden by rows[s][o][a]."""
    S = len(robust_rows)
    q = torch.zeros(S, 5, A, dtype=torch.float64)
    for o, a in enumerate(OWN_ACTION):
        q[:, o, a] = 1.0
    rob = torch.full((S, 5, A), -1.0, dtype=torch.float64)
    for s, row in enumerate(robust_rows):
        for name, acts in row.items():
            for a, v in acts.items():
                rob[s, NAMES.index(name), a] = v
    return table_heads(NAMES, options=q, robustness=rob, averaging=averaging)


def run_hierarchy(heads, situations, running=-1):
    """Step the controller through situations (cells) carrying its state; return the traces."""
    ctrl = HierarchyController(heads, TREE, TAU)
    out, state = [], torch.tensor([running])
    for s in situations:
        td = ctrl(td_of([s], state))
        state = td[keys.NEXT, keys.RUNNING_OPTION]
        out.append(
            (NAMES[td[keys.OPTION].item()], td[keys.HIERARCHY_LEVEL].item(), td[keys.ACTION].item())
        )
    return out


def test_hierarchy_episode_start_runs_the_root_when_it_is_robust():
    heads = tree_heads([{"root": {0: 1.0}}])
    assert run_hierarchy(heads, [0]) == [("root", 0, 0)]


def test_hierarchy_descends_to_the_most_robust_component_under_the_parents_action():
    # root is not robust; under root's action a=0, A is more robust than B (line 10 uses a of
    # o_run), although B is the more robust one under its own action a=2
    heads = tree_heads([{"A": {0: 5.0, 1: 1.0}, "B": {0: 3.0, 2: 9.0}}])
    assert run_hierarchy(heads, [0]) == [("A", 1, 1)]
    heads = tree_heads([{"A": {0: 3.0, 1: 1.0}, "B": {0: 5.0, 2: 9.0}}])
    assert run_hierarchy(heads, [0]) == [("B", 1, 2)]


def test_hierarchy_primitive_options_act_even_when_not_robust():
    # root and A both fail; A's components are leaves: the more robust under A's action acts,
    # although its own robustness is below tau
    heads = tree_heads([{"A": {0: 5.0}, "A1": {1: -0.5}, "A2": {1: -0.2}}])
    assert run_hierarchy(heads, [0]) == [("A2", 2, 0)]


def test_hierarchy_parent_regains_control_as_soon_as_its_robustness_exceeds_tau():
    # situation 0: A1 runs (A not robust); situation 1: A (the parent) robust -> A takes over at
    # once, even though the root is robust too (only the parent is checked, line 2); situation 2:
    # now the root is A's parent and robust -> the root regains control
    rows = [
        {"A": {0: 5.0}, "A1": {1: 2.0}},
        {"A": {1: 1.0}, "A1": {3: 2.0}, "root": {0: 1.0}},
        {"A": {1: 1.0}, "root": {0: 1.0}},
    ]
    heads = tree_heads(rows)
    assert run_hierarchy(heads, [0, 1, 2]) == [("A1", 2, 3), ("A", 1, 1), ("root", 0, 0)]
    # threshold is strict: robustness == tau does not regain control
    rows[1]["A"] = {1: TAU}
    assert run_hierarchy(tree_heads(rows), [0, 1]) == [("A1", 2, 3), ("A1", 2, 3)]


def test_hierarchy_running_subtask_persists_across_steps():
    # B runs and stays robust; its parent (root) is not robust: B keeps control although A is
    # more robust in every situation
    rows = [{"B": {2: 1.0}, "A": {0: 9.0, 1: 9.0, 2: 9.0}}] * 3
    heads = tree_heads(rows)
    assert run_hierarchy(heads, [0, 1, 2], running=NAMES.index("B")) == [("B", 1, 2)] * 3


def test_hierarchy_root_can_follow_the_averaging_policy():
    # paper §3.4.2: "the policy of this subtask is the full task averaging policy". Q_avg prefers
    # action 3, the root's option head action 0; the root is robust only under action 3.
    q_avg = torch.zeros(1, A, dtype=torch.float64)
    q_avg[0, 3] = 1.0
    heads = tree_heads([{"root": {3: 1.0}, "A": {0: 5.0}, "A1": {1: 2.0}}], averaging=q_avg)
    own = HierarchyController(heads, TREE, TAU)  # root's own action 0 is not robust: descend
    avg = HierarchyController(heads, TREE, TAU, root_policy="averaging")
    assert "averaging" in avg.required_heads and "averaging" not in own.required_heads
    for ctrl, want in ((own, ("A1", 2, 3)), (avg, ("root", 0, 3))):
        td = ctrl(td_of([0], torch.tensor([-1])))
        got = (
            NAMES[td[keys.OPTION].item()],
            td[keys.HIERARCHY_LEVEL].item(),
            td[keys.ACTION].item(),
        )
        assert got == want
        scalar = ctrl.act_one({keys.CELL: torch.tensor([0])}, -1)
        assert (NAMES[scalar["option"]], scalar[keys.HIERARCHY_LEVEL], scalar["action"]) == want
    with pytest.raises(ValueError, match="root_policy must be one of"):
        HierarchyController(heads, TREE, TAU, root_policy="flat")


def test_the_oracles_hierarchy_chain_holds_the_controllers_decisions():
    t = random_tables(25, seed=7, num_options=5)
    heads = table_heads(NAMES, options=t["options"], robustness=t["robustness"])
    ctrl = HierarchyController(heads, TREE, -2.0)
    chain = WindyOracle().controller_chain(ctrl)
    S, Z = 25, 6
    cells = torch.arange(S).repeat_interleave(Z)
    running = torch.arange(Z).repeat(S) - 1
    td = ctrl(td_of(cells, running))
    expected = chain["decision"].reshape(S * Z, 5).argmax(-1)
    assert torch.equal(td[keys.OPTION], expected)
    assert torch.equal(td[keys.INTERRUPTED], chain["fires"].reshape(-1))


# ---- sampled returns against the oracle's exact returns -----------------------------------------

CASES = {
    # (layout, training distribution): on whole_column_windy trained on south winds, interruption
    # fires and changes the return (with the paper's training distribution it never fires)
    "default": ("default", "train"),
    "whole_column": ("whole_column_windy", "south"),
}
TEST_INSTANCES = [(0.25, "north"), (0.75, "south"), (1.0, "north"), (0.5, "south")]
N_ENVS = 12000  # about 3000 per test instance
CONTROLLER_NAMES = ("averaging", "options", "interruption", "hierarchy")
# simultaneous 99% intervals: Bonferroni over every (case, controller, instance) comparison
Z99 = NormalDist().inv_cdf(
    1 - 0.01 / (2 * len(CASES) * len(CONTROLLER_NAMES) * len(TEST_INSTANCES))
)


def oracle_and_controller(case: str, name: str) -> tuple[WindyOracle, object]:
    layout, train = CASES[case]
    oracle = WindyOracle(layout, train_instances=train)
    if name != "hierarchy":
        return oracle, make_controller(name, oracle.heads(), oracle.subtasks)
    # hierarchy: root "task" (the averaging policy) over the exit options; robustness = values
    q = torch.cat([oracle.averaging_q().unsqueeze(1), oracle.option_q().permute(1, 0, 2)], 1)
    heads = table_heads(("task", *oracle.option_names), options=q, robustness=q)
    tree = Hierarchy(root="task", children={"task": oracle.option_names})
    return oracle, HierarchyController(heads, tree, tau=-3.0)


def first_episode(env: TransformedEnv, ctrl) -> tuple[torch.Tensor, torch.Tensor, TensorDict]:
    """First-episode return, number of steps where the controller's decision moved, instance."""
    td = env.reset()
    instance = td[keys.INSTANCE].clone()
    n = env.batch_size[0]
    alive = torch.ones(n, dtype=torch.bool)
    ret = torch.zeros(n, dtype=torch.float64)
    fired = torch.zeros(n, dtype=torch.float64)
    for _ in range(env.base_env.horizon):
        td = ctrl(td)
        if keys.INTERRUPTED in td.keys():
            fired += td[keys.INTERRUPTED] * alive
        out, td = env.step_and_maybe_reset(td)
        ret += out["next", "reward"].squeeze(-1) * alive
        alive &= ~out["next", "done"].squeeze(-1)
        if not bool(alive.any()):
            break
    assert not bool(alive.any())
    return ret, fired, instance


@pytest.mark.parametrize("name", CONTROLLER_NAMES)
@pytest.mark.parametrize("case", list(CASES))
def test_sampled_mean_return_matches_the_exact_return_per_instance(case, name):
    """Each sub-environment draws one of the test instances; results are grouped by instance."""
    oracle, ctrl = oracle_and_controller(case, name)
    layout = CASES[case][0]
    inst = WindyInstances(points=tuple(TEST_INSTANCES))
    env = TransformedEnv(WindyGridEnv(N_ENVS, layout, inst, seed=11), ctrl.primer())
    ret, fired, instance = first_episode(env, ctrl)
    p_env, d_env = instance["p"], instance["direction"]
    for p, d in TEST_INSTANCES:
        mask = (p_env == p) & (d_env == windy.direction_index(d))
        n = int(mask.sum())
        assert n > N_ENVS // 8
        exact = float(oracle.controller_return(ctrl, p, d, start="uniform"))
        fires = float(oracle.controller_fire_count(ctrl, p, d, start="uniform"))
        r, f = ret[mask], fired[mask]
        se, se_f = float(r.std()) / math.sqrt(n), float(f.std()) / math.sqrt(n)
        assert abs(float(r.mean()) - exact) <= Z99 * se + 1e-9, (p, d, float(r.mean()), exact)
        assert abs(float(f.mean()) - fires) <= Z99 * se_f + 1e-9, (p, d, float(f.mean()), fires)


def test_interruption_changes_the_exact_return_on_whole_column_windy():
    """The comparison above can tell the controllers apart: exact returns differ there."""
    o_opt, c_opt = oracle_and_controller("whole_column", "options")
    o_int, c_int = oracle_and_controller("whole_column", "interruption")
    diff = o_int.controller_return(c_int, 1.0, "north") - o_opt.controller_return(
        c_opt, 1.0, "north"
    )
    assert float(diff.max()) > 10.0
    assert float(o_int.controller_fire_count(c_int, 1.0, "north", start="uniform")) > 0.1


def test_averaging_controller_return_equals_policy_evaluation():
    o = WindyOracle()
    ctrl = AveragingController(o.heads())
    for p, d in TEST_INSTANCES:
        assert torch.allclose(
            o.controller_return(ctrl, p, d), o.episode_return(o.averaging_policy(), p, d)
        )


# ---- TorchRL Collector, partial resets, Gymnasium -------------------------------------------------


def check_state_is_carried_and_reset(batch: TensorDict) -> None:
    run, opt = batch[keys.RUNNING_OPTION], batch[keys.OPTION]  # (N, T)
    done = batch[keys.NEXT, keys.DONE].squeeze(-1)
    assert torch.equal(batch[keys.NEXT, keys.RUNNING_OPTION], opt)
    expected = torch.where(done[:, :-1], torch.full_like(opt[:, :-1], -1), opt[:, :-1])
    assert torch.equal(run[:, 1:], expected)
    assert bool(done.any())  # partial resets happened


@pytest.mark.parametrize("name", ["options", "interruption", "hierarchy"])
def test_controllers_run_inside_a_torchrl_collector(name):
    oracle, ctrl = oracle_and_controller("whole_column", name)
    env = TransformedEnv(
        WindyGridEnv(num_envs=32, layout="whole_column_windy", instances="north", seed=3),
        ctrl.primer(),
    )
    collector = Collector(
        env,
        ctrl,
        frames_per_batch=32 * 40,
        total_frames=32 * 80,
        auto_register_policy_transforms=False,
    )
    batches = list(collector)
    collector.shutdown()
    assert len(batches) == 2
    for batch in batches:
        check_state_is_carried_and_reset(batch)
    if name == "interruption":
        assert bool(torch.cat([b[keys.INTERRUPTED] for b in batches]).any())
    if name == "hierarchy":
        assert set(torch.cat([b[keys.HIERARCHY_LEVEL] for b in batches]).unique().tolist()) == {
            0,
            1,
        }


def test_collector_auto_registers_the_controllers_primer():
    oracle, ctrl = oracle_and_controller("default", "interruption")
    assert get_primers_from_module(ctrl) is not None
    env = WindyGridEnv(num_envs=8, seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        collector = Collector(
            env,
            ctrl,
            frames_per_batch=8 * 30,
            total_frames=8 * 30,
            auto_register_policy_transforms=True,
        )
    batch = next(iter(collector))
    collector.shutdown()
    check_state_is_carried_and_reset(batch)


def test_gymnasium_env_runs_the_controller_like_the_torchrl_env():
    oracle, ctrl = oracle_and_controller("whole_column", "interruption")
    env = gym.make("taskvar/WindyGrid-WholeColumnWindy-v0")
    pol = base.GymnasiumPolicy(ctrl, width=env.unwrapped.layout.width)
    inst = {"p": 0.75, "direction": "north"}
    gym_cells, gym_options = [], []
    for episode in range(6):
        obs, info = env.reset(seed=21 if episode == 0 else None, options={"instance": inst})
        pol.reset()
        done = False
        while not done:
            a = pol(obs, info)
            gym_options.append(pol.trace[keys.OPTION])
            obs, r, term, trunc, info = env.step(a)
            gym_cells.append(info["cell"][0] * 5 + info["cell"][1])
            done = term or trunc
    # the same episodes in the TorchRL env (sub-environment 0 of seed 21 draws the same stream)
    tenv = TransformedEnv(
        WindyGridEnv(1, "whole_column_windy", WindyInstances.fixed(0.75, "north"), seed=21),
        ctrl.primer(),
    )
    td = tenv.rollout(len(gym_cells), ctrl, break_when_any_done=False)
    assert td[keys.NEXT, keys.CELL][0].tolist() == gym_cells
    assert td[keys.OPTION][0].tolist() == gym_options
    assert int(td[keys.NEXT, keys.DONE].sum()) == 6


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("name", CONTROLLER_NAMES)
def test_controllers_run_on_cuda_and_match_cpu(name):
    oracle, ctrl = oracle_and_controller("whole_column", name)
    kw = dict(layout="whole_column_windy", instances="north", seed=4)
    env = TransformedEnv(WindyGridEnv(256, **kw), ctrl.primer())
    cpu = env.rollout(50, ctrl, break_when_any_done=False)
    ctrl_cuda = ctrl.to("cuda")
    env = TransformedEnv(WindyGridEnv(256, device="cuda", **kw), ctrl_cuda.primer())
    gpu = env.rollout(50, ctrl_cuda, break_when_any_done=False)
    for k in [keys.ACTION, *ctrl.trace_keys]:
        assert torch.equal(gpu[k].cpu(), cpu[k]), k
