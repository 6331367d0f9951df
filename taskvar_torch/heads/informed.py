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
optimiser, gradient clipping and evaluation average (``train.eval_ema_tau``). It is a residual on
the averaging head (:class:`InformedNet` ``residual=True``)::

    Q_inf(s, z, a) = Q_avg(s, a).detach() + Delta(s, z, a)

``Delta`` an MLP of the averaging head's widths over ``[s; z]`` whose last layer starts at zero,
so the informed policy starts as the averaging policy. Its loss is the averaging head's one-step
double-DQN loss (:func:`~taskvar_torch.heads.averaging.averaging_loss`) on ``Q_inf`` with ``z`` at
``s`` and ``z'`` at ``s'`` (Wargus's item and patrol move within an episode; the windy and Taxi
instances do not): the target is the averaging target network plus ``Delta``'s target, its
double-Q argmax the online ``Q_avg + Delta``. The averaging head's values are the ones the learner
computes for its own loss, detached: no extra pass, and no gradient reaches the paper's heads.
``heads.informed_anchor`` (``lambda``) adds ``lambda * mean_a Delta(s, z, a)^2`` over every
action of the sampled ``s``, so ``Q_inf`` departs from ``Q_avg`` only where the data move it.

Why: the informed head never acts while it learns (the behaviour policy is the paper's heads'),
so an action its greedy policy prefers where the behaviour rarely takes it is never corrected.
Trained as a plain DQN (the old form) it looped on three nominal Taxi seeds of five. The residual
alone (``informed_anchor=0``) loops too: on validation seeds 100 and 101 (``configs/taxi.yaml``,
2000 fresh training episodes, env seed 777) it returned -59.1 and -57.0 against averaging's 6.05
and 6.02, moving into walls the behaviour barely tries on rainy and even on dry instances; with
``informed_anchor=0.3`` 2.64 and 5.43, with ``1.0`` (``configs/taxi.yaml``) 5.95 and
6.04 (docs/memory.md). On windy the TD loss alone reaches the optimum (the default, 0; 1.0 there
holds it near the averaging policy: regret 6.2 at ``tests/families/windy/test_heads_windy.py``'s budget).

Its weights are initialised from a generator of their own (:data:`INFORMED_SEED_OFFSET`) and it
takes no random draw while training, so the paper's heads are the same bits with it on or off
(tests/test_informed_head.py). After training it is written as ``DIR/informed.pt``
(:func:`~taskvar_torch.heads.recurrent.save_informed_head`) with a plain copy of the averaging
head's network (:func:`plain_member_mlp`, :class:`ResidualInformedQ`), so the file is
self-contained: the file ``taskvar eval --method all`` plays. With ``heads.network=conv`` (no
plain copy of a conv head) it is the plain MLP ``Q_inf = MLP([s; z])`` as before.
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
from taskvar_torch.heads.targets import group_mean

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
    from taskvar_torch.families import family

    env = family(cfg).make_env(cfg, 1)
    return tuple(
        k[1]
        for k in env.observation_spec.keys(True, True)
        if isinstance(k, tuple) and len(k) == 2 and k[0] == keys.INSTANCE
    )


class InformedNet(nn.Module):
    """``MLP([s; z])``: ``(..., D), (..., F) -> (..., A)``.

    ``residual=True`` (what ``heads.informed`` builds): the MLP is the correction ``Delta(s, z, .)``
    and ``Q_inf = Q_avg.detach() + Delta``, the averaging head's values added by the caller (the
    learner, :func:`informed_loss`; the evaluation bundle, :func:`~taskvar_torch.heads.recurrent
    .make_informed_qnet`). ``residual=False``: the MLP is ``Q_inf`` itself (bundles written before
    the residual form).
    """

    def __init__(self, mlp: nn.Module, residual: bool = False):
        super().__init__()
        self.mlp = mlp
        self.residual = bool(residual)

    def forward(self, observation: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        return self.mlp(torch.cat([observation, features.to(observation.dtype)], -1))


class ResidualInformedQ(nn.Module):
    """The evaluation form of a residual informed head: ``Q_inf(s, z, .) = base(s) + delta([s;
    z])``, ``base`` a plain copy of the averaging head's network (:func:`plain_member_mlp`) and
    ``delta`` the informed head's correction (``(..., D), (..., F) -> (..., A)``)."""

    def __init__(self, base: nn.Module, delta: nn.Module):
        super().__init__()
        self.base = base
        self.delta = delta

    def forward(self, observation: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        x = torch.cat([observation, features.to(observation.dtype)], -1)
        return self.base(observation) + self.delta(x)


def plain_member_mlp(head: nn.Module, activation: str) -> nn.Module:
    """A plain MLP (:func:`~taskvar_torch.heads.networks.make_mlp`) with the weights of a
    one-member head of a single-seed :class:`~taskvar_torch.heads.networks.StackedMLP` (the
    averaging head; the same values up to float rounding), or a copy of a plain MLP head; a
    one-line ``ValueError`` for any other network (``heads.network=conv``)."""
    import copy

    from taskvar_torch.heads.networks import StackedHead, StackedMLP, head_network

    net = head_network(head)
    if not isinstance(net, StackedHead):
        if any(isinstance(m, nn.Linear) for m in net.modules()) and not any(
            isinstance(m, StackedMLP) for m in net.modules()
        ):
            return copy.deepcopy(net)
        raise ValueError(f"no plain MLP form of a {type(net).__name__} head")
    stack = net.stack
    if type(stack) is not StackedMLP or net.members != 1 or stack.seeds != 1:
        raise ValueError(
            "the informed baseline's bundle copies the averaging head as a plain MLP: it needs "
            "heads.network=mlp and one seed's bundle"
        )
    k, out = net.index, stack.out_sizes[net.index]
    if stack.input_mask is not None and not bool((stack.input_mask[k] == 1).all()):
        raise ValueError("the averaging head reads a masked observation: no plain MLP form")
    hidden = [int(w.shape[-1]) for w in stack.weights[:-1]]
    mlp = make_mlp(int(stack.weights[0].shape[1]), int(out), hidden, activation)
    with torch.no_grad():
        for i, lin in enumerate(m for m in mlp.modules() if isinstance(m, nn.Linear)):
            lin.weight.copy_(stack.weights[i][k, :, : lin.out_features].t())
            lin.bias.copy_(stack.biases[i][k, 0, : lin.out_features])
    return mlp.to(stack.weights[0].device)


def make_informed_head(
    obs_dim: int,
    feature_dim: int,
    num_actions: int,
    hidden: Sequence[int],
    activation: str,
    seed: int,
    residual: bool = True,
) -> TensorDictModule:
    """``observation (B, D), instance_features (B, F) -> informed_action_value (B, A)``, an MLP of
    ``hidden`` widths initialised from its own generator (:data:`INFORMED_SEED_OFFSET`);
    ``residual``: the correction ``Delta`` of :class:`InformedNet`, its last layer zero (so
    ``Q_inf`` starts as ``Q_avg``)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(seed) + INFORMED_SEED_OFFSET)
        mlp = make_mlp(int(obs_dim) + int(feature_dim), int(num_actions), hidden, activation)
    if residual:
        last = [m for m in mlp.modules() if isinstance(m, nn.Linear)][-1]
        with torch.no_grad():
            last.weight.zero_()
            last.bias.zero_()
    return TensorDictModule(
        InformedNet(mlp, residual=residual),
        in_keys=[keys.OBSERVATION, INSTANCE_FEATURES],
        out_keys=[keys.INFORMED_ACTION_VALUE],
    )


def informed_loss(
    net: InformedNet,
    target: InformedNet,
    batch: Transitions,
    gamma: float,
    double_q: bool = True,
    averaging: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
    anchor: float = 0.0,
) -> torch.Tensor:
    """The informed head's loss (scalar): the averaging head's one-step double-DQN loss on the
    batch, the network reading ``batch.informed`` at ``s`` and ``batch.informed_next`` at ``s'``.

    A residual network (:class:`InformedNet` ``residual=True``) needs ``averaging``: the averaging
    head's online ``Q_avg(s, .)``, online ``Q_avg(s', .)`` and target ``Q_avg(s', .)`` ``(B, A)``
    each, added (detached) to ``Delta`` and to the target ``Delta`` (the double-Q argmax over the
    online ``Q_avg + Delta``, its value from the target ``Q_avg + Delta``).
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
    if net.residual:
        if averaging is None:
            raise ValueError("a residual informed head needs the averaging head's values")
        avg, avg_next, avg_next_target = (v.detach() for v in averaging)
        delta = q
        q = avg.to(q.dtype) + q
        q_next = avg_next.to(q_next.dtype) + q_next
        q_next_target = avg_next_target.to(q_next_target.dtype) + q_next_target
    loss = averaging_loss(q, q_next, q_next_target, batch, gamma, double_q)
    if net.residual and anchor > 0:
        loss = loss + anchor * group_mean(delta.float().pow(2).mean(-1), batch.seeds)
    return loss


__all__ = [
    "family_instance_keys",
    "informed_features",
    "INFORMED",
    "INFORMED_SEED_OFFSET",
    "INSTANCE_FEATURES",
    "InformedNet",
    "plain_member_mlp",
    "ResidualInformedQ",
    "informed_loss",
    "make_informed_head",
]
