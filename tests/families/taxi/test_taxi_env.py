"""Taxi family: exact against Gymnasium Taxi-v4 (P, rain, fickle passenger), specs, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from gymnasium.envs.toy_text.taxi import TaxiEnv as GymTaxi
from gymnasium.utils.env_checker import check_env
from torchrl.envs.utils import check_env_specs

from taskvar_torch import rng
from taskvar_torch.families.taxi import dynamics as taxi
from taskvar_torch.families.taxi.dynamics import TaxiInstances, TaxiModel, encode
from taskvar_torch.families.taxi.env import _C_ARMED, _C_START, TaxiEnv
from taskvar_torch.families.taxi.gym_env import TaxiGymEnv

torch.set_num_threads(1)

QS = (0.5, 0.7, 0.8, 0.9, 1.0)


def gym_dense(env: GymTaxi) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gymnasium's ``P`` lists as dense ``P (S, A, S')`` (duplicates summed), ``R``, ``done``."""
    P = np.zeros((500, 6, 500))
    R = np.zeros((500, 6))
    done = np.zeros((500, 6), dtype=bool)
    for s in range(500):
        for a in range(6):
            assert len({(r, d) for _, _, r, d in env.P[s][a]}) == 1  # one reward/done per (s, a)
            for p, s2, r, d in env.P[s][a]:
                P[s, a, s2] += p
                R[s, a], done[s, a] = r, d
    return P, R, done


def test_encode_decode_match_taxi_v4_on_ints_and_tensors():
    g = GymTaxi()
    for s in range(500):
        assert taxi.decode(s) == g.decode(s)
        assert taxi.encode(*g.decode(s)) == s
    s = torch.arange(500)
    assert torch.equal(taxi.encode(*taxi.decode(s)), s)
    assert list(taxi.LOCS) == g.locs and taxi.MAP == tuple(
        "".join(c.decode() for c in row) for row in g.desc
    )


