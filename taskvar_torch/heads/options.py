"""Option heads Q_o(s, a) (paper §3.2, capabilities as offline options).

One network outputs every option's action values ``(B, O, A)``; greedy in ``Q_o`` is the option
policy pi^o. Each option learns by double DQN on its own subtask reward, with its own termination
beta_o as episode end, from every sampled transition whose state lies in its initiation set I_o:

    y_o = r_o + gamma * (1 - max(terminated, beta_o(s'))) * Q_o,target(s', argmax_a' Q_o(s', a'))

The transitions come from any behaviour (off-policy), so all options learn from the same sample.
"""

from __future__ import annotations

import torch

from taskvar_torch.heads.relabel import Transitions
from taskvar_torch.heads.targets import bootstrap_value, masked_mean


def option_greedy_actions(q_options: torch.Tensor) -> torch.Tensor:
    """pi^o(s) for every option: ``(B, O, A) -> (B, O)`` int64 (ties: lowest action)."""
    return q_options.argmax(-1)


def options_loss(
    q: torch.Tensor,  # (B, O, A) online Q_o(s, .)
    q_next: torch.Tensor,  # (B, O, A) online Q_o(s', .), no gradient
    q_next_target: torch.Tensor,  # (B, O, A) target Q_o(s', .)
    batch: Transitions,
    gamma: float,
    double_q: bool = True,
    q_far: torch.Tensor | None = None,  # (B, O, A) online Q_o(s_{t+k}, .) with n-step windows
    q_far_target: torch.Tensor | None = None,  # (B, O, A) target Q_o(s_{t+k}, .)
) -> torch.Tensor:
    """Sum over options of each option's mean squared TD error over its initiation set (scalar);
    with ``batch.nstep``, option o's n-step target on the rows its own episodes made."""
    num_options = q.shape[1]
    action = batch.action.view(-1, 1, 1).expand(-1, num_options, 1)  # (B, O, 1)
    q_taken = q.gather(-1, action).squeeze(-1)  # (B, O)
    with torch.no_grad():
        done = torch.maximum(batch.terminated.unsqueeze(-1), batch.beta_next)  # (B, O)
        target = batch.subtask_reward + gamma * (1.0 - done) * bootstrap_value(
            q_next, q_next_target, double_q
        )  # (B, O)
        w = batch.nstep
        if w is not None and q_far is not None:
            far_done = torch.maximum(w.terminated.unsqueeze(-1), w.beta)  # (B, O)
            far = w.subtask_reward + w.discount.unsqueeze(-1) * (1.0 - far_done) * bootstrap_value(
                q_far, q_far_target, double_q
            )
            target = torch.where(w.option_rows, far, target)
    return masked_mean((q_taken - target).pow(2), batch.initiation, batch.seeds)
