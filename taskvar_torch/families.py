"""The family registry: what each task family brings, in one place (docs/design.md, Adding a family).

A family is a distribution over MDPs sharing states and actions (paper §2): its batched env, its
options (subtasks), its named instance distributions and what the heads can use of it. Everything
that depends on the family reads :data:`FAMILIES` (or :func:`family`) instead of testing the
family's name, so a new family is one :class:`Family` entry plus its env and subtasks modules.

Examples:
    >>> family("windy").experiment
    'windy-fig2'
    >>> sorted(FAMILIES)
    ['wargus', 'windy']
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from torchrl.envs import EnvBase

from taskvar_torch.envs import windy
from taskvar_torch.envs.instances import WindyInstances, windy_instances
from taskvar_torch.envs.wargus import WargusConfig, WargusInstances, wargus_instances
from taskvar_torch.envs.wargus_env import WargusEnv
from taskvar_torch.envs.windy_env import OBS_ENCODINGS, WindyGridEnv
from taskvar_torch.heads.networks import PatchLayout
from taskvar_torch.heads.relabel import WINDY_INSTANCE_DIM
from taskvar_torch.subtasks.base import Subtasks
from taskvar_torch.subtasks.wargus import WargusSubtasks
from taskvar_torch.subtasks.windy import WindySubtasks

if TYPE_CHECKING:  # the config imports this registry to validate family keys
    from taskvar_torch.config import Config, EnvConfig

GENERATED = "generated"
"""``env.layout`` value that builds the grid from ``env.height``/``env.width``/... (make_layout)."""
_GENERATOR_KEYS = ("height", "width", "num_exits", "wall_col", "wind_cells_per_exit")
EXACT_ORACLE_CELLS = 400
"""Windy layouts up to this many cells get the exact oracle in reports (docs/oracle.md)."""


@dataclass(frozen=True)
class TestDistribution:
    """A named test distribution of a family (``taskvar eval --test NAME``): which instances its
    episodes draw and which env keys it changes from the bundle's training config.

    Attributes:
        description: what it shifts, in one line (docs/evaluation.md lists them all).
        instances: a named instance distribution or the fields of one (a dict).
        overrides: config overrides of ``env`` keys (``key=value``), validated like a config.
    """

    __test__ = False  # not a pytest test class

    description: str
    instances: Any = "train"
    overrides: tuple[str, ...] = ()


@dataclass(frozen=True)
class Family:
    """One task family: how to build its env and options from a config, and what it supports.

    Attributes:
        name: the config's ``family`` value.
        experiment: the family's figure experiment (``taskvar experiment NAME``).
        env_kwargs: config -> keyword arguments of ``env_class`` for the training env.
        env_class: the batched TorchRL env (``envs/``).
        subtasks: (config, env) -> the family's options (``subtasks/``).
        instance_names: the named instance distributions (``env.instances``, ``eval.test``).
        validate: checks the family's own ``env`` keys; raises a one-line ``ValueError``.
        grid_side: config -> the grid's side length.
        cells: config -> the number of cells (states of the agent's position).
        observation: config -> the observation encoding's name.
        instance_dim: features of the hidden instance the heads may read offline
            (``train.max_value_estimator=instance``); ``None``: not supported.
        conv_patch: config -> the observation's patch layout (``heads.network=conv``); ``None``:
            not supported.
        option_inputs: the subtasks define per-option input features
            (``heads.option_inputs=subtask``).
        exact_oracle: small instances have exact values (``oracle/``).
        tests: the named test distributions (``taskvar eval --test``), the first the default.
        instance_fields: an instance distribution (name, dict or object) -> its fields as a dict,
            for ``--shift env.instances.FIELD=...``; ``None``: the instances cannot be shifted.
        make_instances: fields -> an instance distribution (raises a one-line ``ValueError``).
    """

    name: str
    experiment: str
    env_kwargs: Callable[[Config], dict[str, Any]]
    env_class: type[EnvBase]
    subtasks: Callable[[Config, EnvBase], Subtasks]
    instance_names: tuple[str, ...]
    validate: Callable[[Config], None]
    grid_side: Callable[[Config], int]
    cells: Callable[[Config], int]
    observation: Callable[[Config], str]
    instance_dim: int | None = None
    conv_patch: Callable[[Config], PatchLayout] | None = None
    option_inputs: bool = False
    exact_oracle: bool = False
    tests: dict[str, TestDistribution] = dataclasses.field(default_factory=dict)
    instance_fields: Callable[[Any], dict[str, Any]] | None = None
    make_instances: Callable[[dict[str, Any]], Any] | None = None

    def make_env(
        self,
        cfg: Config,
        num_envs: int | None = None,
        *,
        seed: int | None = None,
        index_offset: int = 0,
        instances: Any = None,
        noise_seed: int | None = None,
        validate_actions: bool | None = None,
    ) -> EnvBase:
        """The family's batched env of ``cfg`` (no transforms). ``None`` keeps the config's value
        (``env.num_envs``, ``seed``, ``env.instances``); ``index_offset`` is the global index of
        sub-environment 0 in the keyed streams (envs with offsets 0, n, 2n... are disjoint slices
        of one env of the summed size); ``noise_seed`` (windy) keys the gusts apart from the
        instances."""
        kw = self.env_kwargs(cfg)
        kw["index_offset"] = int(index_offset)
        if num_envs is not None:
            kw["num_envs"] = int(num_envs)
        if seed is not None:
            kw["seed"] = int(seed)
        if instances is not None:
            kw["instances"] = instances
        if noise_seed is not None:
            kw["noise_seed"] = int(noise_seed)
        if validate_actions is not None:
            kw["validate_actions"] = bool(validate_actions)
        return self.env_class(**kw)

    def require(self, cfg: Config, what: str) -> None:
        """Refuse a config of another family for ``what`` (an experiment or command)."""
        if cfg.family != self.name:
            raise ValueError(f"{what} needs family={self.name!r}, got family={cfg.family!r}")


# --------------------------------------------------------------------------------------------
# windy


def windy_layout(env: EnvConfig) -> windy.WindyLayout:
    """The windy layout an ``EnvConfig`` describes (a name, a map string, or generated).

    Raises:
        ValueError: naming ``env.layout`` or the generator key at fault.
    """
    if env.layout != GENERATED:
        stray = [k for k in _GENERATOR_KEYS if getattr(env, k) is not None]
        if stray:
            raise ValueError(
                f"env.{stray[0]} is only read when env.layout={GENERATED!r}; "
                f"remove it or set env.layout={GENERATED!r} (env.layout is {env.layout!r})"
            )
        if env.layout in windy.LAYOUTS:
            return windy.WindyLayout.named(env.layout)
        if "\n" not in env.layout.strip():
            raise ValueError(
                f"env.layout must be one of {sorted([*windy.LAYOUTS, GENERATED])} or a multi-line "
                f"map string, got {env.layout!r}"
            )
        try:
            return windy.WindyLayout.from_map(env.layout)
        except ValueError as e:
            raise ValueError(f"env.layout: {e}") from None
    for k in ("height", "width"):
        if getattr(env, k) is None:
            raise ValueError(f"env.{k} is required when env.layout={GENERATED!r}")
    try:
        return windy.make_layout(
            env.height,
            env.width,
            num_exits=2 if env.num_exits is None else env.num_exits,
            wall_col=env.wall_col,
            wind_cells_per_exit=1 if env.wind_cells_per_exit is None else env.wind_cells_per_exit,
        )
    except ValueError as e:
        raise ValueError(f"env (layout={GENERATED!r}): {e}") from None


def windy_env_kwargs(cfg: Config) -> dict[str, Any]:
    """Keyword arguments of ``WindyGridEnv`` for the training environment of ``cfg``.

    Examples:
        >>> env = WindyGridEnv(**windy_env_kwargs(cfg))  # doctest: +SKIP
    """
    FAMILIES["windy"].require(cfg, "windy_env_kwargs")
    e = cfg.env
    return {
        "num_envs": e.num_envs,
        "layout": windy_layout(e),
        "instances": e.instances,
        "horizon": e.horizon,
        "obs_encoding": e.obs_encoding,
        "patch_radius": e.patch_radius,
        "seed": cfg.seed,
        "device": cfg.device,
    }


def _one_of(key: str, value: Any, allowed: tuple[str, ...]) -> None:
    if value not in allowed:
        raise ValueError(f"{key} must be one of {sorted(allowed)}, got {value!r}")


def _validate_windy(cfg: Config) -> None:
    env = cfg.env
    _one_of("env.instances", env.instances, WindyInstances.NAMES)
    _one_of("eval.test", cfg.eval.test, WindyInstances.NAMES)
    if env.horizon is not None and env.horizon < 1:
        raise ValueError(f"env.horizon must be >= 1, got {env.horizon}")
    _one_of("env.obs_encoding", env.obs_encoding, OBS_ENCODINGS)
    if env.patch_radius is not None and env.patch_radius < 0:
        raise ValueError(f"env.patch_radius must be >= 0, got {env.patch_radius}")
    if cfg.heads.option_inputs == "subtask" and env.obs_encoding != "exits_patch":
        raise ValueError(
            "heads.option_inputs='subtask' on the windy family needs env.obs_encoding="
            f"'exits_patch' (each exit's offset), got env.obs_encoding={env.obs_encoding!r}"
        )
    windy_layout(env)  # raises a ValueError naming the layout keys


def _windy_side(cfg: Config) -> int:
    lay = windy_layout(cfg.env)
    return max(lay.height, lay.width)


def _windy_patch(cfg: Config) -> PatchLayout:
    if cfg.env.obs_encoding != "coords_patch":
        raise ValueError(
            "heads.network='conv' needs env.obs_encoding='coords_patch', "
            f"got env.obs_encoding={cfg.env.obs_encoding!r}"
        )
    # coords_patch: (row, col), then 3 (2r+1)^2 channels
    return PatchLayout(coords_dim=2, channels=3, size=2 * cfg.env.patch_radius + 1)


def _windy_fields(spec: Any) -> dict[str, Any]:
    inst = windy_instances(spec)
    return {
        "p_low": inst.p_low,
        "p_high": inst.p_high,
        "directions": list(inst.directions),
        "points": None if inst.points is None else [list(p) for p in inst.points],
    }


def _windy_make_instances(fields: dict[str, Any]) -> WindyInstances:
    fields = dict(fields)
    if "p" in fields:  # one wind strength: p_low = p_high = p
        p = fields.pop("p")
        fields.update(p_low=p, p_high=p)
    if isinstance(fields.get("directions"), str):
        fields["directions"] = tuple(d for d in fields["directions"].split("+") if d)
    return windy_instances(fields)


WINDY_TESTS = {
    "train": TestDistribution("the training distribution: p ~ U[0, 1], wind north or south"),
    "south": TestDistribution("only southerly winds (push south), p ~ U[0, 1]", "south"),
    "north": TestDistribution("only northerly winds (push north), p ~ U[0, 1]", "north"),
    "calm": TestDistribution(
        "calm winds: p ~ U[0, 0.3], north or south", {"p_low": 0.0, "p_high": 0.3}
    ),
    "stormy": TestDistribution(
        "stormy winds: p ~ U[0.7, 1], north or south", {"p_low": 0.7, "p_high": 1.0}
    ),
    "middle_exits": TestDistribution(
        "another 5x5 layout: the exits in the middle rows (training winds)",
        overrides=("env.layout=middle_exits",),
    ),
    "whole_column_windy": TestDistribution(
        "another 5x5 layout: wind in the whole column before the wall (training winds)",
        overrides=("env.layout=whole_column_windy",),
    ),
}
"""Windy test distributions (docs/evaluation.md); the layouts need a bundle of the same size."""


# --------------------------------------------------------------------------------------------
# wargus


def _wargus_env_kwargs(cfg: Config) -> dict[str, Any]:
    return {
        "num_envs": cfg.env.num_envs,
        "config": dataclasses.asdict(cfg.env.wargus),
        "instances": cfg.env.instances,
        "seed": cfg.seed,
        "device": cfg.device,
    }


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
}
"""Wargus test distributions (docs/evaluation.md), fresh instances unless stated."""


def _validate_wargus(cfg: Config) -> None:
    _one_of("env.instances", cfg.env.instances, WargusInstances.NAMES)
    _one_of("eval.test", cfg.eval.test, WargusInstances.NAMES)
    try:
        WargusConfig(**dataclasses.asdict(cfg.env.wargus))
    except ValueError as e:
        raise ValueError(f"env.wargus.{e}") from None


# --------------------------------------------------------------------------------------------
# the registry

FAMILIES: dict[str, Family] = {
    "windy": Family(
        name="windy",
        experiment="windy-fig2",
        env_kwargs=windy_env_kwargs,
        env_class=WindyGridEnv,
        subtasks=lambda cfg, env: WindySubtasks(env.model, obs_encoding=cfg.env.obs_encoding),
        instance_names=WindyInstances.NAMES,
        validate=_validate_windy,
        grid_side=_windy_side,
        cells=lambda cfg: windy_layout(cfg.env).num_cells,
        observation=lambda cfg: cfg.env.obs_encoding,
        instance_dim=WINDY_INSTANCE_DIM,
        conv_patch=_windy_patch,
        option_inputs=True,
        exact_oracle=True,
        tests=WINDY_TESTS,
        instance_fields=_windy_fields,
        make_instances=_windy_make_instances,
    ),
    "wargus": Family(
        name="wargus",
        experiment="wargus-fig4",
        env_kwargs=_wargus_env_kwargs,
        env_class=WargusEnv,
        subtasks=lambda cfg, env: WargusSubtasks(composed_reward=cfg.train.composed_reward),
        instance_names=WargusInstances.NAMES,
        validate=_validate_wargus,
        grid_side=lambda cfg: int(cfg.env.wargus.size),
        cells=lambda cfg: int(cfg.env.wargus.size) ** 2,
        observation=lambda cfg: "wargus",
        option_inputs=True,
        tests=WARGUS_TESTS,
        instance_fields=_wargus_fields,
        make_instances=_wargus_make_instances,
    ),
}
"""Every family, by its config name."""


def family(cfg_or_name: Config | str) -> Family:
    """The registry entry of a config (its ``family``) or of a family name."""
    name = cfg_or_name if isinstance(cfg_or_name, str) else cfg_or_name.family
    if name not in FAMILIES:
        raise ValueError(f"family must be one of {sorted(FAMILIES)}, got {name!r}")
    return FAMILIES[name]


__all__ = [
    "FAMILIES",
    "GENERATED",
    "Family",
    "TestDistribution",
    "family",
    "windy_env_kwargs",
    "windy_layout",
]
