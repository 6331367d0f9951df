"""Offline options without interruption (paper §3.2): mu_bar picks, the option runs to termination."""

from __future__ import annotations

from taskvar_torch import keys
from taskvar_torch.controllers.interruption import InterruptionController


class OptionsController(InterruptionController):
    """Options without interruption (paper §3.2): mu_bar (Algorithm 1, line 4) picks an option at
    the episode start or when the running option terminates; its greedy policy acts until then.

    Initiation sets as :class:`InterruptionController`; ``interrupted`` is always False.
    """

    name = "options"
    required_heads = ("options", "switching")
    trace_keys = (keys.OPTION, keys.INTERRUPTED)
    interrupt = False
