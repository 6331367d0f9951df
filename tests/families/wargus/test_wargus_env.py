"""Wargus family (paper §3.5): specs, Gymnasium API, determinism, behaviours, errors."""

from __future__ import annotations

import math

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.envs.registration import EnvSpec
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from taskvar_torch import keys
from taskvar_torch.families.wargus import dynamics as wargus
from taskvar_torch.families.wargus.dynamics import (
    WargusConfig,
    WargusInstances,
    WargusModel,
    WargusState,
)
from taskvar_torch.families.wargus.env import WargusEnv
from taskvar_torch.families.wargus.gym_env import WargusGymEnv

torch.set_num_threads(1)

# a small, eventful family: several patrols and items, resets every few dozen steps
SMALL = dict(
    size=10,
    num_patrols=2,
    num_items=2,
    sight=4,
    shoot_range=2,
    hit_prob=0.5,
    patrol_speed=0.8,
    horizon=40,
)
NOOP = 8


def _state(agent, patrols, items, t=0) -> WargusState:
    """A batch-of-one state from plain lists."""
    return WargusState(
        torch.tensor([agent], dtype=torch.int64),
        torch.tensor([patrols], dtype=torch.int64),
        torch.tensor([items], dtype=torch.int64),
        torch.tensor([t], dtype=torch.int64),
    )


def _batch(state: WargusState, n: int) -> WargusState:
    return WargusState(*(x.expand(n, *x.shape[1:]).clone() for x in state))


def _keys(n: int, offset: int = 0) -> torch.Tensor:
    return wargus.instance_key(torch.arange(n, dtype=torch.int64) + offset)


# TorchRL env, driven with fixed actions; record every step's outcome and the post-reset state
_FIELDS = (
    keys.OBSERVATION,
    keys.REWARD,
    keys.TERMINATED,
    keys.TRUNCATED,
    wargus.AGENT_POS,
    wargus.ITEM_SEEN,
    wargus.PATROL_SEEN,
    wargus.PICKED,
    wargus.ITEM_LOST,
    (keys.INSTANCE, wargus.INSTANCE_SEED),
)


def _run(env: WargusEnv, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor]:
    """Step ``env`` with ``actions`` (T, N); returns the stacked ``next`` data and root observations."""
    td = env.reset()
    nxt, root = [], [td[keys.OBSERVATION]]
    for a in actions:
        td[keys.ACTION] = a
        out, td = env.step_and_maybe_reset(td)
        nxt.append(out[keys.NEXT].select(*_FIELDS))
        root.append(td[keys.OBSERVATION])
    return torch.stack(nxt), torch.stack(root)


def _actions(T: int, N: int, seed: int, num_actions: int = 8) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, num_actions, (T, N), generator=g)


# --------------------------------------------------------------------------------- specs and API


@pytest.mark.parametrize("num_envs", [1, 64])
def test_check_env_specs_without_noop_on_a_small_grid(num_envs):  # default: conformance suite
    check_env_specs(WargusEnv(num_envs, seed=2, noop=True, **SMALL))


def test_observation_never_contains_the_instance():
    env = WargusEnv(4, seed=0)
    td = env.reset()
    assert td[keys.OBSERVATION].shape == (4, wargus.OBS_DIM)
    assert set(td[keys.INSTANCE].keys()) == {
        wargus.INSTANCE_SEED,
        wargus.PATROL_POS,
        wargus.ITEM_POS,
    }
    # two instances whose visible state agrees give the same observation
    m = env.model
    a = WargusState(
        td[wargus.AGENT_POS],
        td[keys.INSTANCE, wargus.PATROL_POS],
        td[keys.INSTANCE, wargus.ITEM_POS],
        torch.zeros(4, dtype=torch.int64),
    )
    assert torch.equal(wargus.observe(m, a)[0], td[keys.OBSERVATION])
    g = WargusGymEnv()
    o1, i1 = g.reset(seed=0, options={"instance": {"seed": 1}})
    assert i1["instance"]["seed"] == 1 and o1.shape == (wargus.OBS_DIM,)


