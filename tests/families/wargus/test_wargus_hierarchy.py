"""Algorithm 2 on hand-built Wargus states, honouring the options' termination (paper §3.4.4,
§3.5.2), the robustness target's horizon, and the calibration of the thresholds.

Heads are tables over a situation index (``cell``); the Wargus state keys the subtasks read
(``item_seen``, ``patrol_seen``, ``item_lost``, ``picked``) are set by hand per situation.
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from taskvar_torch import keys
from taskvar_torch.controllers import HierarchyController, make_controller
from taskvar_torch.families.wargus import dynamics as wargus
from taskvar_torch.families.wargus.subtasks import WargusSubtasks
from taskvar_torch.heads.relabel import Transitions
from taskvar_torch.heads.robustness import (
    RobustnessCalibration,
    calibrate_robustness,
    robustness_loss,
)
from taskvar_torch.oracle import table_heads

SUB = WargusSubtasks()
NAMES = SUB.names  # ("TG", "FE", "TG+FE")
TG, FE, ROOT = (NAMES.index(n) for n in ("TG", "FE", "TG+FE"))
A = 8
TAU = 2.0
# each option's greedy action: TG -> 0, FE -> 4, TG+FE's own head -> 2, the averaging head -> 6
OWN = {TG: 0, FE: 4, ROOT: 2}
AVG_ACTION = 6


def situations(rows: list[dict]) -> tuple[object, TensorDict]:
    """Table heads and the state tensordict of hand-built situations.

    Each row: ``item_seen``, ``patrol_seen`` (bools) and ``R``: {option index: robustness under
    every action}.
    """
    S = len(rows)
    q = torch.zeros(S, 3, A, dtype=torch.float64)
    for o, a in OWN.items():
        q[:, o, a] = 1.0
    q_avg = torch.zeros(S, A, dtype=torch.float64)
    q_avg[:, AVG_ACTION] = 1.0
    rob = torch.zeros(S, 3, A, dtype=torch.float64)
    for s, row in enumerate(rows):
        for o, v in row["R"].items():
            rob[s, o] = v
    heads = table_heads(NAMES, options=q, robustness=rob, averaging=q_avg)
    td = TensorDict(
        {
            keys.CELL: torch.arange(S),
            wargus.ITEM_SEEN: torch.tensor([r["item_seen"] for r in rows]),
            wargus.PATROL_SEEN: torch.tensor([r["patrol_seen"] for r in rows]),
            wargus.ITEM_LOST: torch.zeros(S, dtype=torch.bool),
            wargus.PICKED: torch.zeros(S, dtype=torch.int64),
        },
        batch_size=[S],
    )
    return heads, td


ROWS = [
    # 0: item in sight, patrol far (unseen): the root is robust under pi^avg
    {"item_seen": True, "patrol_seen": False, "R": {ROOT: 5.0, TG: 4.0, FE: 0.0}},
    # 1: patrol in sight and close: the root is not robust; raw R would pick TG (3 > -2)
    {"item_seen": True, "patrol_seen": True, "R": {ROOT: -3.0, TG: 3.0, FE: -2.0}},
    # 2: item out of sight, no patrol, the root below tau: TG seeks
    {"item_seen": False, "patrol_seen": False, "R": {ROOT: 1.0, TG: 0.5, FE: 0.0}},
]


def decide(ctrl: HierarchyController, td: TensorDict, running: list[int]) -> list[str]:
    td = td.clone()
    td.set(keys.RUNNING_OPTION, torch.tensor(running))
    out = ctrl(td)
    return [NAMES[o] for o in out[keys.OPTION].tolist()]


def controller(heads, terminate: bool = True, **kw) -> HierarchyController:
    return make_controller(
        "hierarchy",
        heads,
        SUB,
        hierarchy=SUB.hierarchy,
        tau=TAU,
        root_policy="averaging",
        terminate=terminate,
        **kw,
    )


def test_root_keeps_control_where_the_item_is_in_sight_and_the_patrol_far():
    heads, td = situations(ROWS)
    ctrl = controller(heads)
    assert decide(ctrl, td[:1], [-1]) == ["TG+FE"]  # episode start
    assert decide(ctrl, td[:1], [TG]) == ["TG+FE"]  # the parent regains control (line 3)
    out = ctrl(td[:1].clone().set(keys.RUNNING_OPTION, torch.tensor([-1])))
    assert out[keys.ACTION].item() == AVG_ACTION  # the root acts by the averaging policy


def test_fe_takes_control_where_the_patrol_is_in_sight_and_close():
    heads, td = situations(ROWS)
    # honouring termination: TG cannot run while a patrol is in sight, FE takes control
    assert decide(controller(heads), td[1:2], [-1]) == ["FE"]
    assert decide(controller(heads, descent="normalised"), td[1:2], [-1]) == ["FE"]
    # the paper's literal search picks the raw argmax R, here TG
    assert decide(controller(heads, terminate=False), td[1:2], [-1]) == ["TG"]


def test_tg_terminating_on_patrol_sight_hands_control_back_up():
    heads, td = situations(ROWS)
    # TG was running; the patrol comes into sight (beta_TG = 1), the root is not robust: control
    # returns to the root, which descends to the component that can run, FE
    out = controller(heads)(td[1:2].clone().set(keys.RUNNING_OPTION, torch.tensor([TG])))
    assert NAMES[out[keys.OPTION].item()] == "FE"
    assert not out[keys.INTERRUPTED].item()  # a termination, not an interruption
    # without termination the leaf TG keeps acting (its parent is not robust)
    assert decide(controller(heads, terminate=False), td[1:2], [TG]) == ["TG"]
    # FE escaped (no patrol in sight): FE terminates, control goes up, the root descends to TG
    assert decide(controller(heads), td[2:3], [FE]) == ["TG"]
    assert decide(controller(heads, terminate=False), td[2:3], [FE]) == ["FE"]


def test_termination_aware_kernels_agree_with_the_scalar_search():
    g = torch.Generator().manual_seed(0)
    S = 600
    rows = [
        {
            "item_seen": bool(torch.rand(1, generator=g) < 0.5),
            "patrol_seen": bool(torch.rand(1, generator=g) < 0.5),
            "R": {o: torch.randint(-3, 4, (A,), generator=g).double() for o in range(3)},
        }
        for _ in range(S)
    ]
    heads, td = situations(rows)
    running = torch.randint(-1, 3, (S,), generator=g)
    cal = RobustnessCalibration(torch.tensor([0.5, -1.0, 1.0]), torch.tensor([2.0, 0.5, 1.0]))
    for kw in ({}, {"descent": "normalised"}, {"descent": "normalised", "calibration": cal}):
        ctrl = controller(heads, **kw)
        batched = ctrl(td.clone().set(keys.RUNNING_OPTION, running))
        for i in range(0, S, 5):
            inputs = {
                k: td[i : i + 1].get(k)
                for k in (keys.CELL, wargus.ITEM_SEEN, wargus.PATROL_SEEN, wargus.ITEM_LOST)
            }
            inputs[wargus.PICKED] = td[i : i + 1].get(wargus.PICKED)
            beta = bool(SUB.termination(td[i : i + 1])[0, running[i].clamp(min=0)])
            one = ctrl.act_one(inputs, int(running[i]), beta and int(running[i]) >= 0)
            assert one["option"] == batched[keys.OPTION][i].item(), (kw, i)
            assert one["action"] == batched[keys.ACTION][i].item(), (kw, i)
            assert one[keys.INTERRUPTED] == batched[keys.INTERRUPTED][i].item(), (kw, i)


def test_robustness_target_stops_at_the_options_termination():
    B, O = 4, 3  # noqa: E741
    batch = Transitions(
        observation=torch.zeros(B, 2),
        next_observation=torch.zeros(B, 2),
        action=torch.zeros(B, dtype=torch.int64),
        reward=torch.zeros(B),
        terminated=torch.zeros(B),
        initiation=torch.ones(B, O, dtype=torch.bool),
        initiation_next=torch.ones(B, O, dtype=torch.bool),
        beta_next=torch.tensor([[1.0, 0.0, 0.0]] * B),  # option 0 terminates at s'
        subtask_reward=torch.zeros(B, O),
        robustness_reward=torch.zeros(B, O),
    )
    r = torch.zeros(B, O, A)
    r_next = torch.full((B, O, A), 5.0)
    nxt = torch.zeros(B, O, dtype=torch.int64)
    mask = torch.tensor([[True, False, False]] * B)  # option 0's critic only

    def loss(until: bool) -> float:
        return float(robustness_loss(r, r_next, r_next, mask, batch, 0.9, True, nxt, until))

    assert loss(until=True) == 0.0  # target = rr = 0: nothing past beta_0 is bootstrapped
    assert loss(until=False) == pytest.approx((0.9 * 5.0) ** 2)
    mask = torch.tensor([[False, True, False]] * B)  # option 1 does not terminate: bootstraps
    assert float(robustness_loss(r, r_next, r_next, mask, batch, 0.9, True, nxt, True)) > 0


def test_calibration_keeps_the_root_in_control_on_the_stated_share_of_no_conflict_states():
    g = torch.Generator().manual_seed(1)
    B = 4000
    r = torch.randn(B, 3, generator=g) * torch.tensor([1.0, 3.0, 2.0]) + torch.tensor([0, -2, 4])
    patrol = torch.rand(B, generator=g) < 0.3
    startable = torch.stack([~patrol, patrol, torch.ones_like(patrol)], -1)
    composed = torch.tensor([False, False, True])
    cal = calibrate_robustness(r, startable, ~patrol, composed, keep_share=0.9, default_tau=2.0)
    keeps = (r[~patrol, ROOT] > cal.tau[ROOT]).float().mean()
    assert float(keeps) == pytest.approx(0.9, abs=0.01)
    assert float(cal.scale[FE]) == pytest.approx(float(r[patrol, FE].std()), rel=1e-5)
    # a capability with no qualifying state keeps the default threshold
    none = calibrate_robustness(r, startable & False, ~patrol, composed, 0.9, 2.0)
    assert none.tau.tolist() == [2.0, 2.0, 2.0]
    with pytest.raises(ValueError, match="keep_share"):
        calibrate_robustness(r, startable, ~patrol, composed, 1.0, 2.0)
