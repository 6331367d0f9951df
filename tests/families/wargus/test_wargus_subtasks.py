"""Wargus capabilities (paper §3.5.2): termination, subtask and robustness rewards."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from taskvar_torch import keys
from taskvar_torch.families.wargus import dynamics as wargus
from taskvar_torch.families.wargus.env import WargusEnv
from taskvar_torch.families.wargus.subtasks import WargusSubtasks

torch.set_num_threads(1)

TG, FE, TGFE = 0, 1, 2


def _td(rows: list[tuple]) -> TensorDict:
    """Transitions from rows ``(item_seen, patrol_seen, item_seen', patrol_seen', picked', destroyed)``.

    The event ``item_lost'`` is derived as the env emits it (``wargus.item_lost``); no event at s.
    """
    t = torch.tensor(rows, dtype=torch.int64)  # (B, 6)
    B = t.shape[0]
    return TensorDict(
        {
            wargus.ITEM_SEEN: t[:, 0].bool(),
            wargus.PATROL_SEEN: t[:, 1].bool(),
            wargus.PICKED: torch.zeros(B, dtype=torch.int64),
            wargus.ITEM_LOST: torch.zeros(B, dtype=torch.bool),
            keys.NEXT: {
                wargus.ITEM_SEEN: t[:, 2].bool(),
                wargus.PATROL_SEEN: t[:, 3].bool(),
                wargus.PICKED: t[:, 4],
                wargus.ITEM_LOST: wargus.item_lost(t[:, 0].bool(), t[:, 2].bool(), t[:, 4]),
                keys.TERMINATED: t[:, 5:6].bool(),
            },
        },
        batch_size=[B],
    )


def test_names_hierarchy_and_initiation_anywhere():
    sub = WargusSubtasks()
    assert sub.names == ("TG", "FE", "TG+FE")
    h = sub.hierarchy
    assert h.root == "TG+FE" and h.components("TG+FE") == ("TG", "FE")
    assert h.is_leaf("TG") and h.is_leaf("FE") and h.parent("FE") == "TG+FE"
    td = _td([(0, 0, 0, 0, 0, 0), (1, 1, 1, 1, 0, 0)])
    init = sub.initiation(td)
    assert init.shape == (2, 3) and init.dtype == torch.bool and init.all()


def test_termination_on_events():
    sub = WargusSubtasks()
    td = _td(
        [
            (0, 0, 1, 0, 0, 0),  # comes into sight of the item, no patrol: TG runs, FE ends
            (1, 0, 1, 1, 0, 0),  # patrol seen: TG ends, FE runs
            (1, 0, 0, 0, 0, 0),  # loses sight of the item: TG ends
            (0, 0, 1, 0, 1, 0),  # just picked an item (new one in sight): TG ends
            (1, 0, 0, 0, 1, 0),  # just picked an item (new one out of sight): TG ends
            (
                0,
                0,
                0,
                0,
                0,
                0,
            ),  # item out of sight, as before: no event, TG runs (seeks by bearing)
            (1, 0, 1, 0, 0, 0),  # item still in sight: TG runs
            (0, 1, 0, 1, 0, 0),  # patrol still in sight, item unseen: TG ends, FE runs
        ]
    )
    assert td[keys.NEXT, wargus.ITEM_LOST].tolist() == [0, 0, 1, 0, 0, 0, 0, 0]
    beta = sub.termination(td[keys.NEXT])
    assert beta.dtype == torch.bool and beta.shape == (8, 3)
    assert beta[:, TG].tolist() == [0, 1, 1, 1, 1, 0, 0, 1]
    assert beta[:, FE].tolist() == [1, 0, 1, 1, 1, 1, 1, 0]
    assert not beta[:, TGFE].any()  # the root is the whole task
    # TG's termination reads the event, not the state: the same next state (item unseen, no
    # patrol) ends TG only when sight of the item was just lost
    assert beta[2, TG] and not beta[5, TG]
    assert torch.equal(td[keys.NEXT, wargus.ITEM_SEEN][[2, 5]], torch.tensor([False, False]))


def test_tg_started_where_the_item_is_unseen_runs_until_an_event():
    # follow the item's bearing (TG's intended policy) from starts mostly out of the item's sight:
    # TG must not terminate before the first event (patrol seen, item picked, item lost)
    env = WargusEnv(64, seed=1, size=32, sight=4, shoot_range=1, hit_prob=0.0, horizon=100)
    sub = WargusSubtasks()
    td = env.reset()
    start_unseen = ~td[wargus.ITEM_SEEN]
    assert start_unseen.sum() > 40
    running = torch.ones(64, dtype=torch.bool)  # TG started at every start state
    steps_unseen = torch.zeros(64, dtype=torch.int64)
    ended_by = torch.zeros(64, dtype=torch.int64)  # 1 pick, 2 patrol, 3 lost
    for _ in range(60):
        bearing = td[keys.OBSERVATION][:, wargus.OBS_ITEM_BEARING]
        td[keys.ACTION] = bearing.argmax(-1)  # move towards the item's bearing
        out, td = env.step_and_maybe_reset(td)
        nxt = out[keys.NEXT]
        beta_tg = sub.termination(nxt)[:, TG]
        event = nxt[wargus.PATROL_SEEN] | nxt[wargus.ITEM_LOST] | (nxt[wargus.PICKED] > 0)
        assert torch.equal(beta_tg, event)
        steps_unseen += (running & ~nxt[wargus.ITEM_SEEN]).long()
        kind = torch.where(nxt[wargus.PICKED] > 0, 1, torch.where(nxt[wargus.PATROL_SEEN], 2, 3))
        ended_by = torch.where(running & beta_tg, kind, ended_by)
        running = running & ~beta_tg & ~nxt[keys.DONE].squeeze(-1)
    assert not nxt[wargus.ITEM_LOST][ended_by == 0].any()
    assert not (ended_by == 3).any()  # following the bearing never loses sight of the item
    # TG ran for several steps where the item was unseen, and mostly reached the item
    assert (steps_unseen[start_unseen] >= 3).float().mean() > 0.8
    assert (ended_by[start_unseen] == 1).sum() > (ended_by[start_unseen] == 2).sum()


def test_subtask_rewards_on_hand_built_transitions():
    sub = WargusSubtasks(destruction_penalty=10.0)
    td = _td(
        [
            (1, 0, 1, 0, 1, 0),  # pickup, no patrol
            (0, 1, 0, 1, 0, 0),  # stays in the patrol's sight
            (0, 0, 0, 1, 0, 0),  # enters the patrol's sight
            (0, 1, 0, 0, 0, 0),  # escapes
            (0, 0, 0, 0, 0, 0),  # nothing happens
            (1, 1, 1, 1, 1, 1),  # picks an item and is destroyed on the same step
        ]
    )
    r = sub.reward(td)
    assert r.dtype == torch.float32 and r.shape == (6, 3)
    assert r[:, TG].tolist() == [1, 0, 0, 0, 0, 1]
    assert r[:, FE].tolist() == [0, -1, -1, 1, 0, -11]
    # TG+FE is the full task: its subtask reward is the environment reward (items picked)
    assert r[:, TGFE].tolist() == [1, 0, 0, 0, 0, 1]
    summed = WargusSubtasks(destruction_penalty=10.0, composed_reward="sum").reward(td)
    assert torch.equal(summed[:, TGFE], r[:, TG] + r[:, FE])
    with pytest.raises(ValueError, match="composed_reward must be one of"):
        WargusSubtasks(composed_reward="mean")


def test_startable_and_no_conflict_read_the_patrols_sight():
    sub = WargusSubtasks()
    td = _td([(0, 0, 0, 0, 0, 0), (0, 1, 0, 1, 0, 0), (1, 0, 1, 0, 0, 0)])
    st = sub.startable(td)
    # TG can take control where no patrol is seen, FE only where one is, the root anywhere
    assert st[:, TG].tolist() == [True, False, True]
    assert st[:, FE].tolist() == [False, True, False]
    assert st[:, TGFE].all()
    assert sub.no_conflict(td).tolist() == [True, False, True]


def test_robustness_rewards_on_hand_built_transitions():
    sub = WargusSubtasks()
    td = _td(
        [
            (0, 0, 1, 0, 0, 0),  # comes into sight of the item: +1
            (1, 0, 1, 0, 0, 0),  # stays where the item is seen: +1
            (1, 0, 0, 0, 0, 0),  # leaves the area where the item is seen: -1
            (0, 0, 0, 0, 0, 0),  # far from the item: 0
            (1, 0, 0, 0, 1, 0),  # picks the item, the new one is out of sight: +1, not -1
            (0, 1, 0, 1, 0, 0),  # within the patrol's sight: FE -1
            (0, 0, 0, 1, 0, 0),  # enters the patrol's sight: FE -1
            (1, 1, 1, 0, 0, 0),  # escapes it: FE +1 once
            (1, 1, 1, 1, 0, 1),  # destroyed in sight: FE -1, TG +1
        ]
    )
    rr = sub.robustness_reward(td)
    assert rr[:, TG].tolist() == [1, 1, -1, 0, 1, 0, 0, 1, 1]
    assert torch.equal(rr[:, TG] == -1, td[keys.NEXT, wargus.ITEM_LOST])  # -1 exactly on the event
    assert rr[:, FE].tolist() == [0, 0, 0, 0, 0, -1, -1, 1, -1]
    assert torch.equal(rr[:, TGFE], rr[:, TG] + rr[:, FE])
    pen = WargusSubtasks(robustness_destruction_penalty=10.0).robustness_reward(td)
    assert pen[-1, FE] == -11 and torch.equal(pen[:-1], rr[:-1])


def test_robustness_ranks_item_seen_and_patrol_sight_as_intended():
    # on real transitions: TG's robustness reward is positive where the item is seen, FE's negative
    # inside the patrol's sight; the sustained values set the scale of tau (docs/hierarchy-critics.md)
    env = WargusEnv(32, seed=0, size=12, sight=5, shoot_range=2, hit_prob=0.3, horizon=60)
    td = env.rollout(120, break_when_any_done=False)
    rr = WargusSubtasks().robustness_reward(td)
    seen = td[keys.NEXT, wargus.ITEM_SEEN]
    in_sight = td[keys.NEXT, wargus.PATROL_SEEN]
    assert seen.any() and (~seen).any() and in_sight.any() and (~in_sight).any()
    unseen = ~seen & (td[keys.NEXT, wargus.PICKED] == 0)  # a pickup counts as reaching the item
    assert (rr[..., TG][seen] == 1).all() and (rr[..., TG][unseen] <= 0).all()
    assert (rr[..., FE][in_sight] == -1).all() and (rr[..., FE][~in_sight] >= 0).all()
    # "-1 when it leaves the area where the item is seen" is the env's event item_lost
    assert torch.equal(rr[..., TG] == -1, td[keys.NEXT, wargus.ITEM_LOST])
    assert td[keys.NEXT, wargus.ITEM_LOST].any()


def test_batched_equals_per_env_loop():
    env = WargusEnv(
        8,
        seed=3,
        size=10,
        num_patrols=2,
        num_items=2,
        sight=4,
        shoot_range=2,
        hit_prob=0.4,
        horizon=30,
    )
    td = env.rollout(80, break_when_any_done=False)  # (8, 80)
    assert td[keys.NEXT, keys.TERMINATED].any()
    sub = WargusSubtasks()
    out = {
        "reward": sub.reward(td),
        "robustness": sub.robustness_reward(td),
        "termination": sub.termination(td[keys.NEXT]),
        "initiation": sub.initiation(td),
    }
    for name, val in out.items():
        assert val.shape == (8, 80, 3), name
    for i in range(8):
        assert torch.equal(sub.reward(td[i]), out["reward"][i])
        assert torch.equal(sub.robustness_reward(td[i]), out["robustness"][i])
        assert torch.equal(sub.termination(td[i][keys.NEXT]), out["termination"][i])
    for i, t in [(0, 0), (3, 17), (7, 79)]:  # single transitions (batch shape ())
        one = td[i, t]
        assert torch.equal(sub.reward(one), out["reward"][i, t])
        assert torch.equal(sub.robustness_reward(one), out["robustness"][i, t])
        assert torch.equal(sub.termination(one[keys.NEXT]), out["termination"][i, t])
        assert torch.equal(sub.initiation(one), out["initiation"][i, t])


def test_invalid_penalty_raises():
    with pytest.raises(ValueError, match="destruction_penalty"):
        WargusSubtasks(destruction_penalty=-1.0)
