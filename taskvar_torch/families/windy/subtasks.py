"""Windy capabilities (paper §3.3.1): one ``exit_*`` option per exit of the wall."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from taskvar_torch import keys
from taskvar_torch.families.windy.dynamics import WindyModel
from taskvar_torch.subtasks.base import Subtasks


class WindySubtasks(Subtasks):
    """Exit options: option k reaches the goal side through exit k; initiation everywhere off the
    goal, termination on the goal, subtask reward -1 a step plus ``-wrong_exit_penalty`` through
    another exit."""

    def __init__(
        self, model: WindyModel, wrong_exit_penalty: float = 100.0, obs_encoding: str = "onehot"
    ):
        self.model = model
        self.obs_encoding = obs_encoding
        self.names = model.layout.exit_names
        self.wrong_exit_penalty = float(wrong_exit_penalty)
        self._option_ids = torch.arange(len(self.names), device=model.device)

    def initiation(self, td: TensorDictBase) -> torch.Tensor:
        ok = ~self.model.is_goal[td.get(keys.CELL)]  # (B,)
        return ok.unsqueeze(-1).expand(*ok.shape, self.num_options)

    def termination(self, td: TensorDictBase) -> torch.Tensor:
        done = self.model.is_goal[td.get(keys.CELL)]  # (B,)
        return done.unsqueeze(-1).expand(*done.shape, self.num_options)

    def reward(self, td: TensorDictBase) -> torch.Tensor:
        cell = td.get(keys.CELL)  # (B,)
        arrived = self.model.is_goal[td.get((keys.NEXT, keys.CELL))]  # (B,)
        exit_used = self.model.exit_id[cell]  # (B,): the exit cell the agent left from, or -1
        wrong = arrived.unsqueeze(-1) & (exit_used.unsqueeze(-1) != self._option_ids)  # (B, O)
        return -1.0 - self.wrong_exit_penalty * wrong.to(torch.float32)

    def option_input_mask(self, obs_dim: int) -> torch.Tensor | None:
        """With the ``exits_patch`` observation: option k sees the coordinates, the local patch and
        its own exit's offset (the last ``2 x exits`` features hold every exit's offset); ``None``
        for the other encodings (no per-option features)."""
        if self.obs_encoding != "exits_patch":
            return None
        n = self.num_options
        first = obs_dim - 2 * n  # where the exits' offsets start
        mask = torch.ones(n, obs_dim)
        mask[:, first:] = 0.0
        for k in range(n):
            mask[k, first + 2 * k : first + 2 * k + 2] = 1.0
        return mask
