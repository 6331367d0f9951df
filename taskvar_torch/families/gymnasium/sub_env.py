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

import functools
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

from taskvar_torch.families.gymnasium.returns import (
    flag_problem,
    number_problem,
    observation_problem,
)
from taskvar_torch.guest import guest, short, user_error

INSTANCE_VIA = ("kwargs", "attributes", "options")
"""How an instance reaches the user's env: ``kwargs``: ``make(instance)`` builds the env anew
whenever a sub-environment's instance changes (a string id: ``gym.make(id, **instance)``);
``attributes``: ``setattr(env.unwrapped, name, value)`` before each reset; ``options``:
``env.reset(seed=..., options=instance)``."""

INFO = "taskvar"
"""The info entry a sub-environment reports its options' evaluations in."""

_NONE = object()  # no observation to name


def build(make: str | Callable[[dict], gym.Env], instance: dict, via: str, family: str) -> gym.Env:
    """The user's env: ``make(instance)``, or ``gym.make(make, **instance)`` (``**instance`` only
    under ``via="kwargs"``) for an env id; a failure is a one-line
    :class:`~taskvar_torch.guest.UserCodeError` naming the instance."""
    where = f"instance {short(instance)}"
    if isinstance(make, str):
        kwargs = instance if via == "kwargs" else {}
        what = f"gym.make({make!r}, **instance)"
        return guest(family, what, functools.partial(gym.make, make, **kwargs), where=where)
    return guest(family, "make(instance)", make, instance, where=where)


