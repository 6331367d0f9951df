"""Any Gymnasium env as a task family (docs/gymnasium.md).

:func:`gym_family` makes a :class:`~taskvar_torch.families.Family` from a Gymnasium env id or a
``make(instance)`` callable, named instance distributions, and options written as plain functions
of an observation and its info; a package registers it under the ``taskvar_torch.families`` entry
point, and the installed ``taskvar`` command trains and evaluates it like a built-in family. The
pieces, one module each: :mod:`.encoder` (observation -> tensor), :mod:`.instances` (instance
distributions), :mod:`.options` (options), :mod:`.sub_env` (one Gymnasium env with its instance and
options), :mod:`.env` (the batched TorchRL env over a Gymnasium vector env), :mod:`.family`.

Nothing in taskvar_torch imports this package: only a user's family does.
"""

from taskvar_torch.families.gymnasium.encoder import SpaceEncoder
from taskvar_torch.families.gymnasium.env import GymFamilyEnv
from taskvar_torch.families.gymnasium.family import GymConfig, gym_family
from taskvar_torch.families.gymnasium.options import Option

__all__ = ["GymConfig", "GymFamilyEnv", "Option", "SpaceEncoder", "gym_family"]
