"""Subtasks (capabilities) as data: initiation, termination, subtask and robustness rewards.

Every family exposes a :class:`Subtasks` object whose methods are vectorised over a batch of
transitions, so one stream of raw transitions can be relabelled for every option head. The
families' own subtasks live in their packages (``taskvar_torch.families.<name>.subtasks``).
"""

from taskvar_torch.subtasks.base import Hierarchy, Subtasks

__all__ = ["Hierarchy", "Subtasks"]
