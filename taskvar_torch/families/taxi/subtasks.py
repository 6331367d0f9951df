"""Taxi capabilities (paper §3.2): Dietterich's MAXQ decomposition of Taxi-v4 as flat options.

Computed from the Taxi-v4 state ``cell`` at ``td`` (s) and ``("next", ...)`` (s') and the env
reward; inputs ``(*B)``, outputs ``(*B, 6)`` in :attr:`TaxiSubtasks.names` order. A state is
*delivered* when ``passenger == destination``; every option terminates there.

- ``to_R`` .. ``to_B``: initiable when not delivered and not at the landmark; end at it; -1 a step
  and ``-end_penalty`` more for a step that delivers away from it.
- ``pickup``: initiable with the passenger waiting on the taxi's landmark; ends with it aboard; the
  env reward.
- ``dropoff``: initiable with the passenger aboard at the destination; ends delivered; the env
  reward.

The options are flat (``hierarchy`` is ``None``); docs/taxi.md#the-family.
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
    """Navigate to each landmark, pickup, dropoff (module docstring); ``end_penalty``: a navigation
    option's extra cost of delivering away from its landmark.
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
        """``(*B, 6)`` float32 subtask rewards of ``td -> td["next"]`` (reads ``cell``, ``("next",
        "cell")``, ``("next", "reward")``).
        """
        nxt = td.get(keys.NEXT)
        at2, _, _, _, delivered2 = self._parts(nxt)
        env_r = nxt.get(keys.REWARD).to(torch.float32).reshape(delivered2.shape)  # (*B,)
        cut = (delivered2.unsqueeze(-1) & ~at2).to(torch.float32)  # (*B, 4) delivered away
        nav = -1.0 - self.end_penalty * cut
        return torch.cat([nav, env_r.unsqueeze(-1), env_r.unsqueeze(-1)], -1)