class SubEnv(gym.Env):
    """Sub-environment ``index`` of a Gymnasium family's vector env (a ``gym.Env`` wrapping the
    user's, which it rebuilds when an instance under ``instance_via="kwargs"`` changes).

    Args:
        index: its place in the vector env.
        adapter: the family's :class:`~taskvar_torch.families.gymnasium.family.GymAdapter`
            (``name``, ``make``, ``instance_via``, ``options``, ``state_info``,
            ``instance_info``).
        instance: the instance the env is built with (each reset installs the episode's own).

    Its ``reset`` reads the episode's instance from ``options["taskvar"][index]`` (the vector env
    passes one ``options`` to every sub-environment). Every call into the user's code goes through
    :func:`~taskvar_torch.guest.guest`, and what it returns is checked (:mod:`.returns`): a
    failure or a mismatch is one line naming the family, the function, the sub-environment, the
    step and the observation (docs/gymnasium.md, "When your code fails").
    """

    def __init__(self, index: int, adapter: Any, instance: dict):
        self.index, self.adapter, self.via = int(index), adapter, adapter.instance_via
        self.family = adapter.name
        self.env = build(adapter.make, instance, self.via, self.family)
        self.instance = dict(instance)
        self.observation_space = self.env.observation_space
        self.action_space = self.env.action_space
        self.metadata = getattr(self.env, "metadata", {})
        self.hidden = np.zeros(0)
        self.t = 0  # steps since the last reset (named in a failure's line)

    def _where(self, obs: Any = _NONE) -> str:
        at = f"sub-environment {self.index}, " + ("reset" if self.t == 0 else f"step {self.t}")
        return at if obs is _NONE else f"{at}, observation {short(obs)}"

    def _call(
        self, what: str, fn: Callable[..., Any], *args: Any, obs: Any = _NONE, **kwargs: Any
    ) -> Any:
        return guest(self.family, what, fn, *args, where=self._where(obs), **kwargs)

    def _refuse(self, what: str, problem: str | None, obs: Any = _NONE) -> None:
        if problem is not None:
            raise user_error(self.family, what, f"returned {problem}", self._where(obs))

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        instance = dict((options or {})[INFO][self.index])
        self.t = 0
        if self.via == "kwargs" and instance != self.instance:
            self._call("env.close()", self.env.close)
            self.env = build(self.adapter.make, instance, self.via, self.family)
        elif self.via == "attributes" and getattr(self.adapter, "apply", None) is not None:
            self._call("apply(env, instance)", self.adapter.apply, self.env.unwrapped, instance)
        elif self.via == "attributes":
            env = self.env.unwrapped
            for name, value in instance.items():
                if not hasattr(env, name):  # a misspelt key would set a new attribute: no variation
                    raise user_error(
                        self.family,
                        f"instance key {name!r}",
                        f"is not an attribute of {type(env).__name__} (instance_via='attributes' "
                        "sets existing ones only)",
                        self._where(),
                    )
                self._call(f"setattr(env, {name!r}, value)", setattr, env, name, value)
        self.instance = instance
        out = self._call(
            "env.reset(seed, options)",
            self.env.reset,
            seed=seed,
            options=instance if self.via == "options" else None,
        )
        obs, info = self._unpack("env.reset(seed, options)", out, 2)
        self.hidden = np.array(list(self.instance_info().values()), dtype=np.float64)
        return obs, self.report(obs, info, None)

    def step(self, action):
        self.t += 1  # the step being taken, named in a failure's line
        out = self._call("env.step(action)", self.env.step, action)
        obs, reward, terminated, truncated, info = self._unpack("env.step(action)", out, 5)
        for name, value in (("terminated", terminated), ("truncated", truncated)):
            if (problem := flag_problem(value)) is not None:
                self._refuse("env.step(action)", f"{name}={problem}", obs)
        if (problem := number_problem(reward)) is not None:
            self._refuse("env.step(action)", f"reward={problem}", obs)
        return obs, reward, terminated, truncated, self.report(obs, info, reward)

    def _unpack(self, what: str, out: Any, n: int) -> tuple:
        """The ``n``-tuple ``out`` of ``env.reset`` / ``env.step``, its observation checked against
        the observation space and its info a dict."""
        if not isinstance(out, tuple) or len(out) != n:
            got = f"a tuple of {len(out)}" if isinstance(out, tuple) else type(out).__name__
            self._refuse(
                what,
                f"{got}, not ({'obs, info' if n == 2 else 'obs, reward, terminated, truncated, info'})",
            )
        obs, info = out[0], out[-1]
        problem = observation_problem(self.observation_space, obs, "an observation of ")
        self._refuse(what, problem)
        if not isinstance(info, dict):
            self._refuse(what, f"info {short(info, 48)} ({type(info).__name__}), not a dict", obs)
        return out

    def instance_info(self) -> dict[str, float]:
        """What each function of ``adapter.instance_info`` reads of the env just reset."""
        env, out = self.env.unwrapped, {}
        for name, read in self.adapter.instance_info.items():
            what = f"instance_info[{name!r}](env)"
            value = self._call(what, read, env)
            self._refuse(what, number_problem(value))
            out[name] = float(value)
        return out

    def given_action(self, option: Any, obs: Any, info: dict) -> int:
        """The action index (from 0) of ``option``'s given policy at ``(obs, info)``; anything
        but an action of the env's ``Discrete`` action space is a one-line ``UserCodeError``
        naming the option."""
        what = f"option {option.name!r} policy(obs, info)"
        a = self._call(what, option.policy, obs, info, obs=obs)
        space = self.action_space
        ok = isinstance(a, (int, np.integer)) or (
            isinstance(a, np.ndarray) and a.shape == () and np.issubdtype(a.dtype, np.integer)
        )
        if not ok or isinstance(a, bool) or not space.contains(np.int64(a)):
            self._refuse(
                what,
                f"{short(a, 48)} ({type(a).__name__}), not an action of {space} (an int in "
                f"[{space.start}, {space.start + space.n - 1}])",
                obs,
            )
        return int(a) - int(space.start)

    def report(self, obs: Any, info: dict, reward: float | None) -> dict:
        """``{"taskvar": x}``, ``x`` a ``(5 O + H,)`` float64 array: the options' initiation and
        termination at ``(obs, info)`` (0/1), the subtask rewards of the transition that arrived
        there (zeros after a reset), the given policies' actions there (-1 for a learnt option),
        the robustness rewards of that transition (zeros where an option has none), then the
        episode's ``H`` values of ``instance_info``. One flat array: the vector env merges it
        cheaply. Each function's value is checked: a bool, a finite number, an action."""
        state_info = self.adapter.state_info
        if state_info is not None:
            extra = self._call("state_info(env)", state_info, self.env.unwrapped, obs=obs)
            if not isinstance(extra, dict):
                self._refuse(
                    "state_info(env)",
                    f"{short(extra, 48)} ({type(extra).__name__}), not a dict",
                    obs,
                )
            info = {**info, **extra}
        opts = self.adapter.options
        O = len(opts)  # noqa: E741
        out = np.zeros(5 * O + self.hidden.size)
        call, refuse = self._call, self._refuse
        for j, o in enumerate(opts):
            for k, field in ((j, "initiation"), (O + j, "termination")):
                what = f"option {o.name!r} {field}(obs, info)"
                value = call(what, getattr(o, field), obs, info, obs=obs)
                if (problem := flag_problem(value)) is not None:
                    refuse(what, problem, obs)
                out[k] = bool(value)
            for k, field, fn in (
                (2 * O + j, "reward", o.reward),
                (4 * O + j, "robustness", o.robustness),
            ):
                if reward is None or fn is None:
                    continue
                what = f"option {o.name!r} {field}(obs, info, reward)"
                value = call(what, fn, obs, info, float(reward), obs=obs)
                if (problem := number_problem(value)) is not None:
                    refuse(what, problem, obs)
                out[k] = float(value)
            out[3 * O + j] = -1 if o.policy is None else self.given_action(o, obs, info)
        out[5 * O :] = self.hidden
        return {INFO: out}

    def close(self):
        guest(self.family, "env.close()", self.env.close, where=f"sub-environment {self.index}")


__all__ = ["INFO", "INSTANCE_VIA", "SubEnv", "build"]
