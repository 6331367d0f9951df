"""taskvar_torch: offline learning across task variations for online performance, in PyTorch.

Importing the package registers the Gymnasium ids ``taskvar/WindyGrid-v0``, ``taskvar/Wargus-v0``
and their variants (see :mod:`taskvar_torch.envs.registration`).
"""

from taskvar_torch.envs.registration import register_envs

__version__ = "0.1.0"

register_envs()
