"""Windy family: specs, Gymnasium API, determinism, batched-vs-looped, dynamics vs exact model."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs, step_mdp

import taskvar_torch  # noqa: F401  (registers the gym ids)
from taskvar_torch import rng
from taskvar_torch.envs.registration import env_ids
from taskvar_torch.families.windy import (
    WindyGridEnv,
    WindyInstances,
    WindyLayout,
    WindyModel,
    make_layout,
)
from taskvar_torch.families.windy import (
    dynamics as windy,
)
from taskvar_torch.families.windy.env import _C_START

ENV_IDS = env_ids()
torch.set_num_threads(1)

WINDY_IDS = [i for i in ENV_IDS if "Windy" in i]


def rollout_cells(env: WindyGridEnv, actions: torch.Tensor) -> dict[str, torch.Tensor]:
    """Step ``env`` with ``actions`` (T, N) using auto-reset; return stacked cells/rewards/dones."""
    td = env.reset()
    cells, dones, ps = [], [], []
    for a in actions:
        td["action"] = a
        out, td = env.step_and_maybe_reset(td)
        cells.append(out["next", "cell"])
        dones.append(out["next", "done"].squeeze(-1))
        ps.append(out["instance", "p"])
    return {"cell": torch.stack(cells), "done": torch.stack(dones), "p": torch.stack(ps)}


@pytest.mark.parametrize("n", [1, 64])
@pytest.mark.parametrize("layout", ["middle_exits", "whole_column_windy"])  # default: conformance
def test_check_env_specs(n, layout):
    check_env_specs(WindyGridEnv(num_envs=n, layout=layout, seed=0))


def test_check_env_specs_large_coords_patch():
    env = WindyGridEnv(num_envs=8, layout=make_layout(25, 25, 2), obs_encoding="coords_patch")
    check_env_specs(env)
    assert env.observation_spec["observation"].shape == (8, 2 + 3 * 25)


@pytest.mark.parametrize("env_id", WINDY_IDS)
def test_gymnasium_check_env_and_render_modes(env_id):
    for mode in ("ansi", "rgb_array"):
        env = gym.make(env_id, render_mode=mode)  # check_env: tests/test_family_conformance.py
        obs, info = env.reset(seed=0)
        assert env.observation_space.contains(obs)
        assert "instance" in info and set(info["instance"]) == {"p", "direction"}
        frame = env.render()
        layout = env.unwrapped.layout
        if mode == "ansi":
            assert isinstance(frame, str) and frame.count("A") == 1
        else:
            assert isinstance(frame, np.ndarray) and frame.dtype == np.uint8
            assert frame.shape == (layout.height * 32, layout.width * 32, 3)


def test_observation_never_contains_the_instance():
    env = gym.make("taskvar/WindyGrid-v0").unwrapped
    a, _ = env.reset(
        seed=1, options={"instance": {"p": 0.1, "direction": "north"}, "start": (2, 0)}
    )
    b, _ = env.reset(
        seed=1, options={"instance": {"p": 0.9, "direction": "south"}, "start": (2, 0)}
    )
    np.testing.assert_array_equal(a, b)


@pytest.mark.slow
def test_batched_equals_looped_1000_steps():
    n, steps = 6, 1000
    gen = torch.Generator().manual_seed(0)
    actions = torch.randint(0, 4, (steps, n), generator=gen)
    batched = rollout_cells(WindyGridEnv(num_envs=n, seed=11), actions)
    for i in range(n):
        single = rollout_cells(
            WindyGridEnv(num_envs=1, seed=11, index_offset=i), actions[:, i : i + 1]
        )
        for k in batched:
            torch.testing.assert_close(batched[k][:, i], single[k][:, 0], rtol=0, atol=0)
    assert batched["done"].sum() > 50  # many episodes, so partial resets were exercised


class ReferenceWindy:
    """A plain-Python windy gridworld (the layout's own neighbours, the keyed streams of
    ``taskvar_torch.rng``, one draw at a time): the reference the Gymnasium env and the batched
    env are checked against, bit for bit. Episode ``k`` of seed ``s`` is sub-environment 0's."""

    def __init__(self, layout: WindyLayout, horizon: int, seed: int):
        self.layout, self.horizon, self.episode = layout, horizon, -1
        self.base = rng.sub_env_key(seed, torch.zeros(1, dtype=torch.int64))

    def reset(self) -> int:
        self.episode += 1
        key = rng.episode_key(self.base, self.episode)  # (1,)
        p, d = WindyInstances.named("train").sample(key)
        self.p, self.dir, self.key, self.t = float(p[0]), int(d[0]), int(key[0]), 0
        starts = self.layout.cells_of("S")
        self.cell = starts[int(rng.draw_index(key, _C_START, len(starts))[0])]
        return self.cell

    def step(self, action: int) -> tuple[int, bool, bool]:
        cell = self.layout.neighbour(self.cell, action)
        if self.layout.char(cell) == "W" and rng.draw_uniform(self.key, self.t) < self.p:
            cell = self.layout.neighbour(cell, self.dir)  # the gust
        self.cell, self.t = cell, self.t + 1
        terminated = self.layout.char(cell) == "G"
        return cell, terminated, self.t >= self.horizon and not terminated