def _gym_make(**kwargs):
    return gymnasium.make(EnvSpec(id="WargusTest-v0", entry_point=WargusGymEnv), **kwargs)


def test_render_modes_return_right_type_and_shape():
    env = WargusEnv(3, seed=0, num_patrols=2)
    env.reset()
    text = env.render(2, "ansi")
    assert isinstance(text, str)
    lines = text.rstrip("\n").split("\n")
    assert len(lines) == 1 + 32 and all(len(ln) == 2 * 32 - 1 for ln in lines[1:])
    assert text.count("A") >= 1 and sum(ln.count("P") for ln in lines[1:]) >= 1
    img = env.render(0, "rgb_array")
    assert isinstance(img, np.ndarray) and img.dtype == np.uint8 and img.shape == (256, 256, 3)
    assert len(np.unique(img.reshape(-1, 3), axis=0)) >= 5  # agent, patrol, item, radii, background
    with pytest.raises(ValueError, match="render mode"):
        env.render(0, "human")
    for mode, kind in (("ansi", str), ("rgb_array", np.ndarray)):
        g = WargusGymEnv(render_mode=mode, size=64, num_patrols=3, horizon=1000)
        g.reset(seed=0)
        g.step(0)
        out = g.render()
        assert isinstance(out, kind)
        if kind is np.ndarray:
            assert out.shape == (256, 256, 3) and out.dtype == np.uint8
    plain = WargusGymEnv()
    plain.reset(seed=0)
    with pytest.warns(UserWarning, match="render_mode"):
        assert plain.render() is None


# ------------------------------------------------------------------------ determinism and seeding


@pytest.mark.slow
def test_batched_equals_looped_for_1000_random_steps():
    N, T = 4, 1000
    actions = _actions(T, N, seed=5)
    batched, broot = _run(WargusEnv(N, seed=11, **SMALL), actions)
    assert batched[keys.TERMINATED].any() and batched[keys.TRUNCATED].any()
    assert batched[keys.REWARD].sum() > 0
    for i in range(N):
        single, sroot = _run(WargusEnv(1, seed=11, index_offset=i, **SMALL), actions[:, i : i + 1])
        assert (single == batched[:, i : i + 1]).all(), f"sub-env {i} differs"
        assert torch.equal(sroot, broot[:, i : i + 1])


def test_gym_and_torchrl_bit_identical():
    cfg = dict(SMALL, noop=True)
    T, seed = 400, 17
    actions = _actions(T, 1, seed=9, num_actions=9)
    tr, troot = _run(WargusEnv(1, seed=seed, **cfg), actions)
    g = WargusGymEnv(**cfg)
    obs, info = g.reset(seed=seed)
    assert np.array_equal(obs, troot[0, 0].numpy())
    for t in range(T):
        obs, r, term, trunc, info = g.step(int(actions[t, 0]))
        assert np.array_equal(obs, tr[keys.OBSERVATION][t, 0].numpy()), t
        assert r == float(tr[keys.REWARD][t, 0, 0])
        assert term == bool(tr[keys.TERMINATED][t, 0, 0]) and trunc == bool(
            tr[keys.TRUNCATED][t, 0, 0]
        )
        assert info["instance"]["seed"] == int(tr[keys.INSTANCE, wargus.INSTANCE_SEED][t, 0])
        assert info[wargus.AGENT_POS] == tuple(tr[wargus.AGENT_POS][t, 0].tolist())
        for k in (wargus.ITEM_SEEN, wargus.PATROL_SEEN, wargus.PICKED, wargus.ITEM_LOST):
            assert info[k] == tr[k][t, 0].item() and type(info[k]) is type(tr[k][t, 0].item()), (
                k,
                t,
            )
        if term or trunc:
            obs, info = g.reset()
            assert np.array_equal(obs, troot[t + 1, 0].numpy()), t
            assert info[wargus.ITEM_LOST] is False and info[wargus.PICKED] == 0
    assert tr[keys.TERMINATED].any() and tr[keys.TRUNCATED].any()
    assert tr[wargus.ITEM_LOST].any() and tr[wargus.PICKED].any()  # the events were exercised


