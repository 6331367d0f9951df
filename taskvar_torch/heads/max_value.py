"""Max-value head Q_hat(s, o) ~ max over training instances of Q^{m, mu_bar}(s, o) (Definition 1).

The head is ``Q_hat = Q_mu + softplus(gap)`` (:class:`OptimismGapHead`), so ``Q_hat >= Q^{mu_bar}``.
Two estimators train the gap (``train.max_value_estimator``; docs/notes/design-decisions.md):

**instance**: a critic ``C(s, o | z)`` conditioned on the episode's hidden instance ``z`` (offline
only) learns by intra-option TD under mu_bar, and the head regresses its max over the sample's
``max_value_instances`` instances ``Z``:

    y = r + gamma * (1 - terminated) * [ (1 - beta_o(s')) C_target(s', o | z) + beta_o(s') sum_q
    mu_bar(s', q) C_target(s', q | z) ] loss_C = (y - C(s, o | z))^2,  loss_hat = (Q_hat(s, o) -
    max_{z in Z} C_target(s, o | z))^2

**expectile** (any family): expectile TD at level ``train.max_value_expectile`` on the same
transitions, with ``Q_hat,target`` in place of ``C_target``:

    loss = |tau - 1[y < Q_hat(s, o)]| (y - Q_hat(s, o))^2
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from taskvar_torch.heads.networks import make_mlp
from taskvar_torch.heads.relabel import Transitions
from taskvar_torch.heads.switching import continuation_value
from taskvar_torch.heads.targets import expectile_loss, masked_mean

MAX_VALUE_ESTIMATORS = ("expectile", "instance")


class OptimismGapHead(nn.Module):
    """``Q_hat(s, .) = Q_mu(s, .) + softplus(gap(s, .))``: the max-value head as an optimism gap, so
    ``Q_hat >= Q^{mu_bar}`` by construction; the learner trains ``gap`` on the max-value loss and
    ``base`` on the switching loss.

    Args:
        base: the switching head's network ``(..., D) -> (..., O)``.
        gap: the gap network ``(..., D) -> (..., O)``.
        critic: the ``instance`` estimator's critic ``(..., D + F) -> (..., O)`` (never read by
            ``forward``), or ``None``.
    """

    def __init__(self, base: nn.Module, gap: nn.Module, critic: nn.Module | None = None):
        super().__init__()
        self.base = base
        self.gap = gap
        self.critic = critic

    @staticmethod
    def combine(base_value: torch.Tensor, gap_raw: torch.Tensor) -> torch.Tensor:
        """``base + softplus(gap)`` (the learner calls it with a detached base)."""
        return base_value + F.softplus(gap_raw)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.combine(self.base(x), self.gap(x))


def make_instance_critic(
    obs_dim: int,
    instance_dim: int,
    num_options: int,
    hidden: Sequence[int] = (64, 64),
    activation: str = "relu",
) -> nn.Module:
    """The ``instance`` estimator's critic ``C(s, o | z)``: an MLP ``(B, D + F) -> (B, O)``."""
    return make_mlp(obs_dim + instance_dim, num_options, hidden, activation)


def max_value_loss(
    q_hat: torch.Tensor,  # (B, O) online Q_hat(s, .)
    q_hat_next_target: torch.Tensor,  # (B, O) target Q_hat(s', .)
    mu_bar_next: torch.Tensor,  # (B, O) mu_bar(s', .) from the online switching head
    consistent: torch.Tensor,  # (B, O) bool: s in I_o and a = pi^o(s)
    batch: Transitions,
    gamma: float,
    level: float = 0.95,
) -> torch.Tensor:
    """Expectile TD loss of the max-value head, summed over options (scalar)."""
    with torch.no_grad():
        cont = continuation_value(q_hat_next_target, mu_bar_next, batch.beta_next)  # (B, O)
        target = batch.reward.unsqueeze(-1) + gamma * (1.0 - batch.terminated).unsqueeze(-1) * cont
    return masked_mean(expectile_loss(q_hat, target, level), consistent, batch.seeds)


