"""Every registered taskvar/ id: Gymnasium check_env, render modes, determinism (Minigrid-style sweep)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import taskvar_torch  # noqa: F401
from taskvar_torch.envs.registration import env_ids

ENV_IDS = env_ids()


@pytest.mark.parametrize("env_id", list(ENV_IDS))
def test_registered_env_passes_check_env(env_id):
    env = gym.make(env_id)
    check_env(env.unwrapped)
    assert env_id in gym.registry


@pytest.mark.parametrize("env_id", list(ENV_IDS))
@pytest.mark.parametrize("mode", ["ansi", "rgb_array"])
def test_render_modes(env_id, mode):
    env = gym.make(env_id, render_mode=mode)
    env.reset(seed=0)
    frame = env.render()
    if mode == "ansi":
        assert isinstance(frame, str) and len(frame.splitlines()) >= 4
    else:
        assert isinstance(frame, np.ndarray) and frame.dtype == np.uint8 and frame.ndim == 3
        assert frame.shape[2] == 3 and frame.shape[0] >= 64 and frame.std() > 0


@pytest.mark.parametrize("env_id", list(ENV_IDS))
def test_same_seed_same_trajectory_different_seed_different(env_id):
    def play(seed):
        env = gym.make(env_id)
        obs, _ = env.reset(seed=seed)
        out, acts = [obs], np.random.default_rng(0).integers(0, env.action_space.n, 200)
        for a in acts:
            obs, r, term, trunc, _ = env.step(int(a))
            out.append(obs)
            if term or trunc:
                obs, _ = env.reset()
                out.append(obs)
        return np.stack(out)

    a, b, c = play(1), play(1), play(2)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
