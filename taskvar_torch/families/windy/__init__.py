"""The windy family (paper §3.3.1): dynamics, env, instances, options, exact oracles and the
Figure 2 experiment (docs/windy-fig2.md, docs/oracle.md); :mod:`.family` is the declaration.
"""

from taskvar_torch._lazy import lazy_names

_LAZY = {
    "ReplayReference": f"{__name__}.replay_reference",
    "WindyGridEnv": f"{__name__}.env",
    "WindyInstances": f"{__name__}.instances",
    "WindyLayout": f"{__name__}.dynamics",
    "WindyModel": f"{__name__}.dynamics",
    "WindyOracle": f"{__name__}.oracle",
    "WindySubtasks": f"{__name__}.subtasks",
    "exact_returns": f"{__name__}.learnt",
    "firing_values": f"{__name__}.learnt",
    "learnt_vs_oracle_by_start": f"{__name__}.learnt",
    "make_layout": f"{__name__}.dynamics",
}
"""The package's names, imported from their module on first use (``import taskvar_torch`` reads
the family's declaration only, not its oracles)."""

__getattr__, __dir__ = lazy_names(globals(), _LAZY)

__all__ = [
    "ReplayReference",
    "WindyGridEnv",
    "WindyInstances",
    "WindyLayout",
    "WindyModel",
    "WindyOracle",
    "WindySubtasks",
    "exact_returns",
    "firing_values",
    "learnt_vs_oracle_by_start",
    "make_layout",
]
