"""Wargus capabilities (paper §3.5.2, SPEC §1.2): ToGoal, FromEnemy and their composition TG+FE.

Everything is computed from raw transitions with the integer state keys the Wargus envs emit
(``envs/wargus.py``): ``item_seen``, ``patrol_seen`` and the events ``picked`` and ``item_lost``
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
``TG+FE``     anywhere       never (it is the full task; it ends only   TG + FE
                             with the episode)
============  =============  =========================================  ==============================

Termination is a function of s' only, but TG's reads the *events* of the step that led to s'
(SPEC §1.2: options "terminate on events: seeing the patrol, losing sight of the item, picking the
item, escaping the patrol's sight"): ``item_lost`` (the item was seen at s, is not at s', and none
was picked) and ``picked``; "seeing the patrol" is read as the state ``patrol_seen`` (TG stops
whenever a patrol is in sight, so FE or the root can take over). TG therefore ends on *losing*
sight of the item, not wherever the item is unseen: started (or continuing) where the item is out
of sight, it runs - seeking the item by its always-observed bearing - until it sees a patrol, picks
an item, or sees the item and then loses it again. (An earlier state-based rule, ``item not seen``,
made TG a one-step option wherever the item was unseen, so it never learnt to seek by bearing.)
FE ends when no patrol is in sight (escaped; it ends at once where started out of sight); TG+FE is
the whole task.

Why a destruction penalty in FE's subtask reward: without it, destruction ends FE's stream of -1s,
so the FE policy would learn to be shot (one -1) rather than flee (several -1s then +1). The
default ``destruction_penalty = 10`` charges destruction like staying in sight forever at
gamma = 0.9 (``1 / (1 - gamma)``).

Robustness rewards (paper §3.5.2, SPEC §1.2) for the transition s -> s':

- ``TG``: +1 when the step ends where the item is seen, -1 when it leaves the area where the item
  is seen, 0 otherwise. Picking an item counts as ending where the item is seen (+1), even if the
  new item appears out of sight: reaching the goal is not losing it.
- ``FE``: -1 for every step that ends within a patrol's sight, +1 once when escaping it (seen at s,
  not at s'), 0 otherwise; optionally ``-robustness_destruction_penalty`` on destruction (default
  0, the SPEC's literal reward; destruction then ends the -1s, which ranks being shot above a long
  escape - set it to ``1 / (1 - gamma)`` to rank destruction as never escaping).
- ``TG+FE``: the sum.

Scale of the threshold tau = 2 (SPEC §1.2): robustness critics are Q-functions of these rewards
under the learner's discount gamma. With gamma = 0.9 a sustained +1 is worth 1 / (1 - 0.9) = 10
and a sustained -1 is -10, so R(TG) ranges over about [-1, 10]: R(TG) > 2 means "the item is seen
and, following the option's own policy (``train.robustness_target = "option"``), will stay seen
for at least about 2-3 more steps". Out of sight the +1s start k steps later, discounted by
0.9^k, and stop soon after the item is picked, so R > 2 rarely holds there: at tau = 2 control
mostly falls to TG wherever the item is unseen (README "Wargus Figure 4"). R(FE) lies in about [-10, 1] (it only
exceeds 0 just before an escape), so it never exceeds tau = 2: FE is a leaf and leaves act without
the threshold test in Algorithm 2. R(TG+FE) > 2 where the item is seen and the patrol is not.
With gamma = 0.99 the same rewards are worth 100 and tau should scale with ``1 / (1 - gamma)``
(e.g. tau = 20); we recommend gamma = 0.9 for the robustness critics.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from taskvar_torch import keys
from taskvar_torch.envs.wargus import ITEM_LOST, ITEM_SEEN, PATROL_SEEN, PICKED
from taskvar_torch.subtasks.base import Hierarchy, Subtasks

TG, FE, TG_FE = "TG", "FE", "TG+FE"


def _next(td: TensorDictBase, key: str) -> torch.Tensor:
    return td.get((keys.NEXT, key))


class WargusSubtasks(Subtasks):
    """ToGoal, FromEnemy and TG+FE, vectorised over transitions (paper §3.5.2).

    Args:
        destruction_penalty: subtask-reward cost of being destroyed for FE (and TG+FE).
        robustness_destruction_penalty: robustness-reward cost of being destroyed for FE (and
            TG+FE); 0 is the SPEC's literal reward.

    Examples:
        >>> sub = WargusSubtasks()
        >>> sub.names, sub.hierarchy.components("TG+FE")
        (('TG', 'FE', 'TG+FE'), ('TG', 'FE'))
    """

    names = (TG, FE, TG_FE)
    hierarchy = Hierarchy(root=TG_FE, children={TG_FE: (TG, FE)})

    def __init__(self, destruction_penalty: float = 10.0, robustness_destruction_penalty: float = 0.0):
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
        tg = _next(td, PICKED).to(torch.float32)  # (*B,)
        fe = self._fe(td, self.destruction_penalty)
        return torch.stack((tg, fe, tg + fe), -1)

    def robustness_reward(self, td: TensorDictBase) -> torch.Tensor:
        """``(*B, 3)`` float32 robustness rewards (paper §3.5.2) for ``td -> td["next"]``."""
        seen, seen_next = td.get(ITEM_SEEN), _next(td, ITEM_SEEN)  # (*B,)
        reached = seen_next | (_next(td, PICKED) > 0)
        # -1 exactly on the env's event item_lost (seen at s, not at s', nothing picked)
        tg = reached.to(torch.float32) - (seen & ~reached).to(torch.float32)
        fe = self._fe(td, self.robustness_destruction_penalty)
        return torch.stack((tg, fe, tg + fe), -1)
