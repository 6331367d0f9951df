"""Max-value head Q_hat(s, o) ~ max over training instances of Q^{m, mu_bar}(s, o) (Definition 1).

Q_hat is the best value option o has shown from s in any training instance, running o and then
continuing with mu_bar; offline interruption (Algorithm 1) fires where Q_hat(s, o_run) < V^{mu_bar}(s).

Parametrisation: ``Q_hat = Q_mu + softplus(gap)`` (:class:`OptimismGapHead`), which builds in
``Q_hat >= Q^{mu_bar}`` (a max over instances is at least their mean).

Estimator: **expectile TD** with a high level tau (``train.max_value_expectile``, default 0.95), on
the same intra-option transitions as the switching head (a = pi^o(s), s in I_o):

    y = r + gamma * (1 - terminated) * [ (1 - beta_o(s')) Q_hat,target(s', o)
                                         + beta_o(s') sum_q mu_bar(s', q) Q_hat,target(s', q) ]
    loss = |tau - 1[y < Q_hat(s, o)]| (y - Q_hat(s, o))^2

Why this choice:

* The paper estimates the max with Monte-Carlo returns per instance. With function approximation and
  a continuum of instances (p ~ U[0, 1]) there is no per-instance table to take a max over, so we
  need an *upper* estimator of the next-state outcome distribution. An expectile at level tau -> 1
  tends to the supremum of that distribution; unlike a hard max it is smooth and robust to noise.
* Because the instance is fixed along a trajectory, the best instance's value is reached by taking
  the optimistic (upper-expectile) continuation at every step, including after the option terminates
  (the continuation uses Q_hat weighted by mu_bar, not the average Q_mu).
* It learns from the one shared sample, off-policy, with a TD target; no episode bookkeeping.

Caveat: the expectile is optimistic over *all* randomness at (s, a), within-instance noise as well as
the instance. Where the family's training instances include a near-deterministic one (the windy
family: p ~ U[0, 1] includes p ~ 0, and a harmless wind direction), the max over instances equals
the best outcome and the estimator is consistent as tau -> 1; the finite tau shortfall is
tau-dependent and small (about 0.05 steps per gust for tau = 0.95 on the 5x5 family). Elsewhere it
is an over-estimate of Q_hat, which only makes interruption fire less often (the conservative side
of Theorem 1). The learning test checks it against the exact oracle's Q_hat.
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
    """

    def __init__(self, base: nn.Module, gap: nn.Module):
        super().__init__()
        self.base = base
        self.gap = gap

    @staticmethod
    def combine(base_value: torch.Tensor, gap_raw: torch.Tensor) -> torch.Tensor:
        """``base + softplus(gap)`` (the learner calls it with a detached base)."""
        return base_value + F.softplus(gap_raw)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.combine(self.base(x), self.gap(x))


def make_max_value_head(
    switching: nn.Module,
    obs_dim: int,
    num_options: int,
    hidden: Sequence[int] = (64, 64),
    activation: str = "relu",
) -> TensorDictModule:
    """``observation (B, D) -> max_value (B, O)``: the switching head plus a fresh gap MLP."""
    gap = make_mlp(obs_dim, num_options, hidden, activation)
    return TensorDictModule(
        OptimismGapHead(head_network(switching), gap),
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
    return masked_mean(expectile_loss(q_hat, target, level), consistent)
