"""What the ``informed`` and ``blind`` baselines read of the hidden instance (docs/memory.md).

The ``informed`` baseline (:mod:`taskvar_torch.training.baselines`, a DQN agent of its own) reads the
family's features ``z`` of the hidden instance beside the observation
(``Family.informed_features``, else ``Family.instance_features``: windy ``(p, direction)``, Taxi
the rain and the fickle passenger, Wargus every item's and patrol's position); ``blind`` reads
zeros of the same width. :func:`informed_features` says what a family gives.

:class:`ResidualInformedQ` is the form of ``informed.pt`` bundles written while the paper's
learner trained the informed head as a residual on the averaging head (``Q_avg.detach() +
Delta``, one more head on the same samples, never acting): measured below the averaging policy on
Wargus and MiniGrid, it was removed (docs/changelog.md); such bundles still evaluate.
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
    """``(dim, features)`` the informed head reads for the config's family: its
    ``Family.informed_features(cfg)`` (Wargus: item and patrol positions, a dimension set by the
    config), else ``(instance_dim, instance_features)`` (windy, Taxi); a one-line ``ValueError``
    where the family gives neither (then the informed head is unavailable)."""
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
    """The evaluation form of an old residual informed bundle: ``Q_inf(s, z, .) = base(s) +
    delta([s; z])``, ``base`` a plain copy of the averaging head's network and ``delta`` the
    informed head's correction (``(..., D), (..., F) -> (..., A)``)."""

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
