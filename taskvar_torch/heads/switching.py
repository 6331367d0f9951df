"""Switching head Q_mu(s, o) and the averaging option policy mu_bar (paper §3.2, §3.3).

Q_mu is learnt by *intra-option* Q-learning (Sutton, Precup & Singh, 1999, §6) on the environment
reward: every primitive transition whose action is the one option o would take (a = pi^o(s), with
s in I_o) is an on-policy sample of o, whoever generated it, so all options learn from the same
stream, off-policy, without waiting for options to terminate:

    y = r + gamma * (1 - terminated) * [ (1 - beta_o(s')) Q_mu,target(s', o)
                                         + beta_o(s') V_target(s') ],
    V_target(s') = sum_q mu_bar(s', q) Q_mu,target(s', q)

where mu_bar(s', .) is greedy (or softmax) in the *online* Q_mu over the options initiable at s'
(the double-Q choice). Greedy in Q_mu is mu_bar (Algorithm 1, line 4); V^{mu_bar}(s) is the
interruption threshold of Definition 1. On the windy family the exit options terminate only at the
goal, so Q_mu(s, o) is the value of pi^o averaged over the training instances.
"""

from __future__ import annotations

import torch

from taskvar_torch.config.schema import TrainConfig
from taskvar_torch.heads.options import option_greedy_actions
from taskvar_torch.heads.relabel import Transitions
from taskvar_torch.heads.targets import masked_mean


def mu_bar_temperature(t: TrainConfig) -> float | None:
    """mu_bar's temperature of ``train``: ``None`` for a greedy mu_bar (``train.mu_bar``), else
    the softmax temperature ``train.mu_bar_temperature``."""
    return t.mu_bar_temperature if t.mu_bar == "softmax" else None


def mu_bar_probs(
    option_value: torch.Tensor,  # (B, O) Q_mu(s, .)
    initiation: torch.Tensor | None = None,  # (B, O) bool, options initiable at s
    temperature: float | None = None,
) -> torch.Tensor:
    """mu_bar(s, .) ``(B, O)``: greedy one-hot (ties: lowest index) or softmax over initiable options.

    States where no option is initiable (e.g. terminal ones) fall back to all options.
    """
    q = option_value
    if initiation is not None:
        allowed = initiation | ~initiation.any(-1, keepdim=True)  # (B, O)
        q = q.masked_fill(~allowed, float("-inf"))
    if temperature is None:
        return torch.nn.functional.one_hot(q.argmax(-1), q.shape[-1]).to(option_value.dtype)
    return torch.softmax(q / temperature, dim=-1)


def consistent_with_option(
    action: torch.Tensor,  # (B,)
    q_options: torch.Tensor,  # (B, O, A) Q_o(s, .)
    initiation: torch.Tensor,  # (B, O) bool
) -> torch.Tensor:
    """``(B, O)`` bool: the transition is one option o would have made (s in I_o, a = pi^o(s))."""
    return initiation & (option_greedy_actions(q_options) == action.unsqueeze(-1))


def continuation_value(
    value_next_target: torch.Tensor,  # (B, O) target head at s'
    mu_bar_next: torch.Tensor,  # (B, O) mu_bar(s', .)
    beta_next: torch.Tensor,  # (B, O) beta_o(s')
) -> torch.Tensor:
    """``(1 - beta_o(s')) V(s', o) + beta_o(s') sum_q mu_bar(s', q) V(s', q)``, ``(B, O)``."""
    switch = (mu_bar_next * value_next_target).sum(-1, keepdim=True)  # (B, 1)
    return (1.0 - beta_next) * value_next_target + beta_next * switch


def switching_loss(
    q_mu: torch.Tensor,  # (B, O) online Q_mu(s, .)
    q_mu_next_target: torch.Tensor,  # (B, O) target Q_mu(s', .)
    mu_bar_next: torch.Tensor,  # (B, O) mu_bar(s', .) from the online head, no gradient
    consistent: torch.Tensor,  # (B, O) bool, see consistent_with_option
    batch: Transitions,
    gamma: float,
) -> torch.Tensor:
    """Intra-option Q-learning loss: sum over options of the mean squared TD error (scalar)."""
    with torch.no_grad():
        cont = continuation_value(q_mu_next_target, mu_bar_next, batch.beta_next)  # (B, O)
        target = batch.reward.unsqueeze(-1) + gamma * (1.0 - batch.terminated).unsqueeze(-1) * cont
    return masked_mean((q_mu - target).pow(2), consistent, batch.seeds)
