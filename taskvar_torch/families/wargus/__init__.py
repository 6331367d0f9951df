"""The Wargus family (paper §3.5): its dynamics, env, Gymnasium wrapper, options, rendering,
robustness diagnostics and the Figure 4 protocol, in one package (docs/families.md).

Modules: :mod:`.dynamics` (pure batched transitions, :class:`WargusConfig`, instances), :mod:`.env`,
:mod:`.gym_env`, :mod:`.render`, :mod:`.subtasks` (the gather/deposit hierarchy),
:mod:`.robustness_mc`, :mod:`.fig4` with :mod:`.fig4_trial`, :mod:`.fig4_recurrent`,
:mod:`.fig4_metrics` and :mod:`.fig4_report` (the paper's Figure 4), and :mod:`.family`.
"""

from taskvar_torch.families.wargus.dynamics import WargusConfig, WargusInstances
from taskvar_torch.families.wargus.env import WargusEnv
from taskvar_torch.families.wargus.subtasks import WargusSubtasks

__all__ = ["WargusConfig", "WargusEnv", "WargusInstances", "WargusSubtasks"]