def test_pinned_instance_fixes_the_episode_whatever_the_env_seed():
    a, b = WargusGymEnv(), WargusGymEnv()
    oa, ia = a.reset(seed=1, options={"instance": {"seed": 7}})
    ob, ib = b.reset(seed=2, options={"instance": {"seed": 7}})
    assert ia["instance"]["seed"] == ib["instance"]["seed"] == 7
    assert np.array_equal(oa, ob)
    for act in [0, 1, 2, 3, 4, 5, 6, 7] * 5:
        ra, rb = a.step(act), b.step(act)
        assert np.array_equal(ra[0], rb[0]) and ra[1:4] == rb[1:4]
        if ra[2] or ra[3]:
            break
    oc, _ = a.reset(options={"instance": {"seed": 7}, "start": (3, 4)})
    assert oc[0] == pytest.approx(3 / 31) and oc[1] == pytest.approx(4 / 31)


def test_nominal_instances_cycle_through_fixed_seeds():
    env = WargusEnv(5, seed=123, instances="nominal")
    td = env.reset()
    assert td[keys.INSTANCE, wargus.INSTANCE_SEED].tolist() == list(wargus.NOMINAL_SEEDS)
    # a different env seed plays the same nominal episodes (same agent start, same observation)
    td2 = WargusEnv(5, seed=999, instances="nominal").reset()
    assert torch.equal(td[keys.OBSERVATION], td2[keys.OBSERVATION])
    one = WargusEnv(
        1, seed=0, instances=WargusInstances(seeds=(10, 20, 30)), horizon=2, hit_prob=0.0
    )
    seen = []
    td = one.reset()
    for _ in range(6):
        seen.append(int(td[keys.INSTANCE, wargus.INSTANCE_SEED]))
        td[keys.ACTION] = torch.zeros(1, dtype=torch.int64)
        _, td = one.step_and_maybe_reset(td)
        td[keys.ACTION] = torch.zeros(1, dtype=torch.int64)
        _, td = one.step_and_maybe_reset(td)
    assert seen == [10, 20, 30, 10, 20, 30]
    u = WargusInstances(seeds=(10, 20, 30), order="uniform")
    drawn = u.sample(
        _keys(300), torch.zeros(300, dtype=torch.int64), torch.zeros(300, dtype=torch.int64)
    )
    assert set(drawn.tolist()) == {10, 20, 30}


# ------------------------------------------------------------------------------------- behaviours


def test_patrol_chases_once_it_sees_agent():
    cfg = WargusConfig(size=16, sight=5, shoot_range=1, hit_prob=0.0, patrol_speed=1.0, noop=True)
    m = WargusModel(cfg)
    n = 64  # many instances: a chase is deterministic, whatever the random stream
    s = _batch(_state([8, 8], [[4, 12]], [[0, 0]]), n)
    key = _keys(n)
    noop = torch.full((n,), NOOP)
    path = [(5, 11), (6, 10), (7, 9)]  # shortest 8-connected path towards the agent
    for want in path:
        s, _, destroyed = wargus.step(m, s, noop, key)
        assert (s.patrols[:, 0] == torch.tensor(want)).all(), want
        assert not destroyed.any()
    # the patrol follows a moving agent
    s, _, _ = wargus.step(m, s, torch.full((n,), 2), key)  # agent east to (8, 9)
    assert (s.patrols[:, 0] == torch.tensor([8, 9])).all()
    # out of sight (distance >= sight) it random-walks: all 8 directions occur, chasing is not forced
    far = _batch(_state([8, 8], [[8, 13]], [[0, 0]]), n)
    moved, _, _ = wargus.step(m, far, noop, key)
    deltas = {tuple(d) for d in (moved.patrols[:, 0] - far.patrols[:, 0]).tolist()}
    assert deltas == {d for d in wargus.DELTAS[:8]}


