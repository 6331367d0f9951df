"""Max-value head Q_hat(s, o) ~ max over training instances of Q^{m, mu_bar}(s, o) (Definition 1).

Q_hat is the best value option o has shown from s in any training instance, running o and then
continuing with mu_bar; offline interruption (Algorithm 1) fires where Q_hat(s, o_run) < V^{mu_bar}(s).

Parametrisation: ``Q_hat = Q_mu + softplus(gap)`` (:class:`OptimismGapHead`), which builds in
``Q_hat >= Q^{mu_bar}`` (a max over instances is at least their mean). Two estimators train the
gap (``train.max_value_estimator``):

**instance** (Definition 1 literally; windy). An *instance-conditioned* critic ``C(s, o | z)``,
``z`` the episode's hidden instance (windy: ``(p, one_hot(direction))``, read from the replay;
privileged information used offline only: the controllers read Q_hat, never z nor C), learnt by
ordinary (expectation) intra-option TD under mu_bar on the same transitions as the switching head
(a = pi^o(s), s in I_o), with the instance held fixed as it is along the episode:

    y = r + gamma * (1 - terminated) * [ (1 - beta_o(s')) C_target(s', o | z)
                                         + beta_o(s') sum_q mu_bar(s', q) C_target(s', q | z) ]
    loss_C = (y - C(s, o | z))^2

so ``C(., . | z) -> Q^{z, mu_bar}`` (the values of paper §2.4 in instance z). Then the max of
Definition 1 over the training instances seen, ``Z`` = the instances of ``max_value_instances``
transitions of the sample (a uniform draw from the replay, so the instances the agent has met,
weighted by their data), distilled into the head at every sampled state and initiable option:

    loss_hat = (Q_hat(s, o) - max_{z in Z} C_target(s, o | z))^2

Optimism is then over instances only: within an instance, gusts are averaged by the TD
expectation, as Definition 1 asks (``Q^{m, mu_bar}`` is an expected return in m). This replaces
the paper's per-instance Monte-Carlo tables, which a continuum of instances (p ~ U[0, 1]) and
function approximation do not allow; the max over a random 64 of the seen instances stands in for
the max over all of them (in the windy family the max sits at the calm / harmless-wind end of the
range, which 64 uniform draws approach within ~1/65 in p). The critic lives inside the max-value
head (``OptimismGapHead.critic``), so it is checkpointed with the heads; it costs one extra MLP pass
on ``B * |Z|`` rows per update.

**expectile** (any family; Wargus). Expectile TD with a high level tau
(``train.max_value_expectile``, default 0.95), on the same intra-option transitions:

    y = r + gamma * (1 - terminated) * [ (1 - beta_o(s')) Q_hat,target(s', o)
                                         + beta_o(s') sum_q mu_bar(s', q) Q_hat,target(s', q) ]
    loss = |tau - 1[y < Q_hat(s, o)]| (y - Q_hat(s, o))^2

An expectile at tau -> 1 tends to the supremum of the next-state outcome distribution, taken at
every step: it is optimistic over *all* randomness at (s, a) (gusts, patrol moves, item spawns),
not over instances only, so it over-estimates Q_hat where within-instance noise matters, which makes
interruption fire less often (the conservative side of Theorem 1). Wargus keeps it: a Wargus
instance is a seed that fixes every random draw of the episode (item spawns, patrol walk), so it
has no features a critic could condition on, and "the max over instances" of a seed family *is*
the best outcome of all that randomness, which is what the expectile targets.

Which is the default: the dataclass default stays ``expectile`` (old checkpoints, whose configs
predate the field, load with the estimator they were trained with); the windy configs set
``instance``, chosen on the *training* distribution's oracle figures (``max_value_error``,
``interruption_agreement`` of :func:`~taskvar_torch.heads.validate.compare_with_oracle`, which
evaluate on the training instances), never on test seeds.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from tensordict.nn import TensorDictModule
from torch import nn

from taskvar_torch import keys
from taskvar_torch.heads.networks import head_network, make_mlp
from taskvar_torch.heads.relabel import Transitions
from taskvar_torch.heads.switching import continuation_value
from taskvar_torch.heads.targets import expectile_loss, masked_mean

MAX_VALUE_ESTIMATORS = ("expectile", "instance")


class OptimismGapHead(nn.Module):
    """``Q_hat(s, .) = Q_mu(s, .) + softplus(gap(s, .))``: the max-value head as an optimism gap.

    A max over training instances is at least their average, ``Q_hat(s, o) >= Q^{mu_bar}(s, o)``;
    this parametrisation builds the inequality in. So offline interruption never fires against the
    option mu_bar itself picks (there ``Q_hat >= Q_mu = V^{mu_bar}``), and where no uncertainty is
    left (``Q_hat = Q_mu`` exactly, e.g. one step from the goal) the learnt condition is not a coin
    flip between two noisy estimates of the same number. The learner trains only ``gap`` on the
    max-value loss (``Q_mu`` is detached there) and ``base`` on the switching loss.

    Args:
        base: the switching head's network ``(..., D) -> (..., O)``.
        gap: the gap network ``(..., D) -> (..., O)``.
        critic: the instance-conditioned critic ``(..., D + F) -> (..., O)`` of the ``instance``
            estimator (trained offline only; ``forward`` never reads it), or ``None``.
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


