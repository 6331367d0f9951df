"""taskvar_torch: offline learning across task variations for online performance, in PyTorch.

The front door (docs/design.md#public-interface): :func:`load_config`, :func:`train`,
:func:`load_heads`, :func:`make_env`, :func:`make_subtasks`, :func:`make_controller`,
:class:`Heads`, :func:`evaluate`, :func:`run_episodes`, and the family contract
(:class:`Family`, :class:`TestDistribution`, :func:`register_family`, :func:`check_family`,
:func:`family`; docs/families.md). Importing registers every family's Gymnasium ids; names that
need the learner load on first use.
"""

from taskvar_torch import _startup  # noqa: I001  (first: the command's start-up signals)

from taskvar_torch._lazy import lazy_names
from taskvar_torch.envs.registration import register_envs
from taskvar_torch.contract import Family, TestDistribution, family, register_family

_LAZY = {
    "check_family": "taskvar_torch.family_check",
    "load_config": "taskvar_torch.config",
    "train": "taskvar_torch.training",
    "load_heads": "taskvar_torch.factory",
    "make_env": "taskvar_torch.factory",
    "make_subtasks": "taskvar_torch.factory",
    "make_controller": "taskvar_torch.controllers",
    "Heads": "taskvar_torch.heads.bundle",
    "evaluate": ("taskvar_torch.experiments.bundle_eval", "eval_bundle"),
    "run_episodes": "taskvar_torch.experiments.evaluation",
}
"""Front-door names imported on first use: name -> module (or (module, name there))."""


__getattr__, __dir__ = lazy_names(globals(), _LAZY)

__all__ = [
    "Family",
    "Heads",
    "TestDistribution",
    "check_family",
    "evaluate",
    "family",
    "load_config",
    "load_heads",
    "make_controller",
    "make_env",
    "make_subtasks",
    "register_envs",
    "register_family",
    "run_episodes",
    "train",
]

__version__ = "0.1.0"

if _startup.AS_COMMAND:  # the command imports an installed family when it asks for it by name
    from taskvar_torch.envs.registration import register_builtin_envs

    register_builtin_envs()
else:
    register_envs()
