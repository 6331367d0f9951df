"""Robustness critics R(o, s, a) (paper §3.4.3, §3.5.2): subtask attainability by Q-learning.

One network outputs every capability's critic ``(B, O, A)``. Each learns by TD on its robustness
reward (Wargus: TG +1 per step ending where the item is seen, -1 on losing it; FE -1 per step in the
patrol's sight, +1 on escaping it; TG+FE their sum), discounted by ``train.robustness_gamma``, with
the episode end as terminal. ``R(o, s, a)`` "estimates the expectation that the option o will be
able to achieve its goals from state s and action a" (§3.4.3): the option's attainability *when
following o*, so the default target (``train.robustness_target = "option"``) bootstraps with the
option's own next action, ``pi^o(s') = argmax_a' Q_o(s', a')`` (off-policy evaluation of pi^o from
replay, like expected SARSA with a greedy target policy):

    y_o = rr_o + gamma_R * (1 - terminated) * R_o,target(s', pi^o(s'))

``"greedy"`` is plain (double) Q-learning, ``R_o,target(s', argmax_a' R_o(s', a'))``: the
attainability under the *robustness-greedy* policy, which no controller runs. It overrates an
option whose own policy loses its goal: in Wargus the root's policy walks out of the item's sight,
yet the greedy target values that step as "one step back and the +1s resume" (~5.8 > tau = 2), so
Algorithm 2 kept handing the root control at the sight boundary (README "Wargus Figure 4").

"Every component update also updates its composed parent" (§3.4.1): a composed subtask's domain is
the union of its components' domains, so the parent's update mask is its own initiation set or'ed
with its components' (:func:`parent_closure`). All critics read the same sample, off-policy, so an
update of a component is, in the same gradient step, an update of its parent.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict.nn import TensorDictModule

from taskvar_torch import keys
from taskvar_torch.heads.networks import make_head
from taskvar_torch.heads.relabel import Transitions
from taskvar_torch.heads.targets import bootstrap_value, masked_mean
from taskvar_torch.subtasks.base import Hierarchy

ROBUSTNESS_TARGETS = ("greedy", "option")  # next action of the TD target: argmax R_o, or pi^o


def make_robustness_head(
    obs_dim: int,
    num_options: int,
    num_actions: int,
    hidden: Sequence[int] = (64, 64),
    activation: str = "relu",
) -> TensorDictModule:
    """``observation (B, D) -> robustness (B, O, A)``."""
    return make_head(keys.ROBUSTNESS, obs_dim, (num_options, num_actions), hidden, activation)


def component_matrix(names: Sequence[str], hierarchy: Hierarchy | None) -> torch.Tensor:
    """``(O, O)`` bool ``M[c, p]``: option c is p itself or a (transitive) component of p."""
    idx = {n: i for i, n in enumerate(names)}
    m = torch.eye(len(names), dtype=torch.bool)
    if hierarchy is None:
        return m
    for parent in names:
        stack = list(hierarchy.components(parent))
        while stack:
            child = stack.pop()
            if child in idx:
                m[idx[child], idx[parent]] = True
            stack.extend(hierarchy.components(child))
    return m


def parent_closure(mask: torch.Tensor, components: torch.Tensor) -> torch.Tensor:
    """``(B, O)`` bool: a transition updating a component also updates every composed ancestor."""
    return (mask.unsqueeze(-1) & components).any(-2)  # (B, O, 1) & (O, O) -> (B, O)


def robustness_loss(
    r: torch.Tensor,  # (B, O, A) online R(o, s, .)
    r_next: torch.Tensor,  # (B, O, A) online R(o, s', .), no gradient
    r_next_target: torch.Tensor,  # (B, O, A) target R(o, s', .)
    mask: torch.Tensor,  # (B, O) bool, see parent_closure
    batch: Transitions,
    gamma: float,
    double_q: bool = True,
    next_action: torch.Tensor | None = None,  # (B, O) int64 pi^o(s'), or None: greedy in R_o
) -> torch.Tensor:
    """Sum over capabilities of each critic's mean squared TD error (scalar).

    With ``next_action`` the target evaluates the option's own policy at s' (module docstring);
    without it, (double) Q-learning on R.
    """
    if batch.robustness_reward is None:
        raise ValueError("robustness_loss needs robustness rewards (relabel(..., robustness=True))")
    num_options = r.shape[1]
    action = batch.action.view(-1, 1, 1).expand(-1, num_options, 1)  # (B, O, 1)
    r_taken = r.gather(-1, action).squeeze(-1)  # (B, O)
    with torch.no_grad():
        if next_action is None:
            v_next = bootstrap_value(r_next, r_next_target, double_q)  # (B, O)
        else:
            v_next = r_next_target.gather(-1, next_action.unsqueeze(-1)).squeeze(-1)  # (B, O)
        target = batch.robustness_reward + gamma * (1.0 - batch.terminated).unsqueeze(-1) * v_next
    return masked_mean((r_taken - target).pow(2), mask)
