"""The informed head: the averaging head's network given the hidden instance (docs/memory.md).

``Q_inf(s, z, a)`` is the averaging head of paper §3.1 (DQN on the environment reward across
instances) with one difference: it reads the family's features ``z`` of the hidden instance
beside the observation (``Family.informed_features``, else ``Family.instance_features``: windy
``(p, direction)``, Taxi the rain and the fickle passenger, Wargus every item's and patrol's
position). It is the learnt *ceiling* no controller of the paper can reach, since they never see
``z``.

With ``heads.informed: true`` it is one more head of the multi-head learner
(:class:`~taskvar_torch.heads.learner.MultiHeadLoss`): the same samples, the averaging head's
widths and activation (``heads.hidden``, ``heads.activation``), gamma, double Q, target network,
optimiser, gradient clipping and evaluation average (``train.eval_ema_tau``). Its loss is the
averaging head's one-step double-DQN loss (:func:`~taskvar_torch.heads.averaging.averaging_loss`)
with ``z`` at ``s`` and ``z'`` at ``s'`` (Wargus's item and patrol move within an episode; the
windy and Taxi instances do not). Its weights are initialised from a generator of their own
(:data:`INFORMED_SEED_OFFSET`) and it takes no random draw while training, so the paper's heads
are the same bits with it on or off (tests/test_informed_head.py). After training it is written
as ``DIR/informed.pt`` (:func:`~taskvar_torch.heads.recurrent.save_informed_head`), the file
``taskvar eval --method all`` plays.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn

from taskvar_torch import keys
from taskvar_torch.heads.averaging import averaging_loss
from taskvar_torch.heads.networks import make_mlp
from taskvar_torch.heads.relabel import Transitions

if TYPE_CHECKING:
    from taskvar_torch.config import Config

INFORMED = "informed"
"""The informed head's name in a :class:`~taskvar_torch.heads.bundle.Heads` bundle."""
INSTANCE_FEATURES = "instance_features"
"""Key of the instance features the informed network reads (never an observation)."""
INFORMED_SEED_OFFSET = 1 << 34
"""The informed network of a run seeded ``seed`` is initialised from torch's generator seeded
``seed + INFORMED_SEED_OFFSET`` (inside ``fork_rng``: the global stream is left as it was)."""


def informed_features(cfg: Config) -> tuple[int, Callable[[TensorDictBase], torch.Tensor]]:
    """``(dim, features)`` the informed head reads for the config's family: its
    ``Family.informed_features(cfg)`` (Wargus: item and patrol positions, a dimension set by the
    config), else ``(instance_dim, instance_features)`` (windy, Taxi); a one-line ``ValueError``
    where the family gives neither (then the informed head is unavailable)."""
    from taskvar_torch.families import family

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
    from taskvar_torch.factory import make_env

    env = make_env(cfg, 1)
    return tuple(
        k[1]
        for k in env.observation_spec.keys(True, True)
        if isinstance(k, tuple) and len(k) == 2 and k[0] == keys.INSTANCE
    )


class InformedNet(nn.Module):
    """``Q_inf(s, z, .) = MLP([s; z])``: ``(..., D), (..., F) -> (..., A)``."""

    def __init__(self, mlp: nn.Module):
        super().__init__()
        self.mlp = mlp

    def forward(self, observation: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        return self.mlp(torch.cat([observation, features.to(observation.dtype)], -1))


def make_informed_head(
    obs_dim: int,
    feature_dim: int,
    num_actions: int,
    hidden: Sequence[int],
    activation: str,
    seed: int,
) -> TensorDictModule:
    """``observation (B, D), instance_features (B, F) -> informed_action_value (B, A)``, an MLP of
    ``hidden`` widths initialised from its own generator (:data:`INFORMED_SEED_OFFSET`)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(seed) + INFORMED_SEED_OFFSET)
        mlp = make_mlp(int(obs_dim) + int(feature_dim), int(num_actions), hidden, activation)
    return TensorDictModule(
        InformedNet(mlp),
        in_keys=[keys.OBSERVATION, INSTANCE_FEATURES],
        out_keys=[keys.INFORMED_ACTION_VALUE],
    )


def informed_loss(
    net: InformedNet,
    target: InformedNet,
    batch: Transitions,
    gamma: float,
    double_q: bool = True,
) -> torch.Tensor:
    """The informed head's loss (scalar): the averaging head's one-step double-DQN loss on the
    batch, the network reading ``batch.informed`` at ``s`` and ``batch.informed_next`` at ``s'``.
    """
    if batch.informed is None:
        raise ValueError(
            "heads.informed needs the hidden instance in the replay (('instance', ...)); the "
            "trainer keeps it when heads.informed=true"
        )
    z, z_next = batch.informed, batch.informed_next
    q = net(batch.observation, z)  # (B, A)
    with torch.no_grad():
        q_next = net(batch.next_observation, z_next)  # (B, A)
        q_next_target = target(batch.next_observation, z_next)  # (B, A)
    return averaging_loss(q, q_next, q_next_target, batch, gamma, double_q)


__all__ = [
    "family_instance_keys",
    "informed_features",
    "INFORMED",
    "INFORMED_SEED_OFFSET",
    "INSTANCE_FEATURES",
    "InformedNet",
    "informed_loss",
    "make_informed_head",
]