def instance_max_value_loss(
    q_hat: torch.Tensor,  # (B, O) online Q_hat(s, .) (gradient into the gap only)
    critic: nn.Module,  # online C: (M, D + F) -> (M, O)
    critic_target: nn.Module,  # target C
    mu_bar_next: torch.Tensor,  # (B, O) mu_bar(s', .) from the online switching head
    consistent: torch.Tensor,  # (B, O) bool: s in I_o and a = pi^o(s)
    batch: Transitions,
    gamma: float,
    num_instances: int = 64,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``instance`` estimator's two scalar losses: the critic's TD loss in each transition's own
    instance, and the head's regression on :func:`instance_max` (Definition 1).
    """
    if batch.instance is None:
        raise ValueError(
            "max_value_estimator='instance' needs the hidden instance in the replay "
            "(('instance', 'p'), ('instance', 'direction')); the windy trainer keeps it"
        )
    z = batch.instance  # (B, F)
    c = critic(torch.cat([batch.observation, z], -1))  # (B, O)
    with torch.no_grad():
        c_next = critic_target(torch.cat([batch.next_observation, z], -1))  # (B, O)
        cont = continuation_value(c_next, mu_bar_next, batch.beta_next)  # (B, O)
        y = batch.reward.unsqueeze(-1) + gamma * (1.0 - batch.terminated).unsqueeze(-1) * cont
        q_max = instance_max(critic_target, batch.observation, z, batch.seeds, num_instances)
    loss_critic = masked_mean((c - y).pow(2), consistent, batch.seeds)
    loss_hat = masked_mean((q_hat - q_max).pow(2), batch.initiation, batch.seeds)
    return loss_critic, loss_hat


def distinct_rows(x: torch.Tensor, seeds: int = 1) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Each of ``S`` seed-major row groups of ``x (B, D)`` cut to its distinct rows, padded to equal
    size: ``(rows (S U, D), index (B,))`` with ``x == rows[index]``; ``None`` on a key collision.
    """
    D = x.shape[-1]
    w = torch.rand(D, dtype=torch.float64, generator=torch.Generator().manual_seed(D)) + 0.5
    key = (x.to(torch.float64) @ w.to(x.device)).view(seeds, -1)  # (S, B / S)
    groups = [torch.unique(k, return_inverse=True) for k in key]  # sorted keys, (B / S,) index
    U = max(u.shape[0] for u, _ in groups)
    first = []  # each distinct key's first row, each group padded with its first key's row
    for s, (u, inv) in enumerate(groups):
        pos = torch.full((U,), -1, dtype=torch.int64, device=x.device)
        pos.scatter_reduce_(0, inv, torch.arange(inv.shape[0], device=x.device), "amax")
        pos[u.shape[0] :] = pos[0]
        first.append(pos + s * inv.shape[0])
    index = torch.cat([inv + s * U for s, (_, inv) in enumerate(groups)])  # (B,)
    rows = x[torch.cat(first)]  # (S U, D)
    if not torch.equal(rows[index], x):  # a key collision: no shortcut
        return None
    return rows, index


def instance_max(
    critic_target: nn.Module,  # target C: (M, D + F) -> (M, O)
    observation: torch.Tensor,  # (B, D) s of every sampled transition
    instance: torch.Tensor,  # (B, F) z of every sampled transition
    seeds: int = 1,
    num_instances: int = 64,
) -> torch.Tensor:
    """``max_{z in Z} C_target(s, o | z)`` at every sampled state ``(B, O)``, ``Z`` the instances of
    the first ``num_instances`` rows (of each run's rows); on the CPU over the distinct rows only.
    """
    B, S = observation.shape[0], seeds  # each run's Z from its own rows (heads/seeds.py)
    zs = instance.view(S, B // S, -1)[:, : min(int(num_instances), B // S)]  # (S, M, F) seen ones
    M = zs.shape[1]
    obs, index = observation, None
    if observation.device.type == "cpu" and not torch.compiler.is_compiling():
        distinct = distinct_rows(observation, S)
        if distinct is not None:
            obs, index = distinct  # (S U, D), (B,)
    R = obs.shape[0]  # rows per run: R / S
    grid_obs = obs.unsqueeze(1).expand(R, M, -1)  # (R, M, D)
    grid_z = zs.unsqueeze(1).expand(S, R // S, M, -1).reshape(R, M, -1)  # row r: its run's Z
    q_max = critic_target(torch.cat([grid_obs, grid_z], -1)).max(1).values  # (R, O)
    return q_max if index is None else q_max[index]  # (B, O)
