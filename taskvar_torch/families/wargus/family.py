"""The Wargus family's declaration (paper §3.5, docs/wargus-fig4.md): :func:`family` is the
``wargus`` entry point (docs/families.md).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch

from taskvar_torch import keys
from taskvar_torch.contract import (
    HELDOUT_SEED,
    HELDOUT_SEEDS,
    HELDOUT_SIZE,
    Experiment,
    Family,
    TestDistribution,
    one_of,
)
from taskvar_torch.families.wargus import dynamics as wargus
from taskvar_torch.families.wargus.dynamics import WargusConfig, WargusInstances, wargus_instances
from taskvar_torch.families.wargus.env import WargusEnv
from taskvar_torch.families.wargus.subtasks import COMPOSED_REWARDS, WargusSubtasks

if TYPE_CHECKING:
    from taskvar_torch.config import Config


MAX_COUNT = 2**31 - 1
"""Largest count of Figure 4's keys (the config's counts' bound, config/validate.py)."""
FIG4_BASELINES = ("recurrent",)
"""The baselines ``experiment.baselines`` may name (families/wargus/fig4_recurrent.py)."""


@dataclass(frozen=True)
class WargusSection(WargusConfig):
    """The Wargus family's own env keys, ``env.wargus.*``: the dynamics' shape constants
    (:class:`WargusConfig`, what the env is built from) and the composed option's reward."""

    composed_reward: str = "env"
    """Subtask reward of the composed option TG+FE: env (the environment reward: it is the full
    task, paper §3.4.2) or sum (TG's plus FE's subtask rewards)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        one_of("composed_reward", self.composed_reward, COMPOSED_REWARDS)


@dataclass(frozen=True)
class Fig4Config:
    """Figure 4's own keys, read flat under ``experiment.*`` in a Wargus config beside the shared
    ``experiment.runs`` (the repetitions) and ``experiment.quick_overrides``."""

    trials: int = 500
    """Wargus Figure 4: trials per repetition."""
    learning_episodes_per_trial: int = 30
    """Wargus Figure 4: learning episodes per trial."""
    test_episodes_per_trial: int = 5
    """Wargus Figure 4: nominal test episodes per trial (fixed seeds, no learning)."""
    baselines: tuple[str, ...] = ()
    """Wargus Figure 4: baseline agents run through the same protocol beside the paper's methods,
    each a curve of its own (``recurrent``: docs/wargus-fig4.md#memory); default none."""

    def __post_init__(self) -> None:
        for name in ("trials", "learning_episodes_per_trial", "test_episodes_per_trial"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= MAX_COUNT:
                raise ValueError(f"{name} must be in [1, {MAX_COUNT}], got {v}")
        b = list(self.baselines)
        if any(x not in FIG4_BASELINES for x in b) or len(set(b)) != len(b):
            raise ValueError(
                f"baselines must be distinct names among {list(FIG4_BASELINES)}, got {b}"
            )


def own_keys(cfg: Config) -> WargusSection:
    """The config's Wargus keys (``env.wargus``; defaults where it was built without them)."""
    return getattr(cfg.env, "wargus", None) or WargusSection()


def section(cfg: Config) -> WargusConfig:
    """The dynamics' constants of the config's Wargus keys (what the env is built from)."""
    return WargusConfig.from_any(own_keys(cfg))


def _wargus_env_kwargs(cfg: Config) -> dict[str, Any]:
    return {
        "num_envs": cfg.env.num_envs,
        "config": dataclasses.asdict(section(cfg)),
        "instances": cfg.env.instances,
        "seed": cfg.seed,
        "device": cfg.device,
    }


def wargus_state_features(td: Any, size: int, num_patrols: int, num_items: int) -> torch.Tensor:
    """``(B, 2 * (M + K))``: every item's and patrol's ``(row, col) / (size - 1)`` from
    ``("instance", "item_pos" | "patrol_pos")``; read only by the ``informed`` baseline
    (docs/memory.md); other counts raise ``ValueError``.
    """
    items = td.get((keys.INSTANCE, wargus.ITEM_POS))
    patrols = td.get((keys.INSTANCE, wargus.PATROL_POS))
    want = ((int(num_items), 2), (int(num_patrols), 2))
    if (tuple(items.shape[-2:]), tuple(patrols.shape[-2:])) != want:
        raise ValueError(
            f"the informed baseline reads {num_items} item(s) and {num_patrols} patrol(s); this "
            f"env has {items.shape[-2]} and {patrols.shape[-2]}"
        )
    B = items.shape[0]
    pos = torch.cat([items.reshape(B, -1), patrols.reshape(B, -1)], dim=-1)
    return pos.to(torch.float32) / float(int(size) - 1)


def _wargus_informed(cfg: Config) -> tuple[int, Callable[[Any], torch.Tensor]]:
    w = section(cfg)
    dim = 2 * (int(w.num_items) + int(w.num_patrols))
    feats = functools.partial(
        wargus_state_features,
        size=int(w.size),
        num_patrols=int(w.num_patrols),
        num_items=int(w.num_items),
    )
    return dim, feats


def _wargus_fields(spec: Any) -> dict[str, Any]:
    inst = wargus_instances(spec)
    return {"seeds": None if inst.seeds is None else list(inst.seeds), "order": inst.order}


def _wargus_make_instances(fields: dict[str, Any]) -> WargusInstances:
    fields = dict(fields)
    if isinstance(fields.get("seeds"), (int, str)):
        fields["seeds"] = [int(s) for s in str(fields["seeds"]).split("+") if s]
    return wargus_instances(fields)


WARGUS_TESTS = {
    "nominal": TestDistribution(
        "the nominal test instances (seeds 0-4: Figure 4's test episodes)", "nominal"
    ),
    "train": TestDistribution("fresh instances of the training distribution", "train"),
    "fast_patrol": TestDistribution(
        "a faster patrol: moves every step (patrol_speed 1.0; paper 0.8)",
        overrides=("env.wargus.patrol_speed=1.0",),
    ),
    "more_patrols": TestDistribution(
        "two patrols instead of one", overrides=("env.wargus.num_patrols=2",)
    ),
    "long_sight": TestDistribution(
        "longer sight: objects seen within 12 cells (paper 8)", overrides=("env.wargus.sight=12",)
    ),
    "short_sight": TestDistribution(
        "shorter sight: objects seen within 6 cells (paper 8)", overrides=("env.wargus.sight=6",)
    ),
    "long_range": TestDistribution(
        "longer shooting range: 7 cells (paper 5)", overrides=("env.wargus.shoot_range=7",)
    ),
    "short_range": TestDistribution(
        "shorter shooting range: 3 cells (paper 5)", overrides=("env.wargus.shoot_range=3",)
    ),
    "large_grid": TestDistribution(
        "a 64x64 grid (paper 32x32; the observation is size-independent)",
        overrides=("env.wargus.size=64",),
    ),
    "heldout": TestDistribution(
        f"sealed held-out instances: {HELDOUT_SIZE} instance seeds of the held-out range, cycled",
        {"seeds": HELDOUT_SEEDS},
        seed=HELDOUT_SEED,
    ),
}
"""Wargus test distributions (docs/evaluation.md), fresh instances unless stated."""


def _validate_wargus(cfg: Config) -> None:
    one_of("env.instances", cfg.env.instances, WargusInstances.NAMES)
    one_of("eval.test", cfg.eval.test, WargusInstances.NAMES)


_GYM = "taskvar_torch.families.wargus.gym_env:WargusGymEnv"
GYM_IDS = {
    "taskvar/Wargus-v0": (_GYM, {}),
    "taskvar/Wargus-Large-v0": (_GYM, {"size": 64, "num_patrols": 3, "horizon": 1000}),
}
"""The Wargus family's Gymnasium ids."""


FIG4 = Experiment(
    "wargus-fig4",
    "taskvar_torch.families.wargus.fig4",
    run="wargus_fig4",
    description="lifelong learning curves of the four methods on Wargus (paper Figure 4)",
    config_class=Fig4Config,
    refusals=(
        (
            "checkpoint",
            "wargus-fig4 learns from scratch (lifelong protocol); --checkpoint is not used",
        ),
        (
            "threads",
            "--threads: wargus-fig4 runs one thread per process (small batches; 2 threads "
            "under contention ran 10x slower); use --workers N to use more cores",
        ),
    ),
)
"""Wargus's figure experiment (paper Figure 4, docs/wargus-fig4.md)."""


FAILED_BELOW = None
"""No failure rule for Wargus (``Family.failed_below``, docs/report.md#failed-seeds): its reward is
+1 per item picked, with no goal; an episode ends when a shot destroys the agent or at the
horizon. Every item counts the same, so no number of items separates failing from gathering
fewer: a low return stays a low score and the cell is unchanged."""


def family() -> Family:
    """The Wargus :class:`Family` (the package's ``taskvar_torch.families`` entry point)."""
    return Family(
        name="wargus",
        description="Wargus resource gathering: item and patrol hidden (paper §3.5)",
        experiment=FIG4,
        env_kwargs=_wargus_env_kwargs,
        env_class=WargusEnv,
        subtasks=lambda cfg, env: WargusSubtasks(composed_reward=own_keys(cfg).composed_reward),
        instance_names=WargusInstances.NAMES,
        validate=_validate_wargus,
        config_class=WargusSection,
        legacy_section=True,  # every config held env.wargus until the families became packages
        legacy_env_keys=("train.composed_reward",),  # at train.* until issue 57
        grid_side=lambda cfg: int(section(cfg).size),
        cells=lambda cfg: int(section(cfg).size) ** 2,
        observation=lambda cfg: "wargus",
        informed_features=_wargus_informed,
        option_inputs=True,
        tests=WARGUS_TESTS,
        instance_fields=_wargus_fields,
        make_instances=_wargus_make_instances,
        gym_ids=GYM_IDS,
        failed_below=FAILED_BELOW,
    )
