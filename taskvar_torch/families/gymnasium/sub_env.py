"""One sub-environment of a Gymnasium family: the user's env, its instance, and its options.

The vector env steps ``N`` of these (in this process, or one process each with ``vector=async``),
so everything that reads the user's env runs where the env lives: a reset installs the episode's
instance (CARL-style, through constructor keyword arguments, attributes set on ``env.unwrapped``
or ``reset(options=...)``), and every reset and step evaluates the options on the observation and
info and returns them, with the ``instance_info`` read after the reset, as one numpy array in
``info["taskvar"]`` (the only info entry passed on: the env's own entries may change from step
to step, which the vector env's info merging does not need to carry).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

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
    user's, which it rebuilds when an instance under ``instance_via="kwargs"`` changes).

    Args:
        index: its place in the vector env.
        adapter: the family's :class:`~taskvar_torch.families.gymnasium.family.GymAdapter`
            (``make``, ``instance_via``, ``options``, ``state_info``, ``instance_info``).
        instance: the instance the env is built with (each reset installs the episode's own).

    Its ``reset`` reads the episode's instance from ``options["taskvar"][index]`` (the vector env
    passes one ``options`` to every sub-environment).
    """

    def __init__(self, index: int, adapter: Any, instance: dict):
        self.index, self.adapter, self.via = int(index), adapter, adapter.instance_via
        self.env = build(adapter.make, instance, self.via)
        self.instance = dict(instance)
        self.observation_space = self.env.observation_space
        self.action_space = self.env.action_space
        self.metadata = getattr(self.env, "metadata", {})
        self.hidden = np.zeros(0)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        instance = dict((options or {})[INFO][self.index])
        if self.via == "kwargs" and instance != self.instance:
            self.env.close()
            self.env = build(self.adapter.make, instance, self.via)
        elif self.via == "attributes" and getattr(self.adapter, "apply", None) is not None:
            self.adapter.apply(self.env.unwrapped, instance)  # the family's own installation
        elif self.via == "attributes":
            env = self.env.unwrapped
            for name, value in instance.items():
                if not hasattr(env, name):  # a misspelt key would set a new attribute: no variation
                    raise ValueError(
                        f"instance key {name!r} is not an attribute of {type(env).__name__} "
                        f"(instance_via='attributes' sets existing ones only)"
                    )
                setattr(env, name, value)
        self.instance = instance
        obs, info = self.env.reset(seed=seed, options=instance if self.via == "options" else None)
        self.hidden = np.array(list(self.instance_info().values()), dtype=np.float64)
        return obs, self.report(obs, info, None)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, reward, terminated, truncated, self.report(obs, info, reward)

    def instance_info(self) -> dict[str, float]:
        """What each function of ``adapter.instance_info`` reads of the env just reset."""
        env = self.env.unwrapped
        return {name: float(read(env)) for name, read in self.adapter.instance_info.items()}

    def given_action(self, option: Any, obs: Any, info: dict) -> int:
        """The action index (from 0) of ``option``'s given policy at ``(obs, info)``; anything
        but an action of the env's ``Discrete`` space is a one-line ``ValueError`` naming the
        option."""
        a = option.policy(obs, info)
        space = self.action_space
        ok = isinstance(a, (int, np.integer)) or (
            isinstance(a, np.ndarray) and a.shape == () and np.issubdtype(a.dtype, np.integer)
        )
        if not ok or isinstance(a, bool) or not space.contains(np.int64(a)):
            raise ValueError(
                f"option {option.name!r}: policy(obs, info) returned {a!r} "
                f"({type(a).__name__}), not an action of {space} (an int in [{space.start}, "
                f"{space.start + space.n - 1}])"
            )
        return int(a) - int(space.start)

    def report(self, obs: Any, info: dict, reward: float | None) -> dict:
        """``{"taskvar": x}``, ``x`` a ``(5 O + H,)`` float64 array: the options' initiation and
        termination at ``(obs, info)`` (0/1), the subtask rewards of the transition that arrived
        there (zeros after a reset), the given policies' actions there (-1 for a learnt option),
        the robustness rewards of that transition (zeros where an option has none), then the
        episode's ``H`` values of ``instance_info``. One flat array: the vector env merges it
        cheaply."""
        state_info = self.adapter.state_info
        if state_info is not None:
            info = {**info, **state_info(self.env.unwrapped)}
        opts = self.adapter.options
        O = len(opts)  # noqa: E741
        out = np.zeros(5 * O + self.hidden.size)
        for j, o in enumerate(opts):
            out[j] = bool(o.initiation(obs, info))
            out[O + j] = bool(o.termination(obs, info))
            if reward is not None:
                out[2 * O + j] = float(o.reward(obs, info, float(reward)))
            out[3 * O + j] = -1 if o.policy is None else self.given_action(o, obs, info)
            if reward is not None and o.robustness is not None:
                out[4 * O + j] = float(o.robustness(obs, info, float(reward)))
        out[5 * O :] = self.hidden
        return {INFO: out}

    def close(self):
        self.env.close()


__all__ = ["INFO", "INSTANCE_VIA", "SubEnv", "build"]