def test_patrol_moves_with_probability_patrol_speed():
    cfg = WargusConfig(size=16, sight=5, shoot_range=1, hit_prob=0.0, patrol_speed=0.8, noop=True)
    m, n = WargusModel(cfg), 4000
    s = _batch(_state([8, 8], [[4, 12]], [[0, 0]]), n)
    nxt, _, _ = wargus.step(m, s, torch.full((n,), NOOP), _keys(n))
    frac = (nxt.patrols != s.patrols).any(-1).float().mean().item()
    assert abs(frac - 0.8) < 4 * math.sqrt(0.8 * 0.2 / n)


def test_patrol_shoots_only_within_range():
    cfg = WargusConfig(size=20, sight=8, shoot_range=5, hit_prob=1.0, patrol_speed=0.0, noop=True)
    m = WargusModel(cfg)
    offsets = (
        [(d, 0) for d in range(1, 11)]
        + [(d, d) for d in range(1, 11)]
        + [(-3, d) for d in range(4, 9)]
    )
    n = len(offsets)
    agent = torch.tensor([[9, 9]] * n)
    patrols = (agent + torch.tensor(offsets)).clamp(0, 19).unsqueeze(1)
    s = WargusState(
        agent, patrols, torch.zeros(n, 1, 2, dtype=torch.int64), torch.zeros(n, dtype=torch.int64)
    )
    _, _, destroyed = wargus.step(m, s, torch.full((n,), NOOP), _keys(n))
    dist = wargus.chebyshev(agent.unsqueeze(1), patrols)[:, 0]
    assert torch.equal(destroyed, dist <= 5)
    assert destroyed.any() and (~destroyed).any()
    # hit_prob: 0 never destroys, 0.5 about half the time
    near = _batch(_state([9, 9], [[9, 12]], [[0, 0]]), 4000)
    never = wargus.step(m, near, torch.full((4000,), NOOP), _keys(4000), hit_prob=0.0)[2]
    assert not never.any()
    half = wargus.step(m, near, torch.full((4000,), NOOP), _keys(4000), hit_prob=0.5)[2]
    assert abs(half.float().mean().item() - 0.5) < 4 * math.sqrt(0.25 / 4000)
    # several patrols in range: each shoots once, any hit destroys
    two = WargusConfig(
        size=20, sight=8, shoot_range=5, hit_prob=0.5, patrol_speed=0.0, num_patrols=2, noop=True
    )
    both = _batch(_state([9, 9], [[9, 12], [12, 9]], [[0, 0]]), 4000)
    d2 = wargus.step(WargusModel(two), both, torch.full((4000,), NOOP), _keys(4000))[2]
    assert abs(d2.float().mean().item() - 0.75) < 4 * math.sqrt(0.75 * 0.25 / 4000)


def test_item_respawns_on_pickup():
    cfg = WargusConfig(size=8, sight=4, shoot_range=1, hit_prob=0.0, num_items=2)
    m, n = WargusModel(cfg), 2000
    s = _batch(_state([5, 5], [[0, 0]], [[5, 6], [1, 1]]), n)
    key = _keys(n)
    nxt, picked, _ = wargus.step(m, s, torch.full((n,), 2), key)  # east onto item 0
    assert (picked == 1).all() and (nxt.agent == torch.tensor([5, 6])).all()
    assert (nxt.items[:, 1] == torch.tensor([1, 1])).all()  # the other item stays
    new = nxt.items[:, 0]
    assert not (new == nxt.agent).all(-1).any()  # never on the agent's cell
    cells = (new[:, 0] * 8 + new[:, 1]).bincount(minlength=64)
    assert cells[5 * 8 + 6] == 0 and (cells.numpy() > 0).sum() == 63  # uniform over the other cells
    again, _, _ = wargus.step(m, s, torch.full((n,), 2), key)
    assert torch.equal(again.items, nxt.items)  # the item process is part of the instance
    # through the env: reward +1 exactly when picked
    env = WargusEnv(16, seed=0, size=6, sight=3, shoot_range=0, hit_prob=0.0, horizon=1000)
    data, _ = _run(env, _actions(300, 16, seed=1))
    assert torch.equal(data[keys.REWARD][..., 0], data[wargus.PICKED].float())
    assert data[wargus.PICKED].sum() > 10


