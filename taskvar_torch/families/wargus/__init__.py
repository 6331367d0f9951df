"""The Wargus family (paper §3.5): dynamics, env, options, robustness diagnostics and the Figure 4
protocol (docs/wargus-fig4.md); :mod:`.family` is the declaration.
"""

from taskvar_torch.families.wargus.dynamics import WargusConfig, WargusInstances
from taskvar_torch.families.wargus.env import WargusEnv
from taskvar_torch.families.wargus.subtasks import WargusSubtasks

__all__ = ["WargusConfig", "WargusEnv", "WargusInstances", "WargusSubtasks"]