def make_max_value_head(
    switching: nn.Module,
    obs_dim: int,
    num_options: int,
    hidden: Sequence[int] = (64, 64),
    activation: str = "relu",
    instance_dim: int | None = None,
) -> TensorDictModule:
    """``observation (B, D) -> max_value (B, O)``: the switching head plus a fresh gap MLP (and,
    with ``instance_dim``, an instance-conditioned critic for the ``instance`` estimator)."""
    gap = make_mlp(obs_dim, num_options, hidden, activation)
    critic = None
    if instance_dim is not None:
        critic = make_instance_critic(obs_dim, instance_dim, num_options, hidden, activation)
    return TensorDictModule(
        OptimismGapHead(head_network(switching), gap, critic),
        in_keys=[keys.OBSERVATION],
        out_keys=[keys.MAX_VALUE],
    )


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
    """The ``instance`` estimator's two losses (scalars): the critic's intra-option TD loss in each
    transition's own instance, and the head's regression on ``max_{z in Z} C_target(s, o | z)``
    over ``Z`` = the instances of the sample's first ``num_instances`` transitions (Definition 1;
    with ``batch.seeds = S``, of each run's own rows).
    """
    if batch.instance is None:
        raise ValueError(
            "max_value_estimator='instance' needs the hidden instance in the replay "
            "(('instance', 'p'), ('instance', 'direction')); the windy trainer keeps it"
        )
    z = batch.instance  # (B, F)
    B, O = q_hat.shape  # noqa: E741
    c = critic(torch.cat([batch.observation, z], -1))  # (B, O)
    with torch.no_grad():
        c_next = critic_target(torch.cat([batch.next_observation, z], -1))  # (B, O)
        cont = continuation_value(c_next, mu_bar_next, batch.beta_next)  # (B, O)
        y = batch.reward.unsqueeze(-1) + gamma * (1.0 - batch.terminated).unsqueeze(-1) * cont
        S = batch.seeds  # each run's Z from its own rows (heads/seeds.py)
        zs = z.view(S, B // S, -1)[:, : min(int(num_instances), B // S)]  # (S, M, F) seen ones
        M = zs.shape[1]
        obs = batch.observation.unsqueeze(1).expand(B, M, -1)  # (B, M, D)
        zs = zs.unsqueeze(1).expand(S, B // S, M, -1).reshape(B, M, -1)  # row b: its run's Z
        grid = critic_target(torch.cat([obs, zs], -1))  # (B, M, O)
        q_max = grid.max(1).values  # (B, O): max over instances of Q^{z, mu_bar}(s, o)
    loss_critic = masked_mean((c - y).pow(2), consistent, batch.seeds)
    loss_hat = masked_mean((q_hat - q_max).pow(2), batch.initiation, batch.seeds)
    return loss_critic, loss_hat
