"""Offline options without interruption (paper §3.2): mu_bar picks, the option runs to termination."""

from __future__ import annotations

from taskvar_torch import keys
from taskvar_torch.controllers.interruption import InterruptionController


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
