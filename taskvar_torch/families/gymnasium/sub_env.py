"""One sub-environment of a Gymnasium family: the user's env, its instance, and its options.

The vector env steps ``N`` of these (in this process, or one process each with ``vector=async``),
so everything that reads the user's env runs where the env lives: a reset installs the episode's
instance (CARL-style, through constructor keyword arguments, attributes set on ``env.unwrapped``
or ``reset(options=...)``), and every reset and step evaluates the options on the observation and
info and returns them, as one numpy array, in ``info["taskvar"]`` (the only info entry passed on:
the env's own entries may change from step to step, which the vector env's info merging does not
need to carry).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from taskvar_torch.families.gymnasium.options import Option

INSTANCE_VIA = ("kwargs", "attributes", "options")
"""How an instance reaches the user's env: ``kwargs``: ``make(instance)`` builds the env anew
whenever a sub-environment's instance changes (a string id: ``gym.make(id, **instance)``);
``attributes``: ``setattr(env.unwrapped, name, value)`` before each reset; ``options``:
``env.reset(seed=..., options=instance)``."""

INFO = "taskvar"
"""The info entry a sub-environment reports its options' evaluations in."""


def build(make: str | Callable[[dict], gym.Env], instance: dict, via: str) -> gym.Env:
    """The user's env: ``make(instance)``, or ``gym.make(make, **instance)`` (``**instance`` only
    under ``via="kwargs"``) for an env id."""
    if isinstance(make, str):
        return gym.make(make, **(instance if via == "kwargs" else {}))
    return make(instance)


class SubEnv(gym.Env):
    """Sub-environment ``index`` of a Gymnasium family's vector env (a ``gym.Env`` wrapping the
    user's, which it rebuilds when an instance under ``via="kwargs"`` changes).

    Its ``reset`` reads the episode's instance from ``options["taskvar"][index]`` (the vector env
    passes one ``options`` to every sub-environment).
    """

    def __init__(
        self,
        index: int,
        make: str | Callable[[dict], gym.Env],
        via: str,
        instance: dict,
        options: Sequence[Option],
        state_info: Callable[[gym.Env], dict] | None,
    ):
        self.index, self.make, self.via = int(index), make, via
        self.options, self.state_info = tuple(options), state_info
        self.env = build(make, instance, via)
        self.instance = dict(instance)
        self.observation_space = self.env.observation_space
        self.action_space = self.env.action_space
        self.metadata = getattr(self.env, "metadata", {})

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        instance = dict((options or {})[INFO][self.index])
        if self.via == "kwargs" and instance != self.instance:
            self.env.close()
            self.env = build(self.make, instance, self.via)
        elif self.via == "attributes":
            for name, value in instance.items():
                setattr(self.env.unwrapped, name, value)
        self.instance = instance
        obs, info = self.env.reset(seed=seed, options=instance if self.via == "options" else None)
        return obs, self.report(obs, info, None)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, reward, terminated, truncated, self.report(obs, info, reward)

    def report(self, obs: Any, info: dict, reward: float | None) -> dict:
        """``{"taskvar": x}``, ``x`` a ``(3 O,)`` float64 array: the options' initiation and
        termination at ``(obs, info)`` (0/1), then the subtask rewards of the transition that
        arrived there (zeros after a reset). One flat array: the vector env merges it cheaply."""
        if self.state_info is not None:
            info = {**info, **self.state_info(self.env.unwrapped)}
        opts = self.options
        out = np.zeros(3 * len(opts))
        for j, o in enumerate(opts):
            out[j] = bool(o.initiation(obs, info))
            out[len(opts) + j] = bool(o.termination(obs, info))
            if reward is not None:
                out[2 * len(opts) + j] = float(o.reward(obs, info, float(reward)))
        return {INFO: out}

    def close(self):
        self.env.close()


__all__ = ["INFO", "INSTANCE_VIA", "SubEnv", "build"]
