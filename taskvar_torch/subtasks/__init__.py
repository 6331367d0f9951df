"""Subtasks (capabilities) as data: initiation, termination, subtask and robustness rewards.

Every family exposes a :class:`Subtasks` object whose methods are vectorised over a batch of
transitions, so one stream of raw transitions can be relabelled for every option head.
"""

from taskvar_torch.subtasks.base import Hierarchy, Subtasks
from taskvar_torch.subtasks.wargus import WargusSubtasks
from taskvar_torch.subtasks.windy import WindySubtasks

__all__ = ["Hierarchy", "Subtasks", "WargusSubtasks", "WindySubtasks"]
