"""What a user's Gymnasium code returns, checked against what it declares
(docs/gymnasium.md#when-your-code-fails): each function returns ``None`` when the value is fine,
else the words after ``returned`` in a one-line :class:`~taskvar_torch.guest.UserCodeError`. Cheap:
run at every reset and step.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from gymnasium import spaces

from taskvar_torch.guest import short

_NUMBER = (int, float, np.integer, np.floating)


def _box(space: spaces.Box, obs: Any, where: str) -> str | None:
    if not isinstance(obs, (np.ndarray, np.generic)):
        return f"{where}{type(obs).__name__} {_cut(obs)}, not a numpy array of {space}"
    if obs.shape != space.shape:
        return f"{where}shape {obs.shape}, the observation space's is {space.shape} ({space})"
    if obs.dtype != space.dtype:
        return (
            f"{where}dtype {obs.dtype}, the observation space's is {space.dtype} ({space}): "
            f"return obs.astype(np.{space.dtype}) or declare that dtype"
        )
    return None  # its values' finiteness: once per batch, on the encoded batch (.env)


def _discrete(space: spaces.Discrete, obs: Any, where: str) -> str | None:
    ok = isinstance(obs, (int, np.integer)) and not isinstance(obs, (bool, np.bool_))
    if isinstance(obs, np.ndarray):
        ok = obs.shape == () and obs.dtype.kind in "iu"
    if not ok or not space.start <= int(obs) < space.start + space.n:
        return f"{where}{_cut(obs)} ({type(obs).__name__}), not an element of {space}"
    return None


def _multi(space: spaces.MultiDiscrete | spaces.MultiBinary, obs: Any, where: str) -> str | None:
    if not isinstance(obs, np.ndarray) or obs.shape != space.shape or obs.dtype.kind not in "iub":
        got = (
            f"shape {obs.shape} {obs.dtype}" if isinstance(obs, np.ndarray) else type(obs).__name__
        )
        return f"{where}{got} {_cut(obs)}, not an element of {space}"
    if not space.contains(obs):
        return f"{where}{_cut(obs)}, not an element of {space}"
    return None


def observation_problem(space: spaces.Space, obs: Any, where: str = "") -> str | None:
    """What is wrong with ``obs`` as an element of ``space`` (``None``: nothing): type, shape,
    dtype, a discrete value outside the space, part by part (``where``); ``Box`` bounds and foreign
    spaces are not checked.
    """
    if isinstance(space, spaces.Box):
        return _box(space, obs, where)
    if isinstance(space, spaces.Discrete):
        return _discrete(space, obs, where)
    if isinstance(space, (spaces.MultiDiscrete, spaces.MultiBinary)):
        return _multi(space, obs, where)
    if isinstance(space, spaces.Dict):
        if not isinstance(obs, dict) or set(obs) != set(space.spaces):
            got = sorted(obs) if isinstance(obs, dict) else type(obs).__name__
            return f"{where}{got}, not a dict of the observation space's keys {list(space.spaces)}"
        for k, sub in space.spaces.items():
            if (problem := observation_problem(sub, obs[k], f"{where}[{k!r}] ")) is not None:
                return problem
        return None
    if isinstance(space, spaces.Tuple):
        if not isinstance(obs, tuple) or len(obs) != len(space.spaces):
            return f"{where}{type(obs).__name__}, not a tuple of {len(space.spaces)} parts"
        for i, sub in enumerate(space.spaces):
            if (problem := observation_problem(sub, obs[i], f"{where}[{i}] ")) is not None:
                return problem
        return None
    return None


def flag_problem(value: Any) -> str | None:
    """Anything but a bool (``bool``, ``numpy.bool_``, a 0-d bool array) or an integer 0 or 1."""
    if isinstance(value, (bool, np.bool_)):
        return None
    if isinstance(value, np.ndarray) and value.shape == () and value.dtype.kind in "biu":
        value = value.item()
    if isinstance(value, (int, np.integer)) and value in (0, 1):
        return None
    return f"{_cut(value)} ({type(value).__name__}), not a bool"


def number_problem(value: Any) -> str | None:
    """Anything but a finite real number (``int``, ``float``, a numpy scalar, a 0-d array)."""
    if isinstance(value, np.ndarray) and value.shape == () and value.dtype.kind in "biuf":
        value = value.item()
    if not isinstance(value, _NUMBER):
        return f"{_cut(value)} ({type(value).__name__}), not a number"
    if not math.isfinite(value):
        return f"{value!r}, not a finite number"
    return None


def _cut(value: Any) -> str:
    return short(value, 48)


__all__ = ["flag_problem", "number_problem", "observation_problem"]