@pytest.mark.parametrize("q", QS)
def test_transition_tensors_equal_gymnasium_rainy_P(q):
    P, R, done = taxi.transition_tensors(q)
    Pg, Rg, dg = gym_dense(GymTaxi(is_rainy=True, rainy_probability=q))
    np.testing.assert_allclose(P[0].numpy(), Pg, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(R[0].numpy(), Rg)
    np.testing.assert_array_equal(done[0].numpy(), dg)


def test_transition_tensors_dry_equal_gymnasium_default_P_and_batch_over_q():
    P, R, done = taxi.transition_tensors(list(QS))
    Pg, Rg, dg = gym_dense(GymTaxi())
    np.testing.assert_array_equal(P[-1].numpy(), Pg)  # q = 1 is the dry Taxi
    np.testing.assert_array_equal(R[-1].numpy(), Rg)
    np.testing.assert_array_equal(done[-1].numpy(), dg)
    for i, q in enumerate(QS):  # the batch is the per-q tensors stacked
        assert torch.equal(P[i], taxi.transition_tensors(q)[0][0])


def test_model_outcomes_are_gymnasium_P_entries_in_order():
    """``next[s, a, k]`` is entry k of Gymnasium's rainy list (intended, left, right)."""
    model, g = TaxiModel(), GymTaxi(is_rainy=True, rainy_probability=0.8)
    for s in range(500):
        for a in range(6):
            entries = g.P[s][a]
            for k in range(3):
                expected = entries[k][1] if a < 4 else entries[0][1]
                assert int(model.next[s, a, k]) == expected
            assert float(model.reward[s, a]) == entries[0][2]


def test_start_states_are_gymnasium_initial_state_distribution_support():
    dist = GymTaxi().initial_state_distrib
    assert np.allclose(dist[dist > 0], 1 / 300)
    np.testing.assert_array_equal(np.flatnonzero(dist), taxi.initial_states())


def test_batched_step_matches_per_environment_loop_over_gymnasium_P():
    model, g = TaxiModel(), GymTaxi(is_rainy=True, rainy_probability=0.6)
    gen = torch.Generator().manual_seed(0)
    N = 3000
    state = torch.randint(0, 500, (N,), generator=gen)
    action = torch.randint(0, 6, (N,), generator=gen)
    q = torch.full((N,), 0.6)
    outcome = taxi.rain_outcome(torch.rand(N, generator=gen), q)
    armed = torch.zeros(N, dtype=torch.bool)
    nxt, reward, term, armed2 = taxi.step(model, state, action, outcome, armed, outcome)
    assert not armed2.any()
    for i in range(N):
        s, a, k = int(state[i]), int(action[i]), int(outcome[i])
        _, s2, r, d = g.P[s][a][k if a < 4 else 0]
        assert (int(nxt[i]), float(reward[i]), bool(term[i])) == (s2, r, d)


@pytest.mark.parametrize("q", (0.5, 0.8))
def test_env_steps_sample_the_exact_transition_tensors(q):
    """One step from fixed states under each action: empirical next-state frequencies vs P,
    within 5 standard errors (+1e-3) per next state."""
    P = taxi.transition_tensors(q)[0][0]
    N = 4000
    for s in (encode(0, 0, 0, 1), encode(2, 2, 4, 3), encode(3, 1, 2, 0), encode(4, 4, 1, 2)):
        env = TaxiEnv(N, instances=TaxiInstances.fixed(q, 0.0), start=s, seed=1)
        td = env.reset()
        for a in range(6):
            env.reset()
            td["action"] = torch.full((N,), a)
            nxt = env.step(td)["next", "cell"]
            freq = torch.bincount(nxt, minlength=500).double() / N
            p = P[s, a]
            tol = 5 * (p * (1 - p) / N).sqrt() + 1e-3
            assert ((freq - p).abs() <= tol).all(), (s, a)


# Fickle passenger: pick up at R, a blocked move (no fire), drop off and pick up again at R,
# then moves. The event is (step at which the destination changed, new destination) or never.
FICKLE_START = encode(0, 0, 0, 1)  # taxi at R, passenger at R, destination G
FICKLE_ACTIONS = (4, 1, 5, 4, 0, 0, 2, 1, 3, 0)
Q_F, F_F = 0.7, 0.6


def exact_fickle_events(q: float, f: float) -> np.ndarray:
    """Exact probabilities of the events, ``(T + 1, 4)``: row t < T is 'changed at step t to
    destination d', row T column 0 'never' — by forward propagation over (state, armed) with
    :func:`transition_tensors` and :func:`fickle_rule`."""
    P = taxi.transition_tensors(q)[0][0]  # (S, A, S)
    fires, targets = taxi.fickle_rule()
    T = len(FICKLE_ACTIONS)
    free = torch.zeros(500, dtype=torch.float64)  # not armed
    armed = torch.zeros(500, dtype=torch.float64)
    free[FICKLE_START], armed[FICKLE_START] = 1 - f, f
    events = np.zeros((T + 1, 4))
    target_dest = torch.as_tensor(taxi.decode(targets)[3])  # (S, 3)
    for t, a in enumerate(FICKLE_ACTIONS):
        flow = armed[:, None] * P[:, a, :]  # (S, S')
        fired = (flow * fires).sum(0)  # (S',)
        free = free @ P[:, a, :]
        for k in range(3):
            free.index_add_(0, targets[:, k], fired / 3)
            np.add.at(events[t], target_dest[:, k].numpy(), (fired / 3).numpy())
        armed = (flow * ~fires).sum(0)
    events[T, 0] = 1 - events[:T].sum()
    return events


def event_of(states: list[int]) -> tuple[int, int] | None:
    """(step, new destination) of the first destination change along ``states`` (None if none);
    asserts there is at most one change."""
    dests = [taxi.decode(s)[3] for s in states]
    changes = [t for t in range(1, len(dests)) if dests[t] != dests[t - 1]]
    assert len(changes) <= 1, dests  # at most once an episode
    return (changes[0] - 1, dests[changes[0]]) if changes else None


def frequencies(events: list[tuple[int, int] | None]) -> np.ndarray:
    T = len(FICKLE_ACTIONS)
    out = np.zeros((T + 1, 4))
    for e in events:
        out[(T, 0) if e is None else e] += 1
    return out / len(events)


def assert_close_to(freq: np.ndarray, p: np.ndarray, n: int) -> None:
    """Every event frequency within 5 standard errors (+1e-3) of its exact probability."""
    tol = 5 * np.sqrt(p * (1 - p) / n) + 1e-3
    assert (np.abs(freq - p) <= tol).all(), np.argwhere(np.abs(freq - p) > tol)


@pytest.mark.slow
def test_fickle_passenger_follows_gymnasium_step_in_distribution():
    """Gymnasium's own ``step`` (many seeds) and TaxiEnv both match the exact event law: redraw
    frequency, the step it happens on (never on the pickup or a blocked move), which new
    destination, and at most once."""
    exact = exact_fickle_events(Q_F, F_F)
    assert exact[[0, 1, 2, 3]].sum() == 0  # pickup, blocked move, dropoff, pickup: never fires
    assert exact[len(FICKLE_ACTIONS), 0] == pytest.approx(1 - F_F, abs=0.02)  # fires if armed
    g = GymTaxi(is_rainy=True, rainy_probability=Q_F, fickle_passenger=True, fickle_probability=F_F)
    M = 3000
    gym_events = []
    for seed in range(M):
        g.reset(seed=seed)
        g.s = FICKLE_START
        states = [FICKLE_START] + [g.step(a)[0] for a in FICKLE_ACTIONS]
        gym_events.append(event_of(states))
    assert_close_to(frequencies(gym_events), exact, M)

    N = 20000
    env = TaxiEnv(N, instances=TaxiInstances.fixed(Q_F, F_F), start=FICKLE_START, seed=5)
    td = env.reset()
    states = [td["cell"]]
    for a in FICKLE_ACTIONS:
        td = env.step(td.set("action", torch.full((N,), a)))["next"]
        states.append(td["cell"])
    assert not td["done"].any()
    traj = torch.stack(states, 1).tolist()
    assert_close_to(frequencies([event_of(s) for s in traj]), exact, N)


def test_fickle_probability_one_always_redraws_on_first_move_with_passenger():
    N = 500
    env = TaxiEnv(N, instances=TaxiInstances.fixed(1.0, 1.0), start=encode(2, 2, 4, 3), seed=0)
    td = env.reset()
    assert td["instance", "armed"].all()
    td = env.step(td.set("action", torch.zeros(N, dtype=torch.int64)))["next"]  # south: moves
    row, col, pas, dest = taxi.decode(td["cell"])
    assert (row == 3).all() and (pas == 4).all() and (dest != 3).all()
    assert not td["instance", "armed"].any()
    freq = torch.bincount(dest, minlength=4).double() / N
    assert (freq[:3] - 1 / 3).abs().max() < 0.1


def test_instance_distributions():
    key = torch.arange(20000)
    q, f = TaxiInstances.named("train").sample(key)
    rainy, fickle = q < 1, f > 0
    assert abs(rainy.double().mean() - 0.5) < 0.02 and abs(fickle.double().mean() - 0.5) < 0.02
    assert q[rainy].min() >= 0.7 and q[rainy].max() <= 0.9 and (q[~rainy] == 1).all()
    assert f[fickle].min() >= 0.2 and f[fickle].max() <= 0.4 and (f[~fickle] == 0).all()
    assert (rainy & fickle).double().mean().sub(0.25).abs() < 0.02  # independent draws
    q, f = TaxiInstances.named("dry").sample(key)
    assert (q == 1).all() and (f == 0).all()
    q, f = TaxiInstances.named("storm").sample(key)
    assert q.min() >= 0.5 and q.max() <= 0.7 and f.min() >= 0.8 and f.max() <= 1.0
    q, f = TaxiInstances.named("gymnasium").sample(key)
    assert (q == np.float32(0.8)).all() and (f == np.float32(0.3)).all()
    for name in TaxiInstances.NAMES:
        TaxiInstances.named(name)
    # arming at reset: Bernoulli(f) per episode
    env = TaxiEnv(20000, instances=TaxiInstances.fixed(0.8, 0.3), seed=2)
    assert abs(env.reset()["instance", "armed"].double().mean() - 0.3) < 0.02


def rollout(env: TaxiEnv, actions: torch.Tensor) -> torch.Tensor:
    """States ``(T, N)`` under ``actions`` ``(T, N)`` with auto-reset."""
    td = env.reset()
    out = []
    for a in actions:
        step, td = env.step_and_maybe_reset(td.set("action", a))
        out.append(torch.stack([step["next", "cell"], step["next", "reward"].squeeze(-1).long()]))
    return torch.stack(out)


def test_noise_seed_keeps_instances_and_starts_and_changes_rain():
    N = 64
    e1 = TaxiEnv(N, instances="heavy_rain", seed=3)
    e2 = TaxiEnv(N, instances="heavy_rain", seed=3, noise_seed=1)
    t1, t2 = e1.reset(), e2.reset()
    assert torch.equal(t1["cell"], t2["cell"])
    assert torch.equal(t1["instance", "rainy_probability"], t2["instance", "rainy_probability"])
    actions = torch.zeros(20, N, dtype=torch.int64)
    assert not torch.equal(rollout(e1, actions), rollout(e2, actions))


@pytest.mark.parametrize("n", [1, 4])
@pytest.mark.parametrize("encoding", ["onehot", "factored"])
def test_observation_keys_and_shapes(n, encoding):
    env = TaxiEnv(n, instances="storm", obs_encoding=encoding, seed=0)
    if encoding != "onehot":  # the default's: tests/test_family_conformance.py
        check_env_specs(env)
    td = env.reset()
    assert td["observation"].shape == (n, 500 if encoding == "onehot" else 19)
    assert td["observation"].dtype == torch.float32 and td["cell"].dtype == torch.int64
    assert set(td["instance"].keys()) == {"rainy_probability", "fickle_probability", "armed"}


def test_factored_observation_is_the_decoded_state():
    env = TaxiEnv(16, obs_encoding="factored", seed=0)
    td = env.reset()
    row, col, pas, dest = taxi.decode(td["cell"])
    obs = td["observation"]
    assert torch.equal(obs[:, :5].argmax(-1), row) and torch.equal(obs[:, 5:10].argmax(-1), col)
    assert torch.equal(obs[:, 10:15].argmax(-1), pas) and torch.equal(obs[:, 15:].argmax(-1), dest)


class ReferenceTaxi:
    """A plain-Python Taxi (the model's tables as lists, the keyed streams of
    ``taskvar_torch.rng``, one draw at a time): the reference the Gymnasium env and the batched
    env are checked against, bit for bit. Episode ``k`` of seed ``s`` is sub-environment 0's."""

    def __init__(self, instances: str, seed: int):
        m = TaxiModel()
        self.next, self.reward = m.next.tolist(), m.reward.tolist()
        self.done, self.targets = m.done.tolist(), m.fickle_targets.tolist()
        self.starts, self.instances = m.start_states.tolist(), TaxiInstances.named(instances)
        self.base, self.episode = rng.sub_env_key(seed, torch.zeros(1, dtype=torch.int64)), -1

    def reset(self) -> int:
        self.episode += 1
        key = rng.episode_key(self.base, self.episode)  # (1,)
        q, f = (float(v[0]) for v in self.instances.sample(key))
        self.key, self.t = int(key[0]), 0
        threshold = lambda p: math.ceil(p * (1 << 24))  # noqa: E731  (u < p iff bits < it)
        self.thr = (threshold(q), threshold(0.5 * (1.0 + q)))
        self.armed = (rng.draw_bits(self.key, _C_ARMED) >> 8) < threshold(f)
        start = rng.draw_bits(self.key, _C_START)
        self.state = self.starts[rng.index_of(start, len(self.starts))]
        return self.state

    def step(self, a: int) -> tuple[int, float]:
        s, u = self.state, rng.draw_bits(self.key, 2 * self.t) >> 8  # the rain
        nxt = self.next[s][a][(u >= self.thr[0]) + (u >= self.thr[1])]
        if self.armed and (s // 4) % 5 == taxi.IN_TAXI and s // 20 != nxt // 20:  # fickle
            nxt = self.targets[nxt][rng.index_of(rng.draw_bits(self.key, 2 * self.t + 1), 3)]
            self.armed = False
        self.state, self.t = nxt, self.t + 1
        return nxt, self.reward[s][a]


def test_gym_env_check_env_render_and_matches_batched_env():
    for mode in ("ansi", "rgb_array"):
        check_env(TaxiGymEnv(instances="storm", render_mode=mode), skip_render_check=False)
    g = TaxiGymEnv(instances="storm")
    env = TaxiEnv(1, instances="storm", seed=3)
    ref = ReferenceTaxi("storm", seed=3)
    actions = torch.randint(0, 6, (300, 1), generator=torch.Generator().manual_seed(2))
    batched = rollout(env, actions)
    obs, _ = g.reset(seed=3)
    assert obs == ref.reset()
    for t, a in enumerate(actions[:, 0].tolist()):
        obs, r, term, trunc, _ = g.step(a)
        assert (obs, int(r)) == tuple(batched[t, :, 0].tolist()) == ref.step(a)
        if term or trunc:
            obs, _ = g.reset()
            assert obs == ref.reset()


def test_gym_env_action_mask_is_taxi_v4s_and_options_pin_instance_and_state():
    g, ref = TaxiGymEnv(), GymTaxi()
    for s in range(500):
        _, info = g.reset(options={"state": s})
        np.testing.assert_array_equal(info["action_mask"], ref.action_mask(s))
    inst = {"is_rainy": True, "rainy_probability": 0.6, "fickle_passenger": True}
    obs, info = g.reset(seed=0, options={"instance": inst, "state": 17})
    assert obs == 17
    assert info["instance"]["rainy_probability"] == pytest.approx(0.6)
    assert info["instance"]["fickle_probability"] == pytest.approx(0.3)  # Taxi-v4's default
    _, info = g.reset(options={"instance": {}})
    assert info["instance"]["rainy_probability"] == 1.0 and not info["instance"]["is_rainy"]


def test_render_modes():
    env = TaxiEnv(2, seed=0)
    env.reset()
    text = env.render(1, "ansi")
    assert "destination" in text and "+---------+" in text
    img = env.render(0, "rgb_array")
    assert img.shape == (160, 160, 3) and img.dtype == np.uint8
    with pytest.raises(ValueError, match="render mode"):
        env.render(0, "human")
    g = TaxiGymEnv(render_mode="ansi")
    g.reset(seed=0)
    g.step(0)
    assert "(South)" in g.render()


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: taxi.transition_tensors(1.2), "rainy_probability must be in"),
        (lambda: TaxiInstances(q_low=-0.1), "q_low must be in"),
        (lambda: TaxiInstances(f_high=1.5), "f_high must be in"),
        (lambda: TaxiInstances(q_low=0.9, q_high=0.8), "q_low"),
        (lambda: TaxiInstances(points=((1.1, 0.0),)), "rainy_probability must be in"),
        (lambda: TaxiEnv(instances="windy"), "instance distribution must be one of"),
        (lambda: TaxiEnv(instances={"q": 0.5}), "unknown instance field"),
        (lambda: TaxiEnv(obs_encoding="pixels"), "obs_encoding must be one of"),
        (lambda: TaxiEnv(start=500), "start must be a Taxi-v4 state"),
        (lambda: TaxiEnv(horizon=0), "horizon must be"),
        (
            lambda: TaxiGymEnv().reset(options={"instance": {"rainy_probability": 2.0}}),
            "rainy_probability must be in",
        ),
        (lambda: TaxiGymEnv().reset(options={"instance": {"is_rainy": 1}}), "is_rainy"),
        (lambda: TaxiGymEnv().reset(options={"state": -1}), "state must be"),
        (lambda: TaxiGymEnv().reset(options={"start": 3}), "unknown reset option"),
    ],
)
def test_bad_inputs_raise_one_line_value_errors(make, match):
    with pytest.raises(ValueError, match=match) as err:
        make()
    assert "\n" not in str(err.value)


def test_gym_env_refuses_an_action_out_of_range():
    g = TaxiGymEnv()
    g.reset(seed=0)
    with pytest.raises(ValueError, match="action must be in"):
        g.step(7)
