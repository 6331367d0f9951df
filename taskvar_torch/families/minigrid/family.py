"""The MiniGrid family declaration (docs/minigrid.md), registered through the public door only: the
entry point ``taskvar_torch.families`` names :func:`family` (docs/families.md). Own config keys:
``env.minigrid`` (:class:`MiniGridConfig`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase

from taskvar_torch import keys
from taskvar_torch.contract import HELDOUT_SEED, Family, PatchLayout, TestDistribution
from taskvar_torch.families.minigrid import dynamics as D
from taskvar_torch.families.minigrid.env import OBS_ENCODINGS, ONEHOT_CHANNELS, PARAMS, MiniGridEnv
from taskvar_torch.families.minigrid.layouts import INSTANCE_NAMES, TASKS, check_task

NAME = "minigrid"


@dataclass(frozen=True)
class MiniGridConfig:
    """The MiniGrid family's own env keys (``env.minigrid.*``)."""

    task: str = "doorkey"
    """Which MiniGrid env: doorkey (get the key, open the door, reach the goal) or lavagap (cross
    the lava column through its gap)."""
    size: int = 5
    """Grid side (MiniGrid registers DoorKey 5, 6, 8 and LavaGap 5, 6, 7)."""
    obs_encoding: str = "onehot"
    """Observation: onehot (direction and the 7 x 7 view, object and door state one-hot: 690
    values) or image (direction one-hot and MiniGrid's three codes per cell: 151)."""
    max_steps: int = 0
    """Steps before truncation; 0: MiniGrid's own (10 size^2 for DoorKey, 4 size^2 LavaGap)."""

    def __post_init__(self):
        if self.task not in TASKS:
            raise ValueError(f"task must be one of {list(TASKS)}, got {self.task!r}")
        check_task(self.task, self.size)
        if self.obs_encoding not in OBS_ENCODINGS:
            raise ValueError(
                f"obs_encoding must be one of {list(OBS_ENCODINGS)}, got {self.obs_encoding!r}"
            )
        if self.max_steps < 0:
            raise ValueError(f"max_steps must be >= 0 (0: MiniGrid's own), got {self.max_steps}")


def _section(cfg: Any) -> MiniGridConfig:
    section = getattr(cfg.env, NAME, None)
    return MiniGridConfig() if section is None else section


def _env_kwargs(cfg: Any) -> dict[str, Any]:
    m = _section(cfg)
    return {
        "num_envs": cfg.env.num_envs,
        "instances": cfg.env.instances,
        "task": m.task,
        "size": m.size,
        "max_steps": m.max_steps or None,
        "obs_encoding": m.obs_encoding,
        "seed": cfg.seed,
        "device": cfg.device,
    }


def _subtasks(cfg: Any, env: Any) -> Any:
    from taskvar_torch.families.minigrid.subtasks import DoorKeySubtasks, LavaGapSubtasks

    m = _section(cfg)
    return (DoorKeySubtasks if m.task == "doorkey" else LavaGapSubtasks)(m.size)


def instance_features(td: TensorDictBase) -> torch.Tensor:
    """``(B, 4)``: the layout's parameters (``("instance", "params")``) over 8."""
    params = td.get((keys.INSTANCE, "params"))
    return params.reshape(-1, PARAMS).to(torch.float32) / 8.0