@pytest.mark.slow
def test_item_lost_is_the_event_seen_then_unseen_without_a_pickup():
    # on a long batched rollout with auto-resets: item_lost(s') == seen(s) & ~seen(s') & no pickup,
    # and False on every reset
    env = WargusEnv(8, seed=2, **SMALL)
    td = env.reset()
    assert not td[wargus.ITEM_LOST].any() and td[wargus.ITEM_LOST].dtype == torch.bool
    lost_total = 0
    for a in _actions(600, 8, seed=4):
        td[keys.ACTION] = a
        out, td = env.step_and_maybe_reset(td)
        nxt = out[keys.NEXT]
        want = out[wargus.ITEM_SEEN] & ~nxt[wargus.ITEM_SEEN] & (nxt[wargus.PICKED] == 0)
        assert torch.equal(nxt[wargus.ITEM_LOST], want)
        done = nxt[keys.DONE].squeeze(-1)
        assert not td[wargus.ITEM_LOST][done].any()  # the new episode starts without an event
        assert torch.equal(td[wargus.ITEM_LOST][~done], nxt[wargus.ITEM_LOST][~done])
        lost_total += int(nxt[wargus.ITEM_LOST].sum())
    assert lost_total > 20
    # a pickup whose new item appears out of sight is not losing sight of the item
    cfg = WargusConfig(size=32, sight=2, shoot_range=0, hit_prob=0.0)
    m = WargusModel(cfg)
    s = _state([5, 5], [[30, 30]], [[5, 6]])
    nxt, picked, _ = wargus.step(m, s, torch.tensor([2]), _keys(1))  # east onto the item
    seen_after = wargus.observe(m, nxt)[1]
    assert picked.item() == 1 and not seen_after.item()  # (this key's new item is far away)
    assert not wargus.item_lost(torch.tensor([True]), seen_after, picked).item()
    assert wargus.item_lost(
        torch.tensor([True]), seen_after, torch.zeros(1, dtype=torch.int64)
    ).item()


def test_item_lost_fires_on_the_step_that_leaves_sight_gym_and_torchrl():
    # walk onto the item's area, then away from it: the event fires once, on leaving sight
    cfg = dict(size=24, sight=3, shoot_range=0, hit_prob=0.0, patrol_speed=0.0, horizon=200)
    g = WargusGymEnv(**cfg)
    obs, info = g.reset(seed=0, options={"instance": {"seed": 3}, "start": (12, 12)})
    assert info[wargus.ITEM_LOST] is False
    item = np.array(info["instance"]["item_pos"][0])
    dirs = {d: i for i, d in enumerate(wargus.DELTAS[:8])}
    actions, events = [], []

    def move(sign) -> dict:
        diff = np.sign(item - np.array(info[wargus.AGENT_POS])) * sign
        a = dirs[(int(diff[0]), int(diff[1]))]
        actions.append(a)
        out = g.step(a)
        events.append(out[4][wargus.ITEM_LOST])
        return out[4]

    assert not info[wargus.ITEM_SEEN]  # (this instance's item starts out of sight)
    while not info[wargus.ITEM_SEEN]:
        info = move(+1)
        assert info[wargus.PICKED] == 0
    assert not any(events)  # coming into sight is no event
    while info[wargus.ITEM_SEEN]:
        info = move(-1)
    assert events[-1] is True and sum(events) == 1  # exactly on the step that leaves sight
    info = move(-1)
    assert events[-1] is False  # staying out of sight is no event
    # the TorchRL env emits the same events for the same actions
    env = WargusEnv(1, seed=0, instances=WargusInstances.fixed(3), start=(12, 12), **cfg)
    data, _ = _run(env, torch.tensor(actions).view(-1, 1))
    assert data[wargus.ITEM_LOST][:, 0].tolist() == events


