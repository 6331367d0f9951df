"""The windy family (paper §3.3.1): its dynamics, env, Gymnasium wrapper, instances, options,
exact oracles, rendering and the Figure 2 experiment, in one package (docs/families.md).

Modules: :mod:`.dynamics` (pure batched transitions, layouts), :mod:`.env` (the TorchRL env),
:mod:`.gym_env` (the Gymnasium env), :mod:`.instances`, :mod:`.subtasks` (exit options),
:mod:`.oracle` (:class:`WindyOracle`, exact tables), :mod:`.sparse_oracle` (any grid size),
:mod:`.replay_reference`, :mod:`.learnt` and :mod:`.head_report` (learnt heads measured exactly),
:mod:`.render`, :mod:`.oracle_table`, :mod:`.fig2` with :mod:`.fig2_metrics` and
:mod:`.fig2_report` (the paper's Figure 2), and :mod:`.family` (the declaration).
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