def informed_features(cfg: Any) -> tuple[int, Any]:
    """``(6, features)``: what the informed baseline reads (docs/memory.md), in the agent's own
    frame: the offsets ``(forward, right) / (size - 1)`` to the door or gap, the key (zeros in
    LavaGap) and the goal, from ``("instance", "params")`` and ``cell``.
    """
    m = _section(cfg)
    size, doorkey = int(m.size), m.task == "doorkey"

    def features(td: TensorDictBase) -> torch.Tensor:
        params = td.get((keys.INSTANCE, "params")).reshape(-1, PARAMS).long()  # (B, 4)
        cell = td.get(keys.CELL).reshape(-1).long()  # (B,)
        d, xy = cell % 4, cell // 4
        x, y = xy // size, xy % size
        vec = torch.tensor(D.DIR_TO_VEC, device=cell.device)  # (4, 2)
        fx, fy = vec[d, 0], vec[d, 1]
        goal = torch.full_like(x, size - 2)
        points = [(params[:, 0], params[:, 1]), (params[:, 2], params[:, 3]), (goal, goal)]
        out = []
        for i, (px, py) in enumerate(points):
            dx, dy = px - x, py - y
            rel = torch.stack([dx * fx + dy * fy, dx * -fy + dy * fx], -1).to(torch.float32)
            out.append(rel if doorkey or i != 1 else torch.zeros_like(rel))
        return torch.cat(out, -1) / float(size - 1)  # (B, 6)

    return 6, features


def _patch(cfg: Any) -> PatchLayout:
    channels = ONEHOT_CHANNELS if _section(cfg).obs_encoding == "onehot" else 3
    return PatchLayout(coords_dim=4, channels=channels, size=D.VIEW)


TESTS = {
    "train": TestDistribution("fresh episodes on the training layouts"),
    "heldout": TestDistribution(
        "sealed: the held-out layouts (never trained on) under the held-out seed",
        "heldout",
        seed=HELDOUT_SEED,
    ),
    "minigrid": TestDistribution(
        "sealed: MiniGrid's own layout distribution (held-out layouts included) under the "
        "held-out seed",
        "minigrid",
        seed=HELDOUT_SEED,
    ),
}
"""MiniGrid test distributions (docs/minigrid.md)."""


FAILED_BELOW = 0.1
"""A MiniGrid training seed whose mean return per episode is below 0.1 failed
(``Family.failed_below``, docs/report.md#failed-seeds), chosen from the reward alone: an episode
pays ``1 - 0.9 * steps / max_steps`` when it reaches the goal and 0 otherwise (lava, or truncated
at ``max_steps``: 250 on DoorKey-5x5, 196 on LavaGapS7), so 0.1 is the least return of an episode
that reaches the goal. A success within a tenth of ``max_steps`` pays at least 0.91, so a seed
below 0.1 whose successes are that quick reaches the goal in fewer than 1 episode in 9."""

GYM_IDS = {
    f"taskvar/MiniGrid-{name}-v0": (
        "taskvar_torch.families.minigrid.gym_env:MiniGridGymEnv",
        {"task": task, "size": size},
    )
    for name, task, size in (
        ("DoorKey-5x5", "doorkey", 5),
        ("DoorKey-8x8", "doorkey", 8),
        ("LavaGapS7", "lavagap", 7),
    )
}
"""The port's Gymnasium ids: MiniGrid's names under ``taskvar/``, MiniGrid's spaces."""


def family() -> Family:
    """The MiniGrid :class:`Family` (the package's ``taskvar_torch.families`` entry point)."""
    return Family(
        name=NAME,
        description="MiniGrid DoorKey / LavaGap ported to batched torch: the layout hidden",
        env_class=MiniGridEnv,
        env_kwargs=_env_kwargs,
        subtasks=_subtasks,
        instance_names=INSTANCE_NAMES,
        config_class=MiniGridConfig,
        tests=TESTS,
        instance_dim=PARAMS,
        instance_features=instance_features,
        informed_features=informed_features,
        grid_side=lambda cfg: _section(cfg).size,
        cells=lambda cfg: _section(cfg).size ** 2,
        observation=lambda cfg: _section(cfg).obs_encoding,
        conv_patch=_patch,
        gym_ids=GYM_IDS,
        failed_below=FAILED_BELOW,
    )


__all__ = [
    "GYM_IDS",
    "NAME",
    "TESTS",
    "MiniGridConfig",
    "family",
    "informed_features",
    "instance_features",
]
