"""What the ``informed`` and ``blind`` baselines read of the hidden instance (docs/memory.md).

:func:`informed_features` says what a family gives. :class:`ResidualInformedQ` evaluates old
residual ``informed.pt`` bundles (``Q_avg.detach() + Delta``, a learner head since removed).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import torch
from tensordict import TensorDictBase
from torch import nn

from taskvar_torch import keys

if TYPE_CHECKING:
    from taskvar_torch.config import Config

INFORMED = "informed"
"""The informed baseline's name (its bundle ``DIR/informed.pt``)."""
INSTANCE_FEATURES = "instance_features"
"""Key of the instance features the informed network reads (never an observation)."""


def informed_features(cfg: Config) -> tuple[int, Callable[[TensorDictBase], torch.Tensor]]:
    """``(dim, features)`` the informed baseline reads for the config's family
    (``Family.informed_features``, else ``instance_features``); a one-line ``ValueError`` where the
    family gives neither.
    """
    from taskvar_torch.contract import family

    fam = family(cfg)
    if fam.informed_features is not None:
        dim, feats = fam.informed_features(cfg)
        return int(dim), feats
    if fam.instance_dim is None or fam.instance_features is None:
        raise ValueError(
            f"the informed baseline needs the family's features of the hidden instance "
            f"(Family.informed_features or instance_features); family {fam.name!r} has none, so "
            f"it is unavailable"
        )
    return int(fam.instance_dim), fam.instance_features


def family_instance_keys(cfg: Config) -> tuple[str, ...]:
    """The ``("instance", key)`` fields of the family's env (read from a one-env probe)."""
    from taskvar_torch.contract import family

    env = family(cfg).make_env(cfg, 1)
    return tuple(
        k[1]
        for k in env.observation_spec.keys(True, True)
        if isinstance(k, tuple) and len(k) == 2 and k[0] == keys.INSTANCE
    )


class ResidualInformedQ(nn.Module):
    """An old residual informed bundle: ``Q_inf(s, z, .) = base(s) + delta([s; z])``."""

    def __init__(self, base: nn.Module, delta: nn.Module):
        super().__init__()
        self.base = base
        self.delta = delta

    def forward(self, observation: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        x = torch.cat([observation, features.to(observation.dtype)], -1)
        return self.base(observation) + self.delta(x)


__all__ = [
    "family_instance_keys",
    "informed_features",
    "INFORMED",
    "INSTANCE_FEATURES",
    "ResidualInformedQ",
]
