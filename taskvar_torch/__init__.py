"""taskvar_torch: offline learning across task variations for online performance, in PyTorch.

The front door (``import taskvar_torch as tv``) holds what a user needs; the modules behind it are
the implementation:

- configs: :func:`load_config` (YAML + ``key=value`` overrides, strict);
- training: :func:`train` (every head of the paper from one replay, docs/design.md);
- acting: :func:`load_heads` (a trained bundle), :func:`make_env`, :func:`make_subtasks`,
  :func:`make_controller` (averaging, options, interruption, hierarchy: Algorithms 1-2),
  :class:`Heads` (the bundle controllers read, trained or exact);
- measuring: :func:`evaluate` (``taskvar eval``: a bundle on named test distributions and shifts),
  :func:`run_episodes` (one batched episode per sub-env);
- families: :class:`Family`, :class:`TestDistribution`, :func:`register_family`,
  :func:`check_family`, :func:`family` (docs/families.md).

Importing the package registers every family's Gymnasium ids (``Family.gym_ids``): the built-in
``taskvar/WindyGrid-v0``, ``taskvar/Wargus-v0``, ``taskvar/Taxi-v0`` and their variants, and those
of installed families (see :mod:`taskvar_torch.envs.registration`). The names above that need the
learner are imported on first use, so ``import taskvar_torch`` stays light.

Examples:
    >>> import taskvar_torch as tv
    >>> cfg = tv.load_config("configs/windy.yaml", ["train.total_frames=20000"])  # doctest: +SKIP
    >>> tv.train(cfg, "runs/windy")  # doctest: +SKIP
    >>> heads, cfg = tv.load_heads("runs/windy/final.pt")  # doctest: +SKIP
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
