"""Small tensor helpers shared by the head losses: double-Q bootstraps, masked means, expectiles."""

from __future__ import annotations

import torch


def bootstrap_value(
    q_next_online: torch.Tensor,  # (..., A)
    q_next_target: torch.Tensor,  # (..., A)
    double_q: bool = True,
) -> torch.Tensor:
    """Value of the next state for a Q-learning target, ``(...)``.

    Double Q-learning (van Hasselt et al., 2016): the online network picks ``a*``, the target network
    evaluates it; otherwise ``max_a Q_target``. Matches TorchRL ``DQNLoss(double_dqn=...)``.
    """
    if double_q:
        best = q_next_online.argmax(-1, keepdim=True)  # (..., 1)
        return q_next_target.gather(-1, best).squeeze(-1)
    return q_next_target.max(-1).values


def masked_mean(loss: torch.Tensor, mask: torch.Tensor, seeds: int = 1) -> torch.Tensor:
    """Per-column mean of ``loss (B, K)`` over rows where ``mask (B, K)``, summed over columns (K
    separate learners; an empty column contributes 0); with ``seeds = S`` per seed-major group,
    summed.
    """
    mask = mask.to(loss.dtype)
    if seeds > 1:
        B = loss.shape[0]
        num = (loss * mask).reshape(seeds, B // seeds, -1).sum(1)  # (S, K)
        den = mask.reshape(seeds, B // seeds, -1).sum(1).clamp_min(1.0)
        return (num / den).sum()
    return ((loss * mask).sum(0) / mask.sum(0).clamp_min(1.0)).sum()


def group_mean(loss: torch.Tensor, seeds: int = 1) -> torch.Tensor:
    """Mean of ``loss`` (B,); ``seeds = S``: the sum of the means of its ``S`` seed-major groups."""
    if seeds > 1:
        return loss.reshape(seeds, -1).mean(1).sum()
    return loss.mean()


def expectile_loss(pred: torch.Tensor, target: torch.Tensor, level: float) -> torch.Tensor:
    """Elementwise expectile loss ``|level - 1[target < pred]| (target - pred)^2`` (Newey & Powell,
    1987).
    """
    diff = target - pred
    weight = torch.where(diff < 0, 1.0 - level, level)
    return weight * diff.pow(2)
