"""The MiniGrid family: Farama's MiniGrid DoorKey and LavaGap as a batched torch port, exact
against the ``minigrid`` package, the layout hidden (docs/minigrid.md; docs/families.md).

Modules: :mod:`.dynamics` (pure batched step and egocentric view), :mod:`.layouts` (every
layout, MiniGrid's probabilities, the sealed split), :mod:`.env`, :mod:`.subtasks` and
:mod:`.family` (the declaration, the ``minigrid`` entry point).
"""

from taskvar_torch.families.minigrid.env import MiniGridEnv

__all__ = ["MiniGridEnv"]
