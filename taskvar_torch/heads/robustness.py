"""Robustness critics R(o, s, a) (paper §3.4.3, §3.5.2): subtask attainability by Q-learning.

One network outputs every capability's critic ``(B, O, A)``, learnt by TD on the family's robustness
reward at ``train.robustness_gamma``. The default target bootstraps with the option's own next
action up to its termination (``train.robustness_target = "option"``, ``train.robustness_until =
"termination"``):

    y_o = rr_o + gamma_R * (1 - terminated) * (1 - beta_o(s')) * R_o,target(s', pi^o(s'))

``"greedy"`` is plain (double) Q-learning on R. A composed subtask's update mask is its own
initiation set or'ed with its components' (§3.4.1, :func:`parent_closure`). The threshold tau is
fixed or calibrated (:class:`RobustnessCalibration`); docs/hierarchy-critics.md.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from taskvar_torch.heads.relabel import Transitions
from taskvar_torch.heads.targets import bootstrap_value, masked_mean
from taskvar_torch.subtasks.base import Hierarchy

ROBUSTNESS_TARGETS = ("greedy", "option")  # next action of the TD target: argmax R_o, or pi^o
ROBUSTNESS_UNTIL = ("episode", "termination")  # the critic's horizon: the episode, or beta_o


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
    until_termination: bool = False,
) -> torch.Tensor:
    """Sum over capabilities of each critic's mean squared TD error (scalar): the option's own
    policy at s' with ``next_action``, else (double) Q-learning; no bootstrap where the option
    terminates with ``until_termination``.
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
        cont = (1.0 - batch.terminated).unsqueeze(-1)  # (B, 1)
        if until_termination:
            cont = cont * (1.0 - batch.beta_next)  # (B, O)
        target = batch.robustness_reward + gamma * cont * v_next
    return masked_mean((r_taken - target).pow(2), mask, batch.seeds)


@dataclass(frozen=True)
class RobustnessCalibration:
    """Per-capability thresholds and scales of the robustness critics, set on training states.

    ``tau[o]``: the ``1 - keep_share`` quantile of R(o, s, pi^o(s)) over the states where o's
    subgoals do not conflict (composed, §3.5.3; the fixed threshold where the family names none) or
    where o can take control (leaves). ``scale[o]``: its standard deviation where o can take
    control, for the descent's ``(R - tau) / scale``.
    """

    tau: torch.Tensor  # (O,)
    scale: torch.Tensor  # (O,)

    def to(self, device: torch.device | str) -> RobustnessCalibration:
        return RobustnessCalibration(self.tau.to(device), self.scale.to(device))


def calibrate_robustness(
    robustness: torch.Tensor,  # (B, O) R(o, s, pi^o(s)) under each option's own action
    startable: torch.Tensor,  # (B, O) bool: o can take control at s
    no_conflict: torch.Tensor | None,  # (B,) bool: the subgoals do not conflict at s; None: unnamed
    composed: torch.Tensor,  # (O,) bool: o has components
    keep_share: float,
    default_tau: float,
) -> RobustnessCalibration:
    """:class:`RobustnessCalibration` from a sample of training states; a capability with no
    qualifying state keeps ``default_tau`` and a unit scale.
    """
    if not 0.0 < keep_share < 1.0:
        raise ValueError(f"keep_share must be in (0, 1), got {keep_share}")
    r = robustness.detach().to(torch.float32)
    O = r.shape[1]  # noqa: E741
    tau = torch.full((O,), float(default_tau), dtype=torch.float32, device=r.device)
    scale = torch.ones(O, dtype=torch.float32, device=r.device)
    for o in range(O):
        own = startable[:, o]
        if bool(composed[o]):
            pool = own & no_conflict if no_conflict is not None else torch.zeros_like(own)
        else:
            pool = own
        if bool(pool.any()):
            tau[o] = torch.quantile(r[pool, o], 1.0 - keep_share)
        if int(own.sum()) > 1:
            scale[o] = r[own, o].std().clamp(min=1e-3)
    return RobustnessCalibration(tau, scale)
