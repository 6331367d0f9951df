"""Per-head target relabelling of raw transitions (one stream of experience: docs/design.md).

The replay buffer holds raw transitions only (observation, action, next observation, env reward,
done flags, and the integer state the subtasks read). :func:`relabel` turns one sampled batch into
the quantities every head's target needs: the environment reward and termination for the averaging,
switching and max-value heads; each option's initiation, termination and subtask reward (paper §3.2);
each capability's robustness reward (paper §3.4.3). Computed once per sample, shared by all heads.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase

from taskvar_torch import keys
from taskvar_torch.subtasks.base import Subtasks


@dataclass
class Transitions:
    """One relabelled batch of B transitions for O options (all tensors on the learner's device)."""

    observation: torch.Tensor  # (B, D)
    next_observation: torch.Tensor  # (B, D)
    action: torch.Tensor  # (B,) int64
    reward: torch.Tensor  # (B,) env reward
    terminated: torch.Tensor  # (B,) float, 1 where the episode ended for good (not truncation)
    initiation: torch.Tensor  # (B, O) bool, s in I_o
    initiation_next: torch.Tensor  # (B, O) bool, s' in I_o
    beta_next: torch.Tensor  # (B, O) float, beta_o(s') (option o terminates at s')
    subtask_reward: torch.Tensor  # (B, O)
    robustness_reward: torch.Tensor | None  # (B, O) or None when the family has no robustness
    instance: torch.Tensor | None = None  # (B, F) hidden instance features, or None (see below)
    nstep: NStep | None = None  # multi-step window quantities (heads/nstep.py), or None
    given: torch.Tensor | None = (
        None  # (B, O) int64 given-policy options' actions at s (-1: learnt)
    )
    given_next: torch.Tensor | None = None  # (B, O) int64 their actions at s'
    seeds: int = 1  # S: the rows are S equal seed-major groups, one per run (heads/seeds.py)


@dataclass
class NStep:
    """The n-step window of each sampled transition (:func:`taskvar_torch.heads.nstep.nstep_returns`)."""

    observation: torch.Tensor  # (B, D) s_{t+k}
    reward: torch.Tensor  # (B,) discounted env-reward sum
    subtask_reward: torch.Tensor  # (B, O) discounted subtask-reward sums
    discount: torch.Tensor  # (B,) gamma^k
    terminated: torch.Tensor  # (B,) float, the episode ended for good at the window's end
    beta: torch.Tensor  # (B, O) float, beta_o(s_{t+k})
    averaging_rows: torch.Tensor  # (B,) bool, the averaging head uses the window (mode -1)
    option_rows: torch.Tensor  # (B, O) bool, option o uses it (mode o)

    @property
    def batch_size(self) -> int:
        return self.action.shape[0]


def has_robustness(subtasks: Subtasks) -> bool:
    """Whether the family defines robustness rewards (Wargus does, windy does not)."""
    return type(subtasks).robustness_reward is not Subtasks.robustness_reward


InstanceFeatures = Callable[[TensorDictBase], torch.Tensor]
"""A family's ``instance_features``: transitions ``(B,)`` -> ``(B, F)`` features of their hidden
``("instance", ...)`` entries (``families/``, ``Family.instance_features``)."""


def relabel(
    td: TensorDictBase,
    subtasks: Subtasks,
    robustness: bool = False,
    instance_features: InstanceFeatures | None = None,
) -> Transitions:
    """Relabel a sampled batch ``td`` (B,) of raw transitions for every head; with
    ``instance_features`` (the family's), also the hidden instance's features where the batch
    holds the ``("instance", ...)`` entries.
    """
    nxt = td.get(keys.NEXT)
    terminated = nxt.get(keys.TERMINATED).reshape(-1).to(torch.float32)  # (B,)
    nstep = None
    if "nstep" in td.keys():
        w = td.get("nstep")
        mode = td.get("behaviour").reshape(-1)
        opts = mode.unsqueeze(-1) == torch.arange(subtasks.num_options, device=mode.device)
        nstep = NStep(
            observation=w.get(keys.OBSERVATION),
            reward=w.get("reward").reshape(-1),
            subtask_reward=w.get("subtask_reward"),
            discount=w.get("discount").reshape(-1),
            terminated=w.get(keys.TERMINATED).reshape(-1).to(torch.float32),
            beta=w.get("beta").to(torch.float32),
            averaging_rows=mode < 0,
            option_rows=opts,
        )
    return Transitions(
        observation=td.get(keys.OBSERVATION),
        next_observation=nxt.get(keys.OBSERVATION),
        action=td.get(keys.ACTION).reshape(-1),
        reward=nxt.get(keys.REWARD).reshape(-1),
        terminated=terminated,
        initiation=subtasks.initiation(td),
        initiation_next=subtasks.initiation(nxt),
        beta_next=subtasks.termination(nxt).to(torch.float32),
        subtask_reward=subtasks.reward(td).to(torch.float32),
        robustness_reward=subtasks.robustness_reward(td).to(torch.float32) if robustness else None,
        instance=(
            instance_features(td)
            if instance_features is not None and keys.INSTANCE in td.keys()
            else None
        ),
        nstep=nstep,
        given=subtasks.given_actions(td),
        given_next=subtasks.given_actions(nxt),
    )
