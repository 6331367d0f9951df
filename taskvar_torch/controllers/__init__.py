"""Controllers (paper §3.1-3.4): batched TorchRL policies that read head outputs only.

``averaging`` (§3.1), ``options`` (§3.2), ``interruption`` (§3.3, Algorithm 1) and ``hierarchy``
(§3.4, Algorithm 2); install a controller's primer with ``TransformedEnv(env,
controller.primer())``.
"""

from __future__ import annotations

from taskvar_torch.controllers.averaging import AveragingController
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
    hierarchy_decide_of,
    hierarchy_decide_table_of,
)
from taskvar_torch.controllers.interruption import (
    InterruptionController,
    interruption_decide_of,
)
from taskvar_torch.controllers.options import OptionsController
from taskvar_torch.controllers.side_by_side import SideBySide
from taskvar_torch.heads.bundle import Heads
from taskvar_torch.heads.robustness import RobustnessCalibration
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
    terminate: bool = False,
    descent: str = "raw",
    calibration: RobustnessCalibration | None = None,
) -> Controller:
    """A controller by name: ``averaging``, ``options``, ``interruption`` or ``hierarchy``.

    ``root_policy`` is the composed root's policy (paper §3.4.2). ``hierarchy`` needs ``hierarchy``
    and ``tau``; ``terminate``, ``descent`` and ``calibration`` are :class:`HierarchyController`'s.
    """
    if name not in CONTROLLERS:
        raise ValueError(f"controller must be one of {list(CONTROLLERS)}, got {name!r}")
    if name == "hierarchy":
        if hierarchy is None or tau is None:
            raise ValueError("controller 'hierarchy' needs a hierarchy and a threshold tau")
        return HierarchyController(
            heads,
            hierarchy,
            tau,
            seed=seed,
            root_policy=root_policy,
            subtasks=subtasks if terminate else None,
            descent=descent,
            calibration=calibration,
        )
    if name == "averaging":
        return AveragingController(heads, seed=seed)
    return CONTROLLERS[name](
        heads, subtasks, seed=seed, root_policy=root_policy, hierarchy=hierarchy
    )


__all__ = [
    "CONTROLLERS",
    "AveragingController",
    "Controller",
    "FusedHeads",
    "GymnasiumPolicy",
    "HierarchyController",
    "InterruptionController",
    "OptionsController",
    "SideBySide",
    "TreeTables",
    "argmax0",
    "hierarchy_decide_of",
    "hierarchy_decide_table_of",
    "interruption_decide_of",
    "make_controller",
    "option_first",
    "select0",
]