def _expected_sector(dr: int, dc: int) -> int:
    # compass bearing clockwise from north, 45-degree sectors centred on N, NE, E, ...
    ang = math.degrees(math.atan2(dc, -dr)) % 360.0
    return int(((ang + 22.5) % 360.0) // 45.0)


def test_agent_sees_item_only_within_sight_radius_bearing_always_observed():
    cfg = WargusConfig(size=32, sight=8, shoot_range=5)
    m = WargusModel(cfg)
    agent = [15, 15]
    offsets = [(dr, dc) for dr in range(-15, 17) for dc in range(-15, 17) if (dr, dc) != (0, 0)]
    n = len(offsets)
    items = (torch.tensor([agent]) + torch.tensor(offsets)).unsqueeze(1)  # (n, 1, 2)
    patrols = torch.tensor([[[31, 31]]]).expand(n, 1, 2)
    s = WargusState(
        torch.tensor([agent]).expand(n, 2), patrols, items, torch.zeros(n, dtype=torch.int64)
    )
    obs, item_seen, _ = wargus.observe(m, s)
    dist = torch.tensor([max(abs(a), abs(b)) for a, b in offsets])
    assert torch.equal(item_seen, dist < 8)
    assert torch.equal(obs[:, wargus.OBS_ITEM_SEEN], (dist < 8).float())
    want_off = torch.tensor(offsets, dtype=torch.float32) / 8 * (dist < 8).unsqueeze(-1)
    assert torch.equal(obs[:, wargus.OBS_ITEM_OFFSET], want_off)
    bearing = obs[:, wargus.OBS_ITEM_BEARING]
    assert torch.equal(bearing.sum(-1), torch.ones(n))  # always observed, seen or not
    want = torch.tensor([_expected_sector(a, b) for a, b in offsets])
    assert torch.equal(bearing.argmax(-1), want)
    # the patrol: same rule, distance 16 here, unseen but its bearing (SE) is observed
    assert not obs[:, wargus.OBS_PATROL_SEEN].any()
    assert (obs[:, wargus.OBS_PATROL_OFFSET] == 0).all()
    assert (
        obs[:, wargus.OBS_PATROL_BEARING].argmax(-1) == wargus.BEARINGS.index("southeast")
    ).all()
    assert torch.allclose(obs[:, wargus.OBS_AGENT], torch.tensor([15 / 31, 15 / 31]))
    assert (obs >= m.obs_low).all() and (obs <= m.obs_high).all()


def test_patrols_start_out_of_sight():
    cfg = WargusConfig(num_patrols=3)
    m, n = WargusModel(cfg), 3000
    s = wargus.reset(m, _keys(n))
    assert (wargus.chebyshev(s.agent.unsqueeze(1), s.patrols) >= cfg.sight).all()
    assert not (s.items == s.agent.unsqueeze(1)).all(-1).any()
    cells = s.agent[:, 0] * 32 + s.agent[:, 1]
    assert cells.unique().numel() > 900  # agent start spread over the grid


def test_destruction_terminates():
    # a patrol within shoot range of every cell, never missing: every first step is fatal
    env = WargusEnv(8, seed=0, size=6, sight=6, shoot_range=5, hit_prob=1.0, horizon=50)
    td = env.reset()
    td[keys.ACTION] = env.action_spec.rand()
    out, td = env.step_and_maybe_reset(td)
    nxt = out[keys.NEXT]
    assert nxt[keys.TERMINATED].all() and nxt[keys.DONE].all() and not nxt[keys.TRUNCATED].any()
    assert (td[wargus.PICKED] == 0).all() and not td[keys.DONE].any()  # auto-reset: a new episode
    g = WargusGymEnv(size=6, sight=6, shoot_range=5, hit_prob=1.0)
    g.reset(seed=0)
    _, _, term, trunc, _ = g.step(0)
    assert term and not trunc
    # pure function: destroyed flag; and without hits the episode only truncates at the horizon
    safe = WargusEnv(4, seed=0, size=6, sight=6, shoot_range=5, hit_prob=0.0, horizon=5)
    data, _ = _run(safe, _actions(10, 4, seed=0))
    assert not data[keys.TERMINATED].any()
    assert data[keys.TRUNCATED][:, :, 0].nonzero()[:, 0].unique().tolist() == [4, 9]


# --------------------------------------------------------------------------------- invalid input


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(hit_prob=1.5), "hit_prob"),
        (dict(hit_prob=-0.1), "hit_prob"),
        (dict(patrol_speed=2.0), "patrol_speed"),
        (dict(sight=40), "sight"),
        (dict(sight=0), "sight"),
        (dict(shoot_range=8), "shoot_range"),
        (dict(size=12, sight=8, shoot_range=9), "shoot_range"),
        (dict(shoot_range=-1), "shoot_range"),
        (dict(size=2), "size"),
        (dict(size=10_000), "size"),
        (dict(num_patrols=0), "num_patrols"),
        (dict(num_items=100), "num_items"),
        (dict(horizon=0), "horizon"),
        (dict(noop="yes"), "noop"),
    ],
)
def test_invalid_parameters_raise_naming_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field) as e:
        WargusConfig(**kwargs)
    assert "[" in str(e.value)  # the allowed range is stated
    with pytest.raises(ValueError, match=field):
        WargusEnv(2, **kwargs)
    with pytest.raises(ValueError, match=field):
        WargusGymEnv(**kwargs)


