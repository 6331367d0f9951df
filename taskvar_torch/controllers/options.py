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
    initiable: Tensor | None = None,  # (B, O) bool s_t in I_o
    q_avg: Tensor | None = None,  # (B, A): acts where no option is initiable
) -> dict[str, Tensor]:
    """Algorithm 1 without lines 6-9: returns ``action``, ``option``, ``interrupted`` (all False).

    ``initiable`` / ``q_avg``: line 4 picks among the initiable options, else the averaging action
    acts with option -1 (:func:`~taskvar_torch.controllers.interruption.interruption_decide_of`).
    """
    return interruption_decide(
        q_opt, q_mu, None, running, terminated, initiable=initiable, q_avg=q_avg
    )


class OptionsController(InterruptionController):
    """mu_bar (greedy in Q_mu: line 4 of Algorithm 1) picks an option at the episode start or when
    the running option terminates; the option's greedy policy acts until then. With ``subtasks``
    that define initiation sets, mu_bar picks among the options initiable at s_t, and where none
    is the averaging head acts with option -1 (:class:`InterruptionController`).

    Writes ``action``, ``option``, ``interrupted`` (always False) and ``("next", "running_option")``.
    """

    name = "options"
    required_heads = ("options", "switching")
    trace_keys = (keys.OPTION, keys.INTERRUPTED)
    interrupt = False