def test_gymnasium_env_matches_torchrl_env_bit_for_bit():
    env = WindyGridEnv(num_envs=1, seed=9)
    genv = gym.make("taskvar/WindyGrid-v0").unwrapped
    ref = ReferenceWindy(env.layout, env.horizon, seed=9)
    _, info = genv.reset(seed=9)
    td = env.reset()
    assert divmod(ref.reset(), 5) == info["cell"] and ref.p == info["instance"]["p"]
    actions = np.random.default_rng(0).integers(0, 4, 1500)
    for a in actions:
        td["action"] = torch.tensor([int(a)])
        out = env.step(td)
        _, _, term, trunc, info = genv.step(int(a))
        cell, ref_term, ref_trunc = ref.step(int(a))
        r, c = info["cell"]
        assert int(out["next", "cell"][0]) == r * 5 + c == cell
        assert float(out["instance", "p"][0]) == info["instance"]["p"] == ref.p
        assert bool(out["next", "terminated"][0]) == term == ref_term and trunc == ref_trunc
        if term or trunc:
            _, info = genv.reset()
            td = env.reset()
            assert divmod(ref.reset(), 5) == info["cell"] and ref.p == info["instance"]["p"]
        else:
            td = step_mdp(out)


def test_partial_reset_resets_only_done_envs_and_resamples_instance():
    env = WindyGridEnv(num_envs=4, seed=0)
    td = env.reset()
    td["action"] = torch.tensor([2, 2, 2, 2])
    out, nxt = env.step_and_maybe_reset(td)
    before_p = td["instance", "p"].clone()
    reset = torch.tensor([True, False, False, False]).unsqueeze(-1)
    nxt.set("_reset", reset)
    after = env.reset(nxt)
    assert after["instance", "p"][0] != before_p[0]
    assert torch.equal(after["instance", "p"][1:], before_p[1:])
    assert torch.equal(after["cell"][1:], out["next", "cell"][1:])


def test_wind_pushes_agent_north_with_probability_p():
    # agent moves from (4,0) east into the windy cell (4,1); a north gust sends it to (3,1)
    n, p = 40000, 0.3
    model = WindyModel(WindyLayout.named("default"))
    cell = torch.full((n,), 4 * 5 + 0)
    action = torch.full((n,), 2)
    u = rng.draw_uniform(rng.sub_env_key(0, torch.arange(n)), 0)
    nxt, term = windy.step(model, cell, action, torch.zeros(n, dtype=torch.long), u < p)
    frac = (nxt == 3 * 5 + 1).float().mean().item()
    assert set(nxt.unique().tolist()) == {3 * 5 + 1, 4 * 5 + 1}
    assert abs(frac - p) < 4 * (p * (1 - p) / n) ** 0.5
    assert not term.any()


def test_north_wind_at_north_exit_is_harmless():
    model = WindyModel(WindyLayout.named("default"))
    nxt, _ = windy.step(
        model, torch.tensor([0]), torch.tensor([2]), torch.tensor([0]), torch.tensor([True])
    )
    assert nxt.item() == 1  # pushed north into the edge: stays in the windy cell (0, 1)


@pytest.mark.parametrize("layout", ["default", "middle_exits", "whole_column_windy"])
def test_dynamics_match_transition_tensors(layout):
    """Empirical next-cell frequencies at every (cell, action) agree with P within binomial tolerance."""
    model = WindyModel(WindyLayout.named(layout))
    S, A, n = model.num_cells, 4, 4000
    for p, d in ((0.35, 0), (0.8, 1)):
        P, R = windy.transition_tensors(model, torch.tensor([p]), torch.tensor([d]))
        cells = torch.arange(S).repeat_interleave(A * n)
        actions = torch.arange(A).repeat_interleave(n).repeat(S)
        keys = rng.sub_env_key(17, torch.arange(cells.numel()))
        u = rng.draw_uniform(keys, 5)
        nxt, _ = windy.step(model, cells, actions, torch.full_like(cells, d), u < p)
        counts = torch.zeros(S * A, S, dtype=torch.float64)
        counts.index_put_(
            (cells * A + actions, nxt), torch.ones_like(u, dtype=torch.float64), accumulate=True
        )
        freq = (counts / n).view(S, A, S)
        expected = P[0].clone()
        goal = model.is_goal
        expected[goal] = 0.0  # the exact model makes goals absorbing; step() never starts there
        expected[goal, :, :] = freq[goal]
        tol = 5 * torch.sqrt(expected * (1 - expected) / n) + 1e-12
        assert ((freq - expected).abs() <= tol).all()
        assert torch.allclose(P.sum(-1), torch.ones(1, S, A, dtype=torch.float64))
        assert (R[0, ~goal] == -1).all() and (R[0, goal] == 0).all()


