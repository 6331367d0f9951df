"""Initiation sets in the controllers (paper §3.2; Algorithm 1 lines 4, 6, 7; Algorithm 2 line 10).

mu_bar picks and draws only among the options whose initiation set I_o holds s_t, line 6's
V^{mu_bar} ranges over them, and where none is initiable the averaging head acts with option -1.
Checked on hand-made table heads whose unmasked argmax of Q_mu is a non-initiable option, in the
three implementations (batched kernels, scalar real-time path, the oracle's chains), and on
rollouts (TorchRL and Gymnasium): no option ever starts, or acts, outside its initiation set.
"""

from __future__ import annotations

import math

import gymnasium as gym
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import TransformedEnv

import taskvar_torch  # noqa: F401  (registers the gym ids)
from taskvar_torch import keys
from taskvar_torch.controllers import (
    GymnasiumPolicy,
    HierarchyController,
    InterruptionController,
    OptionsController,
)
from taskvar_torch.controllers.base import sample_categorical
from taskvar_torch.controllers.interruption import interruption_decide_of, masked_mu_bar
from taskvar_torch.families.windy import WindyGridEnv, WindyInstances, WindyOracle
from taskvar_torch.oracle import table_heads
from taskvar_torch.subtasks import Hierarchy, Subtasks

torch.set_num_threads(1)

S, A, W = 25, 4, 5  # the default windy grid: 5 x 5 cells, 4 actions
NAMES = ("o0", "o1", "o2")
NEG = -1e9  # "minus infinity" for hand-made tables
GOAL = WindyOracle().model.is_goal  # (S,) bool


class TableSubtasks(Subtasks):
    """Options whose initiation sets and terminations are per-cell tables ``(S, O)`` bool."""

    def __init__(self, names, init, beta):
        self.names = tuple(names)
        self.init, self.beta = init, beta

    def initiation(self, td):
        return self.init[td.get(keys.CELL)]

    def termination(self, td):
        return self.beta[td.get(keys.CELL)]


def td_of(cells, running) -> TensorDict:
    cells = torch.as_tensor(cells, dtype=torch.int64)
    run = torch.as_tensor(running, dtype=torch.int64).expand(cells.shape)
    return TensorDict({keys.CELL: cells, keys.RUNNING_OPTION: run}, batch_size=cells.shape)


def hand_made(temperature=None):
    """Tables where Q_mu's unmasked argmax is o0 (10) and o0 is initiable nowhere but cell 4.

    cell 0: I = {o1, o2}, Q_mu = (10, 1, 3): line 4 picks o2.
    cell 1: I = {o1, o2}, Q_hat(o0) = 4 lies between V over I (3) and the unmasked V (10).
    cell 2: I = {} (no option can start): the averaging action 3 acts.
    cell 3: I = {o1, o2}, Q_hat very low: line 6 always fires, line 7 draws from {o1, o2}.
    """
    q_mu = torch.tensor([10.0, 1.0, 3.0], dtype=torch.float64).repeat(S, 1)
    q_hat = torch.full((S, 3), 4.0, dtype=torch.float64)
    q_hat[3] = -100.0
    q_opt = torch.zeros(S, 3, A, dtype=torch.float64)
    q_opt[:, 0, 0] = q_opt[:, 1, 1] = q_opt[:, 2, 2] = 1.0  # pi^o = o
    q_avg = torch.zeros(S, A, dtype=torch.float64)
    q_avg[:, 3] = 1.0  # the averaging action: 3
    init = torch.zeros(S, 3, dtype=torch.bool)
    init[:, 1:] = True
    init[2] = False
    init[4, 0] = True
    beta = torch.zeros(S, 3, dtype=torch.bool)
    heads = table_heads(
        NAMES,
        averaging=q_avg,
        options=q_opt,
        switching=q_mu,
        max_value=q_hat,
        softmax_temperature=temperature,
    )
    return heads, TableSubtasks(NAMES, init, beta)


