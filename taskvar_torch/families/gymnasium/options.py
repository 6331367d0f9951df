"""Options of a Gymnasium family as plain functions of an observation and its info (paper §3.2;
docs/gymnasium.md#your-own-controllers-as-options), evaluated beside the env (:mod:`.sub_env`) and
read back as batched ``(B, O)`` tensors by :class:`GymSubtasks`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase

from taskvar_torch import keys
from taskvar_torch.subtasks.base import Hierarchy, Subtasks

SUBTASK = "subtask"
"""The tensordict entry holding the options' evaluations: ``("subtask", "initiation")`` and
``("subtask", "termination")`` ``(N, O)`` bool, ``("subtask", "reward")`` ``(N, O)`` float and,
where an option has a given policy, ``("subtask", "given_action")`` ``(N, O)`` int64 (its action,
as an index from 0; -1 for a learnt option)."""


def _always(obs: Any, info: dict) -> bool:
    return True


def _never(obs: Any, info: dict) -> bool:
    return False


def _env_reward(obs: Any, info: dict, reward: float) -> float:
    return float(reward)


@dataclass(frozen=True)
class Option:
    """One option, by its functions of one sub-environment's observation and info.

    Attributes:
        name: the option's name.
        initiation: ``(obs, info) -> bool``, in the initiation set (default: always).
        termination: ``(obs, info) -> bool``, the option ends there (default: never).
        reward: ``(obs, info, reward) -> float``, the subtask reward (default: the env's).
        policy: ``(obs, info) -> action``, a given controller the option acts by; ``None``: learnt.
        robustness: ``(obs, info, reward) -> float``, the robustness reward (paper §3.4.3); needed
            by every option of a declared ``hierarchy``.
    """

    name: str
    initiation: Callable[[Any, dict], bool] = _always
    termination: Callable[[Any, dict], bool] = _never
    reward: Callable[[Any, dict, float], float] = _env_reward
    policy: Callable[[Any, dict], Any] | None = None
    robustness: Callable[[Any, dict, float], float] | None = None

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"Option name must be a non-empty string, got {self.name!r}")
        for field in ("initiation", "termination", "reward"):
            if not callable(getattr(self, field)):
                raise ValueError(f"Option {self.name!r}: {field} must be callable")
        if self.robustness is not None and not callable(self.robustness):
            raise ValueError(f"Option {self.name!r}: robustness must be callable or None")
        if self.policy is not None and not callable(self.policy):
            raise ValueError(
                f"Option {self.name!r}: policy must be callable (obs, info) -> action or None, "
                f"got {type(self.policy).__name__}"
            )


class GymSubtasks(Subtasks):
    """The options of a Gymnasium family, read from the ``("subtask", ...)`` entries its env
    writes (no option logic here: it ran beside the env)."""

    def __init__(self, names: tuple[str, ...], given: tuple[bool, ...] | None = None):
        self.names = tuple(names)
        self.given = tuple(given) if given is not None and any(given) else None

    def initiation(self, td: TensorDictBase) -> torch.Tensor:
        return td.get((SUBTASK, "initiation"))

    def termination(self, td: TensorDictBase) -> torch.Tensor:
        return td.get((SUBTASK, "termination"))

    def reward(self, td: TensorDictBase) -> torch.Tensor:
        return td.get((keys.NEXT, SUBTASK, "reward"))

    def given_actions(self, td: TensorDictBase) -> torch.Tensor | None:
        return None if self.given is None else td.get((SUBTASK, "given_action"))


class GymHierarchySubtasks(GymSubtasks):
    """The options of a Gymnasium family that declares a composition hierarchy (paper §3.4.2):
    its tree, and the robustness rewards its options' functions gave beside the env."""

    def __init__(self, names, given, hierarchy: Hierarchy):
        super().__init__(names, given)
        self.hierarchy = hierarchy

    def robustness_reward(self, td: TensorDictBase) -> torch.Tensor:
        return td.get((keys.NEXT, SUBTASK, "robustness"))


__all__ = ["SUBTASK", "GymHierarchySubtasks", "GymSubtasks", "Option"]
