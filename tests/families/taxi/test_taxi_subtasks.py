"""TaxiSubtasks: initiation, termination and subtask rewards on hand-checked Taxi-v4 states."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from taskvar_torch import keys
from taskvar_torch.families.taxi.dynamics import IN_TAXI, NUM_STATES, TaxiModel, decode, encode
from taskvar_torch.families.taxi.subtasks import TaxiSubtasks

R, G, Y, B = 0, 1, 2, 3
TO_R, TO_G, TO_Y, TO_B, PICKUP, DROPOFF = range(6)


def _td(cells, next_cells=None, reward=None) -> TensorDict:
    cells = torch.as_tensor(cells)
    td = TensorDict({keys.CELL: cells}, batch_size=cells.shape)
    if next_cells is not None:
        nxt = torch.as_tensor(next_cells)
        td.set(
            keys.NEXT,
            TensorDict(
                {
                    keys.CELL: nxt,
                    keys.REWARD: torch.as_tensor(reward, dtype=torch.float32).unsqueeze(-1),
                },
                batch_size=nxt.shape,
            ),
        )
    return td


def test_initiation_on_hand_checked_states():
    sub = TaxiSubtasks()
    cells = [
        encode(0, 0, R, G),  # at R, passenger waiting at R: pickup, navigate elsewhere
        encode(2, 2, R, G),  # centre, passenger at R: navigation only
        encode(0, 4, IN_TAXI, G),  # at G, aboard, destination G: dropoff
        encode(0, 0, IN_TAXI, G),  # at R, aboard, destination G: no dropoff
        encode(4, 3, Y, B),  # at B, passenger waiting at Y: no pickup
        encode(4, 3, B, B),  # delivered at B: nothing
    ]
    got = TaxiSubtasks().initiation(_td(cells)).tolist()
    assert got == [
        [False, True, True, True, True, False],
        [True, True, True, True, False, False],
        [True, False, True, True, False, True],
        [False, True, True, True, False, False],
        [True, True, True, False, False, False],
        [False] * 6,
    ]
    assert sub.startable(_td(cells)).tolist() == got


def test_termination_on_hand_checked_states():
    cells = [encode(0, 4, IN_TAXI, R), encode(2, 2, G, R), encode(4, 0, Y, Y), encode(4, 3, B, R)]
    got = TaxiSubtasks().termination(_td(cells)).tolist()
    assert got == [
        [False, True, False, False, True, False],  # at G, aboard: to_G and pickup done
        [False] * 6,
        [True] * 6,  # delivered at Y: every option ends with the episode
        [False, False, False, True, False, False],  # at B, passenger waiting at B (dest R)
    ]


def test_every_live_state_has_an_initiable_option_and_none_terminates_where_it_starts():
    sub = TaxiSubtasks()
    td = _td(torch.arange(NUM_STATES))
    init, beta = sub.initiation(td), sub.termination(td)
    _, _, pas, dest = decode(torch.arange(NUM_STATES))
    live = pas != dest
    assert bool(init[live].any(-1).all()) and not bool(init[~live].any())
    assert not bool((init & beta).any())  # startable == initiation


def test_rewards_navigation_minus_one_pickup_dropoff_the_env_reward():
    sub = TaxiSubtasks(end_penalty=100.0)
    s = [encode(1, 0, R, G), encode(0, 0, R, G), encode(0, 4, IN_TAXI, G), encode(0, 0, IN_TAXI, G)]
    s2 = [
        encode(0, 0, R, G),
        encode(0, 0, IN_TAXI, G),
        encode(0, 4, G, G),
        encode(0, 0, IN_TAXI, G),
    ]
    env_r = [-1.0, -1.0, 20.0, -10.0]  # move north to R, pickup, delivery at G, illegal dropoff
    r = sub.reward(_td(s, s2, env_r)).tolist()
    assert r[0] == [-1.0, -1.0, -1.0, -1.0, -1.0, -1.0]
    assert r[1] == [-1.0] * 6
    # delivering at G ends the episode: at G itself to_G arrived; the others never will
    assert r[2] == [-101.0, -1.0, -101.0, -101.0, 20.0, 20.0]
    assert r[3] == [-1.0] * 4 + [-10.0, -10.0]


def test_batched_equals_a_loop_over_single_states():
    sub = TaxiSubtasks()
    model = TaxiModel()
    g = torch.Generator().manual_seed(0)
    cells = torch.randint(0, NUM_STATES, (4, 5), generator=g)
    acts = torch.randint(0, 6, (4, 5), generator=g)
    nxt = model.next[cells, acts, 0]
    rew = model.reward[cells, acts]
    td = _td(cells, nxt, rew)
    for fn in (sub.initiation, sub.termination, sub.reward):
        out = fn(td)
        assert out.shape == (4, 5, 6)
        for i in range(4):
            for j in range(5):
                one = _td(cells[i, j : j + 1], nxt[i, j : j + 1], rew[i, j : j + 1])
                assert torch.equal(fn(one)[0], out[i, j])


def test_negative_end_penalty_is_refused():
    with pytest.raises(ValueError, match="end_penalty"):
        TaxiSubtasks(end_penalty=-1.0)
