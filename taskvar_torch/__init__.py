"""taskvar_torch: offline learning across task variations for online performance, in PyTorch.

Importing the package registers the Gymnasium ids ``taskvar/WindyGrid-v0``, ``taskvar/Wargus-v0``,
``taskvar/Taxi-v0`` and their variants (see :mod:`taskvar_torch.envs.registration`).

A task family of one's own needs no edit of the package (docs/families.md): describe it as a
:class:`Family`, then :func:`register_family` it (or name it in the entry-point group
``taskvar_torch.families`` of an installed package) and :func:`check_family` it.
"""

from taskvar_torch.envs.registration import register_envs
from taskvar_torch.families import Family, TestDistribution, family, register_family
from taskvar_torch.family_check import check_family

__all__ = [
    "Family",
    "TestDistribution",
    "check_family",
    "family",
    "register_family",
    "register_envs",
]

__version__ = "0.1.0"

register_envs()
