"""Controllers (SPEC §3): batched TorchRL policies that read head outputs only.

``averaging`` (paper §3.1), ``options`` (§3.2), ``interruption`` (§3.3, Algorithm 1) and
``hierarchy`` (§3.4, Algorithm 2). Each is a ``TensorDictModuleBase`` carrying ``running_option``
like a recurrent state; install its primer with ``TransformedEnv(env, controller.primer())``.

Examples:
    >>> oracle = WindyOracle()
    >>> ctrl = make_controller("interruption", oracle.heads())
    >>> env = TransformedEnv(WindyGridEnv(num_envs=8), ctrl.primer())
    >>> td = env.rollout(100, ctrl, break_when_any_done=False)
"""

from __future__ import annotations

from taskvar_torch.controllers.averaging import AveragingController, averaging_decide
from taskvar_torch.controllers.base import (
    Controller,
    FusedHeads,
    GymnasiumPolicy,
    argmax0,
    option_first,
    select0,
)
from taskvar_torch.controllers.hierarchy import (
    HierarchyController,
    TreeTables,
    hierarchy_decide,
    hierarchy_decide_of,
)
from taskvar_torch.controllers.interruption import (
    InterruptionController,
    interruption_decide,
    interruption_decide_of,
)
from taskvar_torch.controllers.options import OptionsController, options_decide
from taskvar_torch.heads.bundle import Heads
from taskvar_torch.subtasks.base import Hierarchy, Subtasks

CONTROLLERS: dict[str, type[Controller]] = {
    "averaging": AveragingController,
    "options": OptionsController,
    "interruption": InterruptionController,
    "hierarchy": HierarchyController,
}


def make_controller(
    name: str,
    heads: Heads,
    subtasks: Subtasks | None = None,
    hierarchy: Hierarchy | None = None,
    tau: float | None = None,
    seed: int = 0,
    root_policy: str = "option",
) -> Controller:
    """A controller by name: ``averaging``, ``options``, ``interruption`` or ``hierarchy``.

    ``hierarchy`` needs ``hierarchy`` and ``tau``; ``root_policy`` is its root's policy
    (:class:`HierarchyController`).
    """
    if name not in CONTROLLERS:
        raise ValueError(f"controller must be one of {list(CONTROLLERS)}, got {name!r}")
    if name == "hierarchy":
        if hierarchy is None or tau is None:
            raise ValueError("controller 'hierarchy' needs a hierarchy and a threshold tau")
        return HierarchyController(heads, hierarchy, tau, seed=seed, root_policy=root_policy)
    if name == "averaging":
        return AveragingController(heads, seed=seed)
    return CONTROLLERS[name](heads, subtasks, seed=seed)


__all__ = [
    "CONTROLLERS",
    "AveragingController",
    "Controller",
    "FusedHeads",
    "GymnasiumPolicy",
    "HierarchyController",
    "InterruptionController",
    "OptionsController",
    "TreeTables",
    "argmax0",
    "averaging_decide",
    "hierarchy_decide",
    "hierarchy_decide_of",
    "interruption_decide",
    "interruption_decide_of",
    "make_controller",
    "option_first",
    "options_decide",
    "select0",
]
