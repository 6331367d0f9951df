"""The MiniGrid family: Farama's MiniGrid DoorKey and LavaGap as a batched torch port, exact against
the ``minigrid`` package, the layout hidden (docs/minigrid.md); :mod:`.family` is the declaration
(the ``minigrid`` entry point).
"""

from taskvar_torch.families.minigrid.env import MiniGridEnv

__all__ = ["MiniGridEnv"]
