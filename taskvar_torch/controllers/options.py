"""Offline options without interruption (paper §3.2): mu_bar picks, the option runs to termination."""

from __future__ import annotations

import torch

from taskvar_torch import keys
from taskvar_torch.controllers.interruption import InterruptionController, interruption_decide

Tensor = torch.Tensor


def options_decide(
    q_opt: Tensor,  # (B, O, A)
    q_mu: Tensor,  # (B, O)
    running: Tensor,  # (B,) int64, -1 = empty
    terminated: Tensor | None = None,  # (B,) bool
) -> dict[str, Tensor]:
    """Algorithm 1 without lines 6-9: returns ``action``, ``option``, ``interrupted`` (all False)."""
    return interruption_decide(q_opt, q_mu, None, running, terminated)


class OptionsController(InterruptionController):
    """mu_bar (greedy in Q_mu: line 4 of Algorithm 1) picks an option at the episode start or when
    the running option terminates; the option's greedy policy acts until then.

    Writes ``action``, ``option``, ``interrupted`` (always False) and ``("next", "running_option")``.
    """

    name = "options"
    required_heads = ("options", "switching")
    trace_keys = (keys.OPTION, keys.INTERRUPTED)
    interrupt = False