def test_invalid_actions_instances_and_options_raise():
    env = WargusEnv(3, seed=0)  # an action above the range: tests/test_family_conformance.py
    td = env.reset()
    td[keys.ACTION] = torch.tensor([0, -1, 1])
    with pytest.raises(ValueError, match=r"action must be in \[0, 7\]"):
        env.step(td)
    g = WargusGymEnv()
    g.reset(seed=0)
    for bad in (8, -1, 2.5):
        with pytest.raises(ValueError, match="action"):
            g.step(bad)
    with pytest.raises(ValueError, match="start"):
        g.reset(options={"start": (32, 0)})
    with pytest.raises(ValueError, match="start"):
        WargusEnv(1, start=(-1, 3))
    with pytest.raises(ValueError, match="instance seed"):
        g.reset(options={"instance": {"seed": -3}})
    with pytest.raises(ValueError, match="unknown reset option"):
        g.reset(options={"wind": 1})
    with pytest.raises(ValueError, match="unknown Wargus config field"):
        WargusEnv(1, config={"sigth": 3})
    with pytest.raises(ValueError, match="instance distribution"):
        WargusEnv(1, instances="south")
    with pytest.raises(ValueError, match="seeds"):
        WargusInstances(seeds=(1, -2))
    with pytest.raises(ValueError, match="order"):
        WargusInstances(order="random")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu_bit_for_bit():
    check_env_specs(WargusEnv(64, seed=1, device="cuda"))
    actions = _actions(300, 16, seed=2)
    cpu, croot = _run(WargusEnv(16, seed=8, **SMALL), actions)
    gpu, groot = _run(WargusEnv(16, seed=8, device="cuda", **SMALL), actions.cuda())
    assert (gpu.cpu() == cpu).all() and torch.equal(groot.cpu(), croot)