def both_paths(ctrl, cell, running):
    """The batched decision and the scalar real-time one at one cell: (option, action, interrupted)."""
    td = ctrl(td_of([cell], [running]))
    ended = ctrl.subtasks is not None and running >= 0 and bool(ctrl.subtasks.beta[cell, running])
    one = ctrl.act_one({keys.CELL: torch.tensor([cell])}, running, ended)
    batched = (td[keys.OPTION].item(), td[keys.ACTION].item(), td[keys.INTERRUPTED].item())
    scalar = (one["option"], one["action"], one[keys.INTERRUPTED])
    return batched, scalar


# ---- Algorithm 1 on hand-made heads --------------------------------------------------------------


@pytest.mark.parametrize("cls", [OptionsController, InterruptionController])
def test_line4_picks_the_best_initiable_option(cls):
    heads, sub = hand_made()
    ctrl = cls(heads, sub)
    assert both_paths(ctrl, 0, -1) == ((2, 2, False),) * 2  # o0 (Q_mu 10) is not initiable
    assert both_paths(cls(heads), 0, -1)[0][0] == 0  # without subtasks: the unmasked argmax
    chain = WindyOracle().controller_chain(ctrl)
    assert chain["decision"][0, 0].tolist() == [0.0, 0.0, 1.0, 0.0]


def test_line6_compares_with_v_over_the_initiable_options():
    heads, sub = hand_made()
    ctrl = InterruptionController(heads, sub)
    # o0 runs at cell 1 (outside I_o0: a running option is not re-checked). Q_hat(o0) = 4 is not
    # below V^{mu_bar} = max over {o1, o2} = 3, so o0 continues (the unmasked V = 10 would fire)
    assert both_paths(ctrl, 1, 0) == ((0, 0, False),) * 2
    assert both_paths(InterruptionController(heads), 1, 0)[0][2] is True
    # o1 runs at cell 3 (Q_hat = -100 < 3): line 6 fires and picks o2, not o0
    assert both_paths(ctrl, 3, 1) == ((2, 2, True),) * 2
    chain = WindyOracle().controller_chain(ctrl)
    assert not bool(chain["fires"][1, 1]) and bool(chain["fires"][3, 2])
    assert chain["decision"][3, 2].tolist() == [0.0, 0.0, 1.0, 0.0]


def test_softmax_v_and_draws_range_over_the_initiable_options():
    T, n = 2.0, 20000
    heads, sub = hand_made(temperature=T)
    ctrl = InterruptionController(heads, sub, seed=5)
    mu = torch.softmax(torch.tensor([1.0, 3.0], dtype=torch.float64) / T, -1)  # over {o1, o2}
    v = float((mu * torch.tensor([1.0, 3.0], dtype=torch.float64)).sum())
    assert v < 4.0  # so at cell 1, Q_hat(o0) = 4 is not below V: no firing (unmasked V ~ 9.9)
    td = ctrl(td_of([1] * 100, [0] * 100))
    assert not bool(td[keys.INTERRUPTED].any()) and bool((td[keys.OPTION] == 0).all())
    td = ctrl(td_of([3] * n, [1] * n))  # line 6 fires everywhere: line 7 draws
    assert bool(td[keys.INTERRUPTED].all())
    opt = td[keys.OPTION]
    assert set(opt.unique().tolist()) == {1, 2}  # never o0 (unmasked mu_bar(o0) ~ 0.93)
    freq = float((opt == 2).double().mean())
    p2 = float(mu[1])
    assert abs(freq - p2) < 4 * math.sqrt(p2 * (1 - p2) / n)
    for _ in range(300):  # the scalar path's draws
        one = ctrl.act_one({keys.CELL: torch.tensor([3])}, 1)
        assert one[keys.INTERRUPTED] and one["option"] in (1, 2)
    chain = WindyOracle().controller_chain(ctrl)
    torch.testing.assert_close(chain["decision"][3, 2, 1:3], mu)
    assert float(chain["decision"][3, 2, 0]) == 0.0 and not bool(chain["fires"][1, 1])


