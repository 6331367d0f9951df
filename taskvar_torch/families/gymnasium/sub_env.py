"""One sub-environment of a Gymnasium family: the user's env, its instance and its options, all
evaluated where the env lives and returned as one array in ``info["taskvar"]``.
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
    """Sub-environment ``index`` of a Gymnasium family's vector env, wrapping the user's env
    (rebuilt when a ``kwargs`` instance changes) for ``adapter``; its ``reset`` reads the episode's
    instance from ``options["taskvar"][index]``. Every call into user code goes through
    :func:`~taskvar_torch.guest.guest` and is checked (:mod:`.returns`).
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
        self._calls = self._option_calls(adapter.options)
        O, H = len(adapter.options), len(adapter.instance_info)  # noqa: E741
        self._blank = np.zeros(5 * O + H)  # report's array before the calls: -1 for learnt ones
        self._blank[3 * O : 4 * O] = [-1 if o.policy is None else 0 for o in adapter.options]

    def _where(self, obs: Any = _NONE) -> str:
        at = f"sub-environment {self.index}, " + ("reset" if self.t == 0 else f"step {self.t}")
        return at if obs is _NONE else f"{at}, observation {short(obs)}"

    def _call(
        self, what: str, fn: Callable[..., Any], *args: Any, obs: Any = _NONE, **kwargs: Any
    ) -> Any:
        return guest(self.family, what, fn, *args, where=lambda: self._where(obs), **kwargs)

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

    def _option_calls(self, opts: Any) -> list[tuple[int, str, str, Callable[..., Any]]]:
        """Each option function's place in :meth:`report`'s array, what it returns (``flag``,
        ``number``, ``action``), its name in a failure's line, and the function, in the order
        they are called."""
        O = len(opts)  # noqa: E741
        calls = []
        for j, o in enumerate(opts):
            calls += [
                (j, "flag", f"option {o.name!r} initiation(obs, info)", o.initiation),
                (O + j, "flag", f"option {o.name!r} termination(obs, info)", o.termination),
                (2 * O + j, "number", f"option {o.name!r} reward(obs, info, reward)", o.reward),
            ]
            if o.policy is not None:
                calls.append(
                    (3 * O + j, "action", f"option {o.name!r} policy(obs, info)", o.policy)
                )
            if o.robustness is not None:
                what = f"option {o.name!r} robustness(obs, info, reward)"
                calls.append((4 * O + j, "number", what, o.robustness))
        return calls

    def _given_action(self, what: str, policy: Callable, obs: Any, info: dict, where) -> int:
        """The action index (from 0) of a given policy at ``(obs, info)``; anything but an action
        of the env's ``Discrete`` action space is a one-line ``UserCodeError`` naming the
        option."""
        a = guest(self.family, what, policy, obs, info, where=where)
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
        """``{"taskvar": x}``, ``x`` a ``(5 O + H,)`` float64 array: initiation, termination,
        subtask rewards, given actions and robustness rewards of the options, then the ``H``
        ``instance_info`` values; each value checked.
        """
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
        out = self._blank.copy()
        family, r = self.family, None if reward is None else float(reward)

        def where() -> str:
            return self._where(obs)

        for k, kind, what, fn in self._calls:  # (index in out, kind, function's name, function)
            if kind == "flag":
                value = guest(family, what, fn, obs, info, where=where)
                if (problem := flag_problem(value)) is not None:
                    self._refuse(what, problem, obs)
                out[k] = bool(value)
            elif kind == "number":
                if r is None:
                    continue  # after a reset: no transition, no subtask reward
                value = guest(family, what, fn, obs, info, r, where=where)
                if (problem := number_problem(value)) is not None:
                    self._refuse(what, problem, obs)
                out[k] = float(value)
            else:
                out[k] = self._given_action(what, fn, obs, info, where)
        out[out.size - self.hidden.size :] = self.hidden
        return {INFO: out}

    def close(self):
        guest(self.family, "env.close()", self.env.close, where=f"sub-environment {self.index}")


__all__ = ["INFO", "INSTANCE_VIA", "SubEnv", "build"]
