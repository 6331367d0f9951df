"""Input checks shared by the families' envs: one wording for a malformed action, reset option,
instance or start cell. Each raises a one-line ``ValueError`` naming the argument and returns the
cleaned value, so ``reset`` can validate everything before it changes any state.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch


def as_int(value: Any) -> int | None:
    """``value`` as a Python int when it is an integral number (``3``, ``np.int64(3)``, ``3.0``,
    a one-element integer array or tensor), else ``None`` (bools, NaN, ``None``, lists, strings)."""
    if isinstance(value, (bool, np.bool_)):
        return None
    if isinstance(value, (np.ndarray, torch.Tensor)):
        if value.ndim != 0 or value.dtype in (torch.bool, np.bool_):
            return None
        value = value.item()
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real) and math.isfinite(value) and float(value).is_integer():
        return int(value)
    return None


def check_action(action: Any, num_actions: int) -> int:
    """The action as an int in ``[0, num_actions)``; ``ValueError`` for anything else."""
    a = as_int(action)
    if a is None or not 0 <= a < num_actions:
        raise ValueError(f"action must be in [0, {num_actions - 1}] (an integer), got {action!r}")
    return a


def check_reset_options(options: Any, allowed: Sequence[str]) -> dict[str, Any]:
    """``options`` of ``reset`` as a dict holding only ``allowed`` keys (``None``: empty)."""
    if options is None:
        return {}
    if not isinstance(options, Mapping):
        raise ValueError(
            f"reset options must be a dict with keys from {list(allowed)}, got {options!r}"
        )
    unknown = sorted(map(str, set(options) - set(allowed)))
    if unknown:
        raise ValueError(f"unknown reset option(s) {unknown}; allowed: {list(allowed)}")
    return dict(options)


def check_fields(value: Any, name: str, allowed: Sequence[str]) -> dict[str, Any]:
    """A dict option (e.g. ``options["instance"]``) holding only ``allowed`` keys."""
    if not isinstance(value, Mapping):
        raise ValueError(
            f'options["{name}"] must be a dict with keys from {list(allowed)}, got {value!r}'
        )
    unknown = sorted(map(str, set(value) - set(allowed)))
    if unknown:
        raise ValueError(f"unknown {name} field(s) {unknown}; allowed: {list(allowed)}")
    return dict(value)


def check_probability(value: Any, name: str) -> float:
    """A real number in ``[0, 1]`` (not a bool, not NaN)."""
    ok = isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))
    if not ok or not 0.0 <= float(value) <= 1.0:  # NaN fails the comparison
        raise ValueError(f"{name} must be in [0, 1] (a number), got {value!r}")
    return float(value)


def check_cell(value: Any, height: int, width: int, name: str = "start") -> tuple[int, int]:
    """A ``(row, col)`` pair of integers inside a ``height x width`` grid."""
    pair = None
    if isinstance(value, (Sequence, np.ndarray, torch.Tensor)) and not isinstance(value, str):
        if len(value) == 2:
            pair = (as_int(value[0]), as_int(value[1]))
    if pair is None or None in pair:
        raise ValueError(f"{name} must be a (row, col) pair of integers, got {value!r}")
    r, c = pair
    if not (0 <= r < height and 0 <= c < width):
        raise ValueError(
            f"{name} must be a (row, col) inside {height}x{width} (row in [0, {height - 1}], "
            f"col in [0, {width - 1}]), got {value!r}"
        )
    return r, c


def check_as_config(family: str, section: Mapping[str, Any], instances: Any = None) -> None:
    """A Gymnasium env's constructor arguments checked as the config's ``env.<family>`` keys are
    (the same bounds and memory estimate); a one-line ``ValueError`` names the argument by its
    config key.
    """
    from taskvar_torch.config import config_from_dict
    from taskvar_torch.config.memory import check_memory, estimate

    plain = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in section.items()}
    env: dict[str, Any] = {"num_envs": 1, family: plain}
    if isinstance(instances, str):
        env["instances"] = instances
    source = f"the {family} env's arguments, checked as config keys"
    try:
        cfg = config_from_dict({"family": family, "env": env}, source)
        table = f"env.{family}"
        check_memory({table: estimate(cfg, training=False).get(table, 0)})
    except ValueError as e:
        msg = str(e).strip().splitlines()[0]
        raise ValueError(msg if source in msg else f"{msg} ({source})") from None
