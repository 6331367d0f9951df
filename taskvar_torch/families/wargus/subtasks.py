"""Wargus capabilities (paper §3.5.2): ToGoal, FromEnemy and their composition TG+FE.

Everything is computed from raw transitions with the integer state keys the Wargus envs emit
(``families/wargus/dynamics.py``): ``item_seen``, ``patrol_seen`` and the events ``picked`` and ``item_lost``
(of the step that led to the state) at the root of ``td`` (state s)
and under ``("next", ...)`` (state s'), plus ``("next", "terminated")`` (destruction: the only
way a Wargus episode terminates). Inputs have any batch shape ``(*B)``; outputs are ``(*B, 3)``
in the order of :attr:`WargusSubtasks.names`.

Options (paper Figure 3: ``TG+FE`` is the root, ``TG`` and ``FE`` its components):

============  =============  =========================================  ==============================
option        initiation     termination beta(s')                       subtask reward
============  =============  =========================================  ==============================
``TG``        anywhere       patrol seen, or sight of the item just     +1 per item picked
                             lost, or an item just picked
``FE``        anywhere       patrol not seen (escaped)                  -1 per step ending in the
                                                                        patrol's sight, +1 on escaping,
                                                                        -``destruction_penalty`` when
                                                                        destroyed
``TG+FE``     anywhere       never (it is the full task; it ends only   the environment reward (+1 per
                             with the episode)                          item picked); ``composed_reward
                                                                        = "sum"``: TG + FE
============  =============  =========================================  ==============================

Termination is a function of s' only, but TG's reads the *events* of the step that led to s'
(options "terminate upon the occurrence of an event such as seeing the adversary or losing sight
of the goal item", paper §3.5.2): ``item_lost`` (the item was seen at s, is not at s', and none
was picked) and ``picked``; "seeing the patrol" is read as the state ``patrol_seen`` (TG stops
whenever a patrol is in sight, so FE or the root can take over). TG therefore ends on *losing*
sight of the item, not wherever the item is unseen: started (or continuing) where the item is out
of sight, it runs - seeking the item by its always-observed bearing - until it sees a patrol, picks
an item, or sees the item and then loses it again. FE ends when no patrol is in sight (escaped; it
ends at once where started out of sight); TG+FE is the whole task, and its policy is the full-task
averaging policy on the environment reward alone (paper §3.4.2), so its default subtask reward is
the environment's.

Where a component can take control (:meth:`WargusSubtasks.startable`): TG where no patrol is in
sight, FE where one is (each elsewhere would end at once), the root anywhere. The subgoals
*conflict* where a patrol is in sight (:meth:`WargusSubtasks.no_conflict`: no patrol seen).

Why a destruction penalty in FE's subtask reward: without it, destruction ends FE's stream of -1s,
so the FE policy would learn to be shot (one -1) rather than flee (several -1s then +1). The
default ``destruction_penalty = 10`` charges destruction like staying in sight forever at
gamma = 0.9 (``1 / (1 - gamma)``).

Robustness rewards (paper §3.5.2) for the transition s -> s':

- ``TG``: +1 when the step ends where the item is seen, -1 when it leaves the area where the item
  is seen, 0 otherwise. Picking an item counts as ending where the item is seen (+1), even if the
  new item appears out of sight: reaching the goal is not losing it.
- ``FE``: -1 for every step that ends within a patrol's sight, +1 once when escaping it (seen at s,
  not at s'), 0 otherwise; optionally ``-robustness_destruction_penalty`` on destruction (default
  0, the paper's literal reward).
- ``TG+FE``: the sum.

Scale of the threshold (``heads/robustness.py``): the critics are Q-functions of these rewards
under pi^o, discounted by gamma_R and cut at the option's own termination. So R(TG) counts the
steps with the item in sight until the pick (-1 and the end where sight is lost), R(FE) is at most
1 (positive only just before an escape) and about -1 per step still to spend in sight, and
R(TG+FE), which never terminates, sums both along the averaging policy until destruction. A fixed
tau (the paper's 2) means different things on these scales; the calibrated threshold sets
tau(TG+FE) on training states so that the root keeps control on a stated share of the no-conflict
states.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from taskvar_torch import keys
from taskvar_torch.families.wargus.dynamics import (
    ITEM_LOST,
    ITEM_SEEN,
    OBS_AGENT,
    OBS_DIM,
    OBS_ITEM_BEARING,
    OBS_ITEM_OFFSET,
    OBS_ITEM_SEEN,
    OBS_PATROL_BEARING,
    OBS_PATROL_OFFSET,
    OBS_PATROL_SEEN,
    PATROL_SEEN,
    PICKED,
)
from taskvar_torch.subtasks.base import Hierarchy, Subtasks

TG, FE, TG_FE = "TG", "FE", "TG+FE"
COMPOSED_REWARDS = ("env", "sum")  # TG+FE's subtask reward: the environment's, or TG + FE


def _next(td: TensorDictBase, key: str) -> torch.Tensor:
    return td.get((keys.NEXT, key))


class WargusSubtasks(Subtasks):
    """ToGoal, FromEnemy and TG+FE, vectorised over transitions (paper §3.5.2).

    Args:
        destruction_penalty: subtask-reward cost of being destroyed for FE (and TG+FE with
            ``composed_reward="sum"``).
        robustness_destruction_penalty: robustness-reward cost of being destroyed for FE (and
            TG+FE); 0 is the paper's literal reward.
        composed_reward: TG+FE's subtask reward: ``"env"`` (the environment reward: TG+FE is the
            full task, paper §3.4.2) or ``"sum"`` (TG's plus FE's subtask rewards).

    Examples:
        >>> sub = WargusSubtasks()
        >>> sub.names, sub.hierarchy.components("TG+FE")
        (('TG', 'FE', 'TG+FE'), ('TG', 'FE'))
    """

    names = (TG, FE, TG_FE)
    hierarchy = Hierarchy(root=TG_FE, children={TG_FE: (TG, FE)})
    initiable_everywhere = True  # :meth:`initiation` is all True

    def __init__(
        self,
        destruction_penalty: float = 10.0,
        robustness_destruction_penalty: float = 0.0,
        composed_reward: str = "env",
    ):
        if composed_reward not in COMPOSED_REWARDS:
            raise ValueError(
                f"composed_reward must be one of {list(COMPOSED_REWARDS)}, got {composed_reward!r}"
            )
        self.composed_reward = composed_reward
        for name, v in (
            ("destruction_penalty", destruction_penalty),
            ("robustness_destruction_penalty", robustness_destruction_penalty),
        ):
            if not float(v) >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {v}")
        self.destruction_penalty = float(destruction_penalty)
        self.robustness_destruction_penalty = float(robustness_destruction_penalty)

    def initiation(self, td: TensorDictBase) -> torch.Tensor:
        """``(*B, 3)`` bool: every option may start anywhere."""
        seen = td.get(ITEM_SEEN)  # (*B,)
        return torch.ones(*seen.shape, 3, dtype=torch.bool, device=seen.device)

    def termination(self, td: TensorDictBase) -> torch.Tensor:
        """``(*B, 3)`` bool beta at the state at the root of ``td`` (pass ``td["next"]``).

        TG: patrol seen, or the step that led here lost sight of the item (``item_lost``) or picked
        an item; FE: no patrol seen; TG+FE: never (module docstring).
        """
        patrol_seen = td.get(PATROL_SEEN)  # (*B,)
        tg = patrol_seen | td.get(ITEM_LOST) | (td.get(PICKED) > 0)
        return torch.stack((tg, ~patrol_seen, torch.zeros_like(tg)), -1)

    def startable(self, td: TensorDictBase) -> torch.Tensor:
        """``(*B, 3)`` bool: TG where no patrol is seen, FE where one is, TG+FE anywhere."""
        patrol_seen = td.get(PATROL_SEEN)  # (*B,)
        return torch.stack((~patrol_seen, patrol_seen, torch.ones_like(patrol_seen)), -1)

    def no_conflict(self, td: TensorDictBase) -> torch.Tensor:
        """``(*B,)`` bool: no patrol in sight, so seeking the item conflicts with nothing."""
        return ~td.get(PATROL_SEEN)

    def _destroyed(self, td: TensorDictBase) -> torch.Tensor:
        term = td.get((keys.NEXT, keys.TERMINATED), None)
        if term is None:
            return torch.zeros_like(td.get(PATROL_SEEN), dtype=torch.float32)
        return term.reshape(td.get(PATROL_SEEN).shape).to(torch.float32)  # (*B,)

    def _fe(self, td: TensorDictBase, penalty: float) -> torch.Tensor:
        seen, seen_next = td.get(PATROL_SEEN), _next(td, PATROL_SEEN)  # (*B,)
        r = (seen & ~seen_next).to(torch.float32) - seen_next.to(torch.float32)
        if penalty:
            r = r - penalty * self._destroyed(td)
        return r  # (*B,)

    def reward(self, td: TensorDictBase) -> torch.Tensor:
        """``(*B, 3)`` float32 subtask rewards for ``td -> td["next"]`` (module docstring)."""
        tg = _next(td, PICKED).to(torch.float32)  # (*B,) the env reward: +1 per item picked
        fe = self._fe(td, self.destruction_penalty)
        root = tg if self.composed_reward == "env" else tg + fe
        return torch.stack((tg, fe, root), -1)

    def robustness_reward(self, td: TensorDictBase) -> torch.Tensor:
        """``(*B, 3)`` float32 robustness rewards (paper §3.5.2) for ``td -> td["next"]``."""
        seen, seen_next = td.get(ITEM_SEEN), _next(td, ITEM_SEEN)  # (*B,)
        reached = seen_next | (_next(td, PICKED) > 0)
        # -1 exactly on the env's event item_lost (seen at s, not at s', nothing picked)
        tg = reached.to(torch.float32) - (seen & ~reached).to(torch.float32)
        fe = self._fe(td, self.robustness_destruction_penalty)
        return torch.stack((tg, fe, tg + fe), -1)

    def option_input_mask(self, obs_dim: int) -> torch.Tensor:
        """``(3, 24)``: TG sees the agent's position and the item's bearing, seen flag and offset;
        FE the agent's position and the patrol's; TG+FE (the full task) everything."""
        if obs_dim != OBS_DIM:
            raise ValueError(f"Wargus observations have {OBS_DIM} values, got {obs_dim}")
        mask = torch.zeros(3, OBS_DIM)
        item = (
            OBS_AGENT,
            OBS_ITEM_BEARING,
            slice(OBS_ITEM_SEEN, OBS_ITEM_SEEN + 1),
            OBS_ITEM_OFFSET,
        )
        patrol = (
            OBS_AGENT,
            OBS_PATROL_BEARING,
            slice(OBS_PATROL_SEEN, OBS_PATROL_SEEN + 1),
            OBS_PATROL_OFFSET,
        )
        for row, parts in ((0, item), (1, patrol)):
            for part in parts:
                mask[row, part] = 1.0
        mask[2] = 1.0
        return mask