def test_reward_and_episode_end():
    env = WindyGridEnv(
        num_envs=1, seed=0, start=(0, 0), instances=WindyInstances.fixed(0.0, "north")
    )
    td = env.reset()
    total = 0.0
    for _ in range(3):  # east x3: (0,1) -> (0,2) -> (0,3) goal
        td["action"] = torch.tensor([2])
        out = env.step(td)
        total += out["next", "reward"].item()
        td = step_mdp(out)
    assert total == -3.0 and out["next", "terminated"].item() and out["next", "done"].item()


def test_truncation_after_horizon():
    env = WindyGridEnv(num_envs=2, seed=0, horizon=7)
    td, truncated = env.reset(), []
    for _ in range(7):  # north into the edge or the wall: never reaches the goal
        td["action"] = torch.zeros(2, dtype=torch.long)
        out = env.step(td)
        truncated.append(out["next", "truncated"].squeeze(-1))
        td = step_mdp(out)
    truncated = torch.stack(truncated)
    assert truncated[-1].all() and not truncated[:-1].any()


def test_start_cells_are_uniform_over_s_cells():
    env = WindyGridEnv(num_envs=5000, seed=1)
    cells = env.reset()["cell"]
    assert set(cells.unique().tolist()) == {0, 5, 10, 15, 20}
    counts = torch.bincount(cells, minlength=25)[[0, 5, 10, 15, 20]].double()
    assert ((counts / 5000 - 0.2).abs() < 4 * (0.16 / 5000) ** 0.5).all()


def test_instance_distributions():
    key = rng.episode_key(rng.sub_env_key(0, torch.arange(20000)), 0)
    p, d = WindyInstances.named("train").sample(key)
    assert 0.0 <= p.min() and p.max() < 1.0 and abs(p.mean().item() - 0.5) < 0.01
    assert set(d.unique().tolist()) == {0, 1}
    _, d = WindyInstances.named("south").sample(key)
    assert set(d.unique().tolist()) == {1}
    p, d = WindyInstances.fixed(0.25, "north").sample(key)
    assert (p == 0.25).all() and (d == 0).all()


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: WindyInstances(p_low=-0.1), "p_low must be in \\[0, 1\\]"),
        (lambda: WindyInstances(p_high=1.5), "p_high must be in \\[0, 1\\]"),
        (lambda: WindyInstances.fixed(2.0, "north"), "p must be in \\[0, 1\\]"),
        (lambda: WindyInstances(directions=("up",)), "direction must be one of"),
        (lambda: WindyInstances.named("west-ish"), "instance distribution must be one of"),
        (lambda: WindyLayout.from_map("S . G\nS G"), "row 1 has 2 cells"),
        (lambda: WindyLayout.from_map("S X G"), "unknown cell characters \\['X'\\]"),
        (lambda: WindyLayout.from_map("S . #"), "no goal cell"),
        (lambda: make_layout(5, 5, num_exits=1), "num_exits must be >= 2"),
        (lambda: make_layout(3, 5, num_exits=4), "height must be >= num_exits"),
        (lambda: make_layout(5, 5, wall_col=4), "wall_col must be in"),
        (lambda: WindyGridEnv(layout="nope"), "layout must be one of"),
        (lambda: WindyGridEnv(start=(9, 9)), "start must be a \\(row, col\\) inside 5x5"),
        (lambda: WindyGridEnv(obs_encoding="pixels"), "observation encoding must be one of"),
        (lambda: WindyGridEnv(num_envs=0), "num_envs must be >= 1"),
    ],
)
def test_invalid_parameters_raise_value_error_naming_the_field(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_gym_env_refuses_bad_actions_and_reset_options():
    genv = gym.make("taskvar/WindyGrid-v0").unwrapped
    genv.reset(seed=0)
    with pytest.raises(ValueError, match="action must be in \\[0, 3\\]"):
        genv.step(4)
    with pytest.raises(ValueError, match="unknown reset option"):
        genv.reset(options={"wind": 1})
    with pytest.raises(ValueError, match="p must be in \\[0, 1\\]"):
        genv.reset(options={"instance": {"p": 1.2}})


def test_scaled_layout_generator():
    lay = make_layout(51, 51, num_exits=4, wind_cells_per_exit=2)
    assert lay.num_exits == 4 and lay.exit_names == ("exit_0", "exit_1", "exit_2", "exit_3")
    assert [g[0] // 51 for g in lay.exit_cells] == [0, 17, 33, 50]
    assert sum(r.count("W") for r in lay.rows) == 8
    assert (
        windy.default_horizon(lay) == 408
        and windy.default_horizon(WindyLayout.named("default")) == 100
    )


def test_noise_seed_keeps_instances_and_starts_but_changes_gusts():
    gen = torch.Generator().manual_seed(4)
    actions = torch.randint(0, 4, (200, 64), generator=gen)
    a = rollout_cells(WindyGridEnv(num_envs=64, seed=5), actions)
    b = rollout_cells(WindyGridEnv(num_envs=64, seed=5, noise_seed=1), actions)
    assert torch.equal(a["p"][0], b["p"][0])  # same first instances
    assert torch.equal(
        WindyGridEnv(num_envs=64, seed=5).reset()["cell"],
        WindyGridEnv(num_envs=64, seed=5, noise_seed=1).reset()["cell"],
    )
    assert not torch.equal(a["cell"], b["cell"])
