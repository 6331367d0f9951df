"""Averaging head Q_avg(s, a) (paper §3.1): DQN on the environment reward across instances.

Instances are redrawn at every reset, so Q-learning over the stream learns the value of the flat
*averaging policy* pi_bar, the baseline every other method is compared with.

Target (double DQN, identical to TorchRL ``DQNLoss(double_dqn=True)``; a test checks the two agree):

    y = r + gamma * (1 - terminated) * Q_target(s', argmax_a' Q(s', a'))
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict.nn import TensorDictModule

from taskvar_torch import keys
from taskvar_torch.heads.networks import make_head
from taskvar_torch.heads.relabel import Transitions
from taskvar_torch.heads.targets import bootstrap_value, group_mean


def make_averaging_head(
    obs_dim: int, num_actions: int, hidden: Sequence[int] = (64, 64), activation: str = "relu"
) -> TensorDictModule:
    """``observation (B, D) -> action_value (B, A)``."""
    return make_head(keys.ACTION_VALUE, obs_dim, num_actions, hidden, activation)


def averaging_loss(
    q: torch.Tensor,  # (B, A) online Q(s, .)
    q_next: torch.Tensor,  # (B, A) online Q(s', .), no gradient
    q_next_target: torch.Tensor,  # (B, A) target Q(s', .)
    batch: Transitions,
    gamma: float,
    double_q: bool = True,
    q_far: torch.Tensor | None = None,  # (B, A) online Q(s_{t+k}, .) with n-step windows
    q_far_target: torch.Tensor | None = None,  # (B, A) target Q(s_{t+k}, .)
) -> torch.Tensor:
    """Mean squared TD error of the averaging head (scalar); with ``batch.nstep``, the n-step
    target on the averaging-mode rows (heads/nstep.py)."""
    q_taken = q.gather(-1, batch.action.unsqueeze(-1)).squeeze(-1)  # (B,)
    with torch.no_grad():
        target = batch.reward + gamma * (1.0 - batch.terminated) * bootstrap_value(
            q_next, q_next_target, double_q
        )  # (B,)
        w = batch.nstep
        if w is not None and q_far is not None:
            far = w.reward + w.discount * (1.0 - w.terminated) * bootstrap_value(
                q_far, q_far_target, double_q
            )
            target = torch.where(w.averaging_rows, far, target)
    return group_mean((q_taken - target).pow(2), batch.seeds)