def test_a_draw_never_rounds_onto_a_non_initiable_option():
    probs = torch.tensor([[0.3], [0.7], [0.0]], dtype=torch.float32)
    allowed = torch.tensor([[True], [True], [False]])
    u = torch.tensor([1.0 - 2**-24])  # past the rounded total: clamps to the last allowed index
    assert sample_categorical(probs, u, allowed).tolist() == [1]


@pytest.mark.parametrize("softmax", [False, True])
def test_the_masked_kernel_has_no_host_sync(softmax):
    # meta tensors have no data: a hidden host read (.item(), bool(t), masking by a bool index) raises
    B, O = 64, 3  # noqa: E741
    meta = lambda *shape, dtype=torch.float32: torch.empty(*shape, device="meta", dtype=dtype)  # noqa: E731
    initiable = meta(O, B, dtype=torch.bool)
    mu = masked_mu_bar(meta(O, B), 0.5, initiable) if softmax else None
    out = interruption_decide_of(
        meta(O, A, B),
        meta(O, B),
        meta(O, B),
        meta(B, dtype=torch.int64),
        meta(B, dtype=torch.bool),
        mu,
        meta(B) if softmax else None,
        initiable,
        meta(A, B),
    )
    assert all(v.device.type == "meta" and v.shape == (B,) for v in out.values())


@pytest.mark.parametrize("cls", [OptionsController, InterruptionController])
def test_no_initiable_option_falls_back_to_the_averaging_action(cls):
    heads, sub = hand_made()
    ctrl = cls(heads, sub)
    assert both_paths(ctrl, 2, -1) == ((-1, 3, False),) * 2  # option -1, Q_avg's action
    td = ctrl(td_of([2], [-1]))
    assert td[keys.NEXT, keys.RUNNING_OPTION].tolist() == [-1]  # line 4 again next step
    # a running option continues where none is initiable (nothing to interrupt to)
    sub.beta[2] = False
    heads.heads["max_value"].module.table[2] = -100.0
    assert both_paths(cls(heads, sub), 2, 1) == ((1, 1, False),) * 2
    # ... and where it terminates, the averaging action acts
    sub.beta[2, 1] = True
    assert both_paths(cls(heads, sub), 2, 1) == ((-1, 3, False),) * 2
    chain = WindyOracle().controller_chain(cls(heads, sub))
    assert chain["action"].shape == (S, 4) and chain["action"][2, 3].item() == 3
    assert chain["next_state"][3].item() == 0  # the carried state stays empty
    assert chain["decision"][2, 0, 3].item() == 1.0 and chain["decision"][2, 2, 3].item() == 1.0


def test_the_fallback_needs_the_averaging_head():
    heads, sub = hand_made()
    no_avg = table_heads(
        NAMES,
        options=heads.heads["options"].module.table,
        switching=heads.heads["switching"].module.table,
    )
    with pytest.raises(ValueError, match="no option is initiable"):
        OptionsController(no_avg, sub)
    OptionsController(no_avg)  # without subtasks: not needed


# ---- the three implementations agree on random tables --------------------------------------------


