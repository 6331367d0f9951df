"""Robustness critics R(o, s, a) (paper §3.4.3, §3.5.2): subtask attainability by Q-learning.

One network outputs every capability's critic ``(B, O, A)``. Each learns by double Q-learning on its
robustness reward (Wargus: TG +1 on coming into sight of the item, -1 on losing it; FE -1 per step in
the patrol's sight, +1 on escaping it; TG+FE their sum), discounted by ``train.robustness_gamma``,
with the episode end as terminal:

    y_o = rr_o + gamma_R * (1 - terminated) * R_o,target(s', argmax_a' R_o(s', a'))

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
) -> torch.Tensor:
    """Sum over capabilities of each critic's mean squared TD error (scalar)."""
    if batch.robustness_reward is None:
        raise ValueError("robustness_loss needs robustness rewards (relabel(..., robustness=True))")
    num_options = r.shape[1]
    action = batch.action.view(-1, 1, 1).expand(-1, num_options, 1)  # (B, O, 1)
    r_taken = r.gather(-1, action).squeeze(-1)  # (B, O)
    with torch.no_grad():
        target = batch.robustness_reward + gamma * (1.0 - batch.terminated).unsqueeze(-1) * (
            bootstrap_value(r_next, r_next_target, double_q)
        )  # (B, O)
    return masked_mean((r_taken - target).pow(2), mask)
