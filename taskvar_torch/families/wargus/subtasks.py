"""Wargus capabilities (paper §3.5.2): ToGoal, FromEnemy and their composition TG+FE.

Computed from raw transitions with the integer state keys the Wargus envs emit
(``families/wargus/dynamics.py``): ``item_seen``, ``patrol_seen``, ``picked`` and ``item_lost``
at the root of ``td`` (s) and under ``("next", ...)`` (s'), and ``("next", "terminated")``
(destruction). Any batch shape ``(*B)``; outputs ``(*B, 3)`` in :attr:`WargusSubtasks.names`
order.

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

TG ends on *losing* sight of the item (an event of the step, paper §3.5.2), not wherever it is
unseen. :meth:`WargusSubtasks.startable`: TG where no patrol is seen, FE where one is, the root
anywhere; the subgoals conflict where a patrol is seen (:meth:`WargusSubtasks.no_conflict`).

Robustness rewards (paper §3.5.2) for s -> s': ``TG``: +1 when the step ends with the item seen
(a pick counts), -1 when it leaves sight of it, else 0; ``FE``: -1 per step ending in a patrol's
sight, +1 once on escaping, optionally ``-robustness_destruction_penalty`` on destruction;
``TG+FE``: the sum. The critics' scales differ per option (R(FE) <= 1, R(TG+FE) sums both until
destruction), hence the calibrated threshold (docs/hierarchy-critics.md).
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
        destruction_penalty: subtask-reward cost of destruction for FE (and TG+FE with ``"sum"``).
        robustness_destruction_penalty: robustness-reward cost of destruction for FE and TG+FE (0:
            the paper's literal reward).
        composed_reward: TG+FE's subtask reward, ``"env"`` (the full task, paper §3.4.2) or
            ``"sum"`` (TG's plus FE's).
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
        """``(*B, 3)`` bool beta at the state at the root of ``td`` (pass ``td["next"]``; module
        docstring)."""
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
