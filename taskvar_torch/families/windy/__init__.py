"""The windy family (paper §3.3.1): its dynamics, env, Gymnasium wrapper, instances, options,
exact oracles, rendering and the Figure 2 experiment, in one package (docs/families.md).

Modules: :mod:`.dynamics` (pure batched transitions, layouts), :mod:`.env` (the TorchRL env),
:mod:`.gym_env` (the Gymnasium env), :mod:`.instances`, :mod:`.subtasks` (exit options),
:mod:`.oracle` (:class:`WindyOracle`, exact tables), :mod:`.sparse_oracle` (any grid size),
:mod:`.replay_reference`, :mod:`.learnt` and :mod:`.head_report` (learnt heads measured exactly),
:mod:`.render`, :mod:`.oracle_table`, :mod:`.fig2` with :mod:`.fig2_metrics` and
:mod:`.fig2_report` (the paper's Figure 2), and :mod:`.family` (the declaration).
"""

from importlib import import_module
from typing import Any

_LAZY = {
    "ReplayReference": "replay_reference",
    "WindyGridEnv": "env",
    "WindyInstances": "instances",
    "WindyLayout": "dynamics",
    "WindyModel": "dynamics",
    "WindyOracle": "oracle",
    "WindySubtasks": "subtasks",
    "exact_returns": "learnt",
    "firing_values": "learnt",
    "learnt_vs_oracle_by_start": "learnt",
    "make_layout": "dynamics",
}
"""The package's names, imported from their module on first use (``import taskvar_torch`` reads
the family's declaration only, not its oracles)."""


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_LAZY])


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