def random_case(seed: int, temperature=None):
    """Integer-valued tables (frequent ties), random initiation sets (some cells with none) and
    terminations."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *shape: torch.randint(-4, 1, shape, generator=g).to(torch.float64)  # noqa: E731
    init = torch.rand(S, 3, generator=g) < 0.45
    beta = torch.rand(S, 3, generator=g) < 0.3
    heads = table_heads(
        NAMES,
        averaging=r(S, A),
        options=r(S, 3, A),
        switching=r(S, 3),
        max_value=r(S, 3),
        softmax_temperature=temperature,
    )
    return heads, TableSubtasks(NAMES, init, beta)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("cls", [OptionsController, InterruptionController])
def test_batched_scalar_and_chain_agree_and_honour_initiation(cls, seed):
    heads, sub = random_case(seed)
    assert bool((~sub.init.any(-1)).any())  # some cells have no initiable option
    ctrl = cls(heads, sub)
    Z = 4
    cells = torch.arange(S).repeat_interleave(Z)
    running = torch.arange(Z).repeat(S) - 1
    td = ctrl(td_of(cells, running))
    chain = WindyOracle().controller_chain(ctrl)
    n = chain["decision"].reshape(S * Z, Z).argmax(-1)  # greedy: one-hot rows
    expected = torch.where(n == 3, -1, n)  # the last column is the averaging fallback
    assert torch.equal(td[keys.OPTION], expected)
    assert torch.equal(td[keys.INTERRUPTED], chain["fires"].reshape(-1))
    assert torch.equal(td[keys.ACTION], chain["action"][cells, n])
    for i in range(S * Z):
        run = int(running[i])
        ended = run >= 0 and bool(sub.beta[cells[i], run])
        one = ctrl.act_one({keys.CELL: cells[i : i + 1]}, run, ended)
        assert (one["option"], one["action"], one[keys.INTERRUPTED]) == (
            td[keys.OPTION][i].item(),
            td[keys.ACTION][i].item(),
            td[keys.INTERRUPTED][i].item(),
        )
    # every pick (a new option) is initiable; -1 only where none is
    opt = td[keys.OPTION]
    picked = (opt >= 0) & (opt != running)
    assert bool(sub.init[cells[picked], opt[picked]].all())
    assert bool((~sub.init[cells[opt < 0]].any(-1)).all())


def test_initiable_everywhere_gives_the_same_decisions_as_no_subtasks():
    # the windy and Wargus case: every option initiable at every decision state
    for T in (None, 1.5):
        heads, sub = random_case(3, temperature=T)
        sub.init[:] = True
        sub.beta[:] = False
        cells = torch.arange(S).repeat(40)
        running = torch.randint(-1, 3, cells.shape, generator=torch.Generator().manual_seed(1))
        a = InterruptionController(heads, sub, seed=2)(td_of(cells, running))
        b = InterruptionController(heads, None, seed=2)(td_of(cells, running))
        for k in (keys.ACTION, keys.OPTION, keys.INTERRUPTED):
            assert torch.equal(a[k], b[k]), (T, k)


# ---- rollouts -----------------------------------------------------------------------------------


def rollout_case(seed: int, temperature=None):
    """Random heads whose Q_mu prefers o0; I_o0 = column 0, I_o1 = rows 0-2, I_o2 = rows 2-4 left
    of the goal side, none at cell 21 (row 4, column 1); an option terminates outside its I_o, so
    a running option that leaves I_o hands the choice back to mu_bar (or the goal ends it)."""
    heads, _ = random_case(seed, temperature)
    heads.heads["switching"].module.table[:, 0] += 10.0  # the unmasked argmax: o0
    row, col = torch.arange(S) // W, torch.arange(S) % W
    left = ~GOAL
    init = torch.stack([col == 0, left & (row <= 2), left & (row >= 2)], -1)
    init[21] = False
    beta = ~init | GOAL.unsqueeze(-1)
    return heads, TableSubtasks(NAMES, init, beta)


def check_initiation(cells, running, option, init):
    """No option starts, or acts, outside its initiation set; -1 only where none is initiable."""
    act = option >= 0
    assert bool(init[cells[act], option[act]].all())
    assert bool((~init[cells[~act]].any(-1)).all())
    assert bool(act.any()) and bool((option != running).any())


@pytest.mark.parametrize("temperature", [None, 0.5])
@pytest.mark.parametrize("cls", [OptionsController, InterruptionController])
def test_rollout_never_acts_outside_an_initiation_set(cls, temperature):
    heads, sub = rollout_case(4, temperature)
    ctrl = cls(heads, sub, seed=1)
    env = TransformedEnv(
        WindyGridEnv(64, instances=WindyInstances.fixed(0.5, "north"), seed=2), ctrl.primer()
    )
    td = env.rollout(60, ctrl, break_when_any_done=False)
    cells, opt = td[keys.CELL].reshape(-1), td[keys.OPTION].reshape(-1)
    check_initiation(cells, td[keys.RUNNING_OPTION].reshape(-1), opt, sub.init)
    assert bool((opt < 0).any())  # cell 21 is visited: the averaging fallback acted


def test_gymnasium_policy_never_acts_outside_an_initiation_set():
    heads, sub = rollout_case(5, temperature=0.5)
    pol = GymnasiumPolicy(InterruptionController(heads, sub, seed=3), width=W)
    env = gym.make("taskvar/WindyGrid-v0")
    cells, running, options = [], [], []
    for episode in range(4):
        obs, info = env.reset(seed=7 if episode == 0 else None)
        pol.reset()
        done = False
        while not done:
            running.append(pol.state)
            cells.append(info["cell"][0] * W + info["cell"][1])
            obs, _, term, trunc, info = env.step(pol(obs, info))
            options.append(pol.trace["option"])
            done = term or trunc
    t = lambda x: torch.tensor(x, dtype=torch.int64)  # noqa: E731
    check_initiation(t(cells), t(running), t(options), sub.init)


def test_hierarchy_descends_only_to_startable_components():
    # root "task" (startable everywhere, acts by Q_avg) over the three options of rollout_case
    heads3, sub3 = rollout_case(6)
    g = torch.Generator().manual_seed(6)
    names = ("task", *NAMES)
    q = torch.cat(
        [heads3.heads["averaging"].module.table.unsqueeze(1), heads3.heads["options"].module.table],
        1,
    )
    rob = torch.randint(-3, 3, (S, 4, A), generator=g).double()
    heads = table_heads(names, options=q, robustness=rob)
    init = torch.cat([torch.ones(S, 1, dtype=torch.bool), sub3.init], 1)
    beta = torch.cat([torch.zeros(S, 1, dtype=torch.bool), sub3.beta], 1)
    sub = TableSubtasks(names, init, beta)
    tree = Hierarchy(root="task", children={"task": NAMES})
    ctrl = HierarchyController(heads, tree, tau=0.0, subtasks=sub)
    Z = 5
    cells = torch.arange(S).repeat_interleave(Z)
    running = torch.arange(Z).repeat(S) - 1
    td = ctrl(td_of(cells, running))
    opt = td[keys.OPTION]
    descended = opt != 0  # a component acts: control descended to it, or it kept control
    kept = descended & (opt == running) & ~beta[cells, opt]
    assert bool(init[cells[descended & ~kept], opt[descended & ~kept]].all())
    assert bool((descended & ~kept).any())
    chain = WindyOracle().controller_chain(ctrl)  # the oracle's search honours them too
    assert torch.equal(opt, chain["decision"].reshape(S * Z, 4).argmax(-1))
    assert torch.equal(td[keys.INTERRUPTED], chain["fires"].reshape(-1))


def test_subtasks_initiable_everywhere_skip_the_mask_and_its_fallback():
    """Wargus options start anywhere (``initiable_everywhere``): no mask is read and the option
    controllers need no averaging head; windy's and Taxi's initiation sets are read."""
    from taskvar_torch.controllers.base import defines_initiation
    from taskvar_torch.families.taxi.subtasks import TaxiSubtasks
    from taskvar_torch.families.wargus.subtasks import WargusSubtasks

    wargus = WargusSubtasks()
    td = TensorDict({"item_seen": torch.zeros(5, dtype=torch.bool)}, [5])
    assert bool(wargus.initiation(td).all())  # the declaration holds
    assert not defines_initiation(wargus) and defines_initiation(TaxiSubtasks())
    assert not defines_initiation(None)
