"""Batched evaluation episodes and the statistics experiments report: :func:`run_episodes`
(defined with the envs, :mod:`taskvar_torch.envs.episodes`, and handed on here: one episode per
sub-environment, paired across calls on the same seed), :func:`mean_ci95` and
:func:`paired_summary`.
"""

from __future__ import annotations

import math

import torch

from taskvar_torch.envs.episodes import run_episodes


def mean_ci95(x: torch.Tensor) -> tuple[float, float]:
    """Mean and half-width of a normal-approximation 95% confidence interval."""
    x = x.double().reshape(-1)
    m = x.mean().item()
    if x.numel() < 2:
        return m, float("nan")
    return m, 1.959964 * x.std(unbiased=True).item() / math.sqrt(x.numel())


def paired_summary(diff: torch.Tensor) -> dict[str, float]:
    """Fractions no worse / better / worse and the mean difference with its 95% CI.

    ``diff`` = return(method) - return(baseline) per paired episode.
    """
    diff = diff.double().reshape(-1)
    m, ci = mean_ci95(diff)
    return {
        "fraction_no_worse": (diff >= 0).double().mean().item(),
        "fraction_better": (diff > 0).double().mean().item(),
        "fraction_worse": (diff < 0).double().mean().item(),
        "mean_difference": m,
        "mean_difference_ci95": ci,
        "episodes": int(diff.numel()),
    }


__all__ = ["mean_ci95", "paired_summary", "run_episodes"]
