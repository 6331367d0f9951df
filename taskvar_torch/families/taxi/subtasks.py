"""Taxi capabilities (paper §3.2; Dietterich's MAXQ decomposition of Taxi-v4 as flat options).

Everything is computed from the Taxi-v4 state integer ``cell`` (0..499, ``families/taxi/dynamics.py``'s
encoding: passenger index 4 = in the taxi) at the root of ``td`` (state s) and under
``("next", ...)`` (state s'), plus the env reward ``("next", "reward")`` for the options whose
subtask reward is the environment's. Inputs have any batch shape ``(*B)``; outputs are
``(*B, 6)`` in the order of :attr:`TaxiSubtasks.names`.

A state is *delivered* when the passenger sits at its destination (``passenger == destination``,
only ever reached by a delivery, which ends the episode): every option terminates there.

===========  =====================================  ==========================  ===================
option       initiation I_o                         termination beta_o(s')      subtask reward
===========  =====================================  ==========================  ===================
``to_R`` ..  not delivered, taxi not at landmark X  taxi at X (or delivered)    -1 per step;
``to_B``                                                                        ``-end_penalty``
                                                                                more if the step
                                                                                delivers away from X
``pickup``   passenger waiting (not aboard, not     passenger aboard (or        the env reward
             delivered), taxi on its landmark       delivered)
``dropoff``  passenger aboard, taxi at the          delivered                   the env reward
             destination
===========  =====================================  ==========================  ===================

Initiation sets matter here (unlike windy and Wargus, where every option starts anywhere): the
controllers pick and draw only among the options initiable at s (Algorithm 1 lines 4 and 7 over
I_o). In every non-delivered state at least one option is initiable (the taxi stands on at most
one landmark, so at least three ``to_*`` are), so mu_bar always has a choice.

Episode end: a delivery ends the episode and every option with it (beta = 1 at delivered
states), as windy's exit options end on the goal side. A navigation option that delivers the
passenger on its way (its policy may use any of the six actions) ends the episode before reaching
its landmark; like windy's wrong-exit penalty, ``end_penalty`` (default 100, the discounted cost
``1 / (1 - gamma)`` of never arriving at gamma = 0.99) charges that, so the option is credited
with reaching *its* landmark only. Truncation at the horizon is the learner's business.

``hierarchy`` is ``None``: the options are flat. A MAXQ-style Get/Put tree (``Get`` over
``to_*`` + ``pickup``, ``Put`` over ``to_*`` + ``dropoff``) would need composed options with
their own heads and robustness rewards; that is the lead's call (not defined here).

Examples:
    >>> from tensordict import TensorDict
    >>> from taskvar_torch.families.taxi.dynamics import encode
    >>> sub = TaxiSubtasks()
    >>> td = TensorDict({"cell": torch.tensor([encode(0, 0, 0, 1)])}, batch_size=[1])
    >>> sub.initiation(td).tolist()  # at R with the passenger waiting at R
    [[False, True, True, True, True, False]]
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from taskvar_torch import keys
from taskvar_torch.families.taxi.dynamics import IN_TAXI, LOC_NAMES, LOCS, NUM_COLS, NUM_LOCS
from taskvar_torch.subtasks.base import Subtasks

NAV_NAMES = tuple(f"to_{n}" for n in LOC_NAMES)
PICKUP, DROPOFF = "pickup", "dropoff"
TAXI_OPTION_NAMES = (*NAV_NAMES, PICKUP, DROPOFF)

Tensor = torch.Tensor


def _landmark_pos(device: torch.device) -> Tensor:
    """``(4,)`` int64 flat taxi positions ``row * 5 + col`` of R, G, Y, B."""
    return torch.tensor([r * NUM_COLS + c for r, c in LOCS], dtype=torch.int64, device=device)


def state_parts(cell: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(pos, passenger, destination)`` of Taxi-v4 states ``(*B,)``: ``pos = row * 5 + col``."""
    cell = cell.to(torch.int64)
    dest = cell % NUM_LOCS
    rest = cell // NUM_LOCS
    return rest // (NUM_LOCS + 1), rest % (NUM_LOCS + 1), dest


class TaxiSubtasks(Subtasks):
    """Navigate to each landmark, pickup, dropoff: MAXQ's subtasks as flat options (module docstring).

    Args:
        end_penalty: extra subtask cost to a navigation option of a step that delivers the
            passenger (ending the episode) away from its landmark.
    """

    names = TAXI_OPTION_NAMES
    hierarchy = None

    def __init__(self, end_penalty: float = 100.0):
        if not float(end_penalty) >= 0.0:
            raise ValueError(f"end_penalty must be >= 0, got {end_penalty}")
        self.end_penalty = float(end_penalty)

    # ---- state predicates ----------------------------------------------------------------------

    @staticmethod
    def _parts(td: TensorDictBase) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """``at (*B, 4)`` taxi on each landmark, ``pos``, ``passenger``, ``destination``,
        ``delivered (*B,)``."""
        cell = td.get(keys.CELL)
        pos, pas, dest = state_parts(cell)
        at = pos.unsqueeze(-1) == _landmark_pos(cell.device)  # (*B, 4)
        delivered = pas == dest  # (*B,): passenger < 4 at its destination
        return at, pos, pas, dest, delivered

    @staticmethod
    def _at_index(at: Tensor, idx: Tensor) -> Tensor:
        """``at[..., idx]`` for an index ``(*B,)`` in 0..3 (clamped; callers mask the rest)."""
        return at.gather(-1, idx.clamp(max=NUM_LOCS - 1).unsqueeze(-1)).squeeze(-1)

    def initiation(self, td: TensorDictBase) -> Tensor:
        """``(*B, 6)`` bool I_o (module docstring): where each option may be started."""
        at, _, pas, dest, delivered = self._parts(td)
        live = ~delivered
        nav = ~at & live.unsqueeze(-1)  # (*B, 4)
        waiting = (pas < IN_TAXI) & live
        pickup = waiting & self._at_index(at, pas)
        dropoff = (pas == IN_TAXI) & self._at_index(at, dest)
        return torch.cat([nav, pickup.unsqueeze(-1), dropoff.unsqueeze(-1)], -1)

    def termination(self, td: TensorDictBase) -> Tensor:
        """``(*B, 6)`` bool beta_o at the state at the root of ``td`` (pass ``td["next"]``)."""
        at, _, pas, _, delivered = self._parts(td)
        d = delivered.unsqueeze(-1)
        nav = at | d
        pickup = (pas == IN_TAXI) | delivered
        return torch.cat([nav, pickup.unsqueeze(-1), delivered.unsqueeze(-1)], -1)

    def reward(self, td: TensorDictBase) -> Tensor:
        """``(*B, 6)`` float32 subtask rewards of ``td -> td["next"]`` (module docstring).

        Reads ``cell``, ``("next", "cell")`` and ``("next", "reward")``.
        """
        nxt = td.get(keys.NEXT)
        at2, _, _, _, delivered2 = self._parts(nxt)
        env_r = nxt.get(keys.REWARD).to(torch.float32).reshape(delivered2.shape)  # (*B,)
        cut = (delivered2.unsqueeze(-1) & ~at2).to(torch.float32)  # (*B, 4) delivered away
        nav = -1.0 - self.end_penalty * cut
        return torch.cat([nav, env_r.unsqueeze(-1), env_r.unsqueeze(-1)], -1)
