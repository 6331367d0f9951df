"""The family registry: what each task family brings, behind one public contract (docs/families.md).

A family is a distribution over MDPs sharing states and actions (paper §2): its batched env, its
options (subtasks), its named instance and test distributions, and what the heads, the exact oracle
and the experiments can use of it. Everything that depends on the family reads the registry
(:func:`family`) instead of testing the family's name, so a new family needs no edit of the package:

- :func:`register_family` adds one from code in the same process;
- the entry-point group ``taskvar_torch.families`` adds those of any installed package (the way
  Gymnasium and pytest find plugins), so the installed ``taskvar`` command sees them; an entry
  point names a :class:`Family` or a callable returning one;
- :func:`check_family` checks the contract and names what is missing in one line.

The built-in families use the same door: windy and Wargus are registered below with
:func:`register_family`, Taxi through the package's own entry point (``taskvar_torch/taxi.py``).

Examples:
    >>> family("windy").experiment
    'windy-fig2'
    >>> sorted(FAMILIES)[:2]
    ['taxi', 'wargus']
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.metadata
import warnings
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import torch
from torchrl.envs import EnvBase

from taskvar_torch import keys
from taskvar_torch.envs import wargus, windy
from taskvar_torch.envs.instances import WindyInstances, windy_instances
from taskvar_torch.envs.wargus import WargusConfig, WargusInstances, wargus_instances
from taskvar_torch.envs.wargus_env import WargusEnv
from taskvar_torch.envs.windy_env import OBS_ENCODINGS, WindyGridEnv
from taskvar_torch.envs.windy_env import observation_size as windy_observation_size
from taskvar_torch.heads.networks import PatchLayout
from taskvar_torch.heads.relabel import WINDY_INSTANCE_DIM, windy_instance_features
from taskvar_torch.subtasks.base import Subtasks
from taskvar_torch.subtasks.wargus import WargusSubtasks
from taskvar_torch.subtasks.windy import WindySubtasks

Config = Any
"""A :class:`taskvar_torch.config.Config` (not imported: the config package reads this registry,
never the reverse)."""
EnvConfig = Any
"""Its ``env`` section, :class:`taskvar_torch.config.EnvConfig`."""

ENTRY_POINT_GROUP = "taskvar_torch.families"
"""The entry-point group an installed package registers its families under (docs/families.md)."""
BUILTIN = ("windy", "wargus", "taxi")
"""The package's own families; another family of one of these names is refused."""
GENERATED = "generated"
"""``env.layout`` value that builds the grid from ``env.height``/``env.width``/... (make_layout)."""
_GENERATOR_KEYS = ("height", "width", "num_exits", "wall_col", "wind_cells_per_exit")
EXACT_ORACLE_CELLS = 400
"""Windy layouts up to this many cells get the exact oracle in reports (docs/oracle.md)."""
HELDOUT_SEED = 7_000_000
"""First seed of the sealed held-out range ``[HELDOUT_SEED, HELDOUT_SEED + HELDOUT_SIZE)``
(docs/claims.md): no config, doc, test or tuning script names a seed in it
(``tests/test_heldout.py`` checks), so no design choice was ever made on its episodes. Windy and
Taxi play their test distribution under env seed ``HELDOUT_SEED + run``; Wargus plays the
instance seeds of the range."""
MAX_WINDY_SIDE = 4096
"""Largest height or width of a generated windy grid (``env.layout=generated``)."""
MAX_WINDY_CELLS = (1 << 24) - 1
"""Most cells of a windy layout: start cells are drawn by ``rng.draw_index`` (n < 2^24)."""
HELDOUT_SIZE = 300
"""Seeds in the sealed range: Wargus's held-out instances, and the most held-out runs."""


@dataclass(frozen=True)
class TestDistribution:
    """A named test distribution of a family (``taskvar eval --test NAME``): which instances its
    episodes draw and which env keys it changes from the bundle's training config.

    Attributes:
        description: what it shifts, in one line (docs/evaluation.md lists them all).
        instances: a named instance distribution or the fields of one (a dict).
        overrides: config overrides of ``env`` keys (``key=value``), validated like a config.
        seed: a sealed test seed (``HELDOUT_SEED``): ``taskvar eval`` plays under it and refuses
            another ``--seed``; ``None``: the evaluation's seed (the bundle's ``seed + 1``).
    """

    __test__ = False  # not a pytest test class

    description: str
    instances: Any = "train"
    overrides: tuple[str, ...] = ()
    seed: int | None = None


@dataclass(frozen=True, kw_only=True)
class Family:
    """One task family: how to build its env and options from a config, and what it supports.

    The first five attributes are required; the rest are optional capabilities (``None``: the
    family does not offer it, and the commands that need it say so in one line). docs/families.md
    has the contract the env and the subtasks must honour, and a walk-through.

    Attributes:
        name: the config's ``family`` value.
        env_class: the batched TorchRL env (a ``BatchedFamilyEnv``); its constructor takes
            ``num_envs``, ``seed``, ``instances``, ``index_offset``, ``noise_seed`` and
            ``validate_actions`` besides what ``env_kwargs`` gives.
        env_kwargs: config -> keyword arguments of ``env_class`` for the training env.
        subtasks: (config, env) -> the family's options (a :class:`Subtasks`).
        instance_names: the named instance distributions (``env.instances``, ``eval.test``).
        config_class: the family's own env keys, a frozen dataclass read under
            ``env.<name>`` (strictly: a misspelt key is a one-line error naming it; its
            ``__post_init__`` range errors start with the field's name). ``None``: no own keys.
        validate: extra checks of a config of this family; raises a one-line ``ValueError``.
        tests: the named test distributions (``taskvar eval --test``), the first the default.
        instance_fields: an instance distribution (name, dict or object) -> its fields as a dict,
            for ``--shift env.instances.FIELD=...``; ``None``: the instances cannot be shifted.
        make_instances: fields -> an instance distribution (raises a one-line ``ValueError``).
        shift_aliases: extra ``env.instances.FIELD`` names ``make_instances`` accepts (windy's
            ``p``: one wind strength for the band).
        instance_dim: features of the hidden instance the heads may read offline
            (``train.max_value_estimator=instance``), computed by ``instance_features``.
        instance_features: a tensordict of transitions -> ``(B, instance_dim)`` features of
            their ``("instance", ...)`` entries.
        informed_features: config -> ``(dim, features)``, what the ``informed`` baseline reads
            beside the observation (docs/memory.md): ``features`` maps transitions to ``(B, dim)``
            features of the hidden instance and state. ``None``: ``(instance_dim,
            instance_features)``. Its own hook because its dimension may depend on the config
            (Wargus: the item and patrol positions) and because only the baseline reads it, never
            the ``instance`` max-value estimator (Definition 1's max over instances).
        oracle: config -> the family's exact oracle for that env, or ``None`` where it has none
            (too large, another encoding). It offers the windy oracle's interface
            (docs/families.md): ``instance_keys``, ``controller_return``, ``averaging_policy``.
        oracle_summary: (heads, config) -> lines comparing the learnt heads with the exact oracle
            (printed after ``taskvar train``); ``None``: nothing printed.
        averaging_optimum: config -> the exact mean-MDP averaging policy ``(cells,)`` over
            ``cell``, the scale experiment's reference (also for grids too large for ``oracle``).
        head_report: (config, heads, with_max_value) -> every head against exact values (the
            scale experiment's ``head_report``).
        experiment: the family's figure experiment (``taskvar experiment NAME``, sweeps).
        grid_side: config -> the grid's side length (the scale experiment's tables).
        cells: config -> the number of positions of the agent.
        observation: config -> the observation encoding's name.
        observation_size: config -> the observation's length, without building the env (the
            memory estimate, :mod:`taskvar_torch.config.memory`); ``None``: read from a
            one-environment env.
        conv_patch: config -> the observation's patch layout (``heads.network=conv``).
        option_inputs: the subtasks define per-option input features
            (``heads.option_inputs=subtask``).
        description: one line for listings.
    """

    name: str
    env_class: type[EnvBase]
    env_kwargs: Callable[[Config], dict[str, Any]]
    subtasks: Callable[[Config, EnvBase], Subtasks]
    instance_names: tuple[str, ...]
    config_class: type | None = None
    validate: Callable[[Config], None] | None = None
    tests: dict[str, TestDistribution] = dataclasses.field(default_factory=dict)
    instance_fields: Callable[[Any], dict[str, Any]] | None = None
    make_instances: Callable[[dict[str, Any]], Any] | None = None
    shift_aliases: tuple[str, ...] = ()
    instance_dim: int | None = None
    instance_features: Callable[[Any], Any] | None = None
    informed_features: Callable[[Config], tuple[int, Callable[[Any], Any]]] | None = None
    oracle: Callable[[Config], Any] | None = None
    oracle_summary: Callable[[Any, Config], list[str]] | None = None
    averaging_optimum: Callable[[Config], Any] | None = None
    head_report: Callable[..., dict[str, Any]] | None = None
    experiment: str | None = None
    grid_side: Callable[[Config], int] | None = None
    cells: Callable[[Config], int] | None = None
    observation: Callable[[Config], str] | None = None
    observation_size: Callable[[Config], int] | None = None
    conv_patch: Callable[[Config], PatchLayout] | None = None
    option_inputs: bool = False
    description: str = ""

    @property
    def exact_oracle(self) -> bool:
        """Whether the family brings an exact oracle (``oracle``)."""
        return self.oracle is not None

    def env_config(self, cfg: Config) -> Any:
        """The family's own keys of ``cfg`` (``cfg.env.<name>``; defaults when the config was
        built without them); ``None`` for a family without ``config_class``."""
        if self.config_class is None:
            return None
        section = getattr(cfg.env, self.name, None)
        return self.config_class() if section is None else section

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
        of one env of the summed size); ``noise_seed`` keys the per-step noise apart from the
        instances (common random numbers for paired episodes)."""
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

    def needs(self, capability: str, what: str) -> Any:
        """The optional attribute ``capability``, or a one-line ``ValueError`` saying that
        ``what`` needs it and this family does not bring it."""
        value = getattr(self, capability)
        if value is None or value == {}:
            raise ValueError(
                f"{what} needs a family with {capability!r}; family {self.name!r} has none "
                "(docs/families.md)"
            )
        return value


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
    family("windy").require(cfg, "windy_env_kwargs")
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
    if env.layout == GENERATED:  # the grid is built below: bound its size first
        for k in ("height", "width"):
            v = getattr(env, k)
            if v is not None and not 1 <= v <= MAX_WINDY_SIDE:
                raise ValueError(f"env.{k} must be in [1, {MAX_WINDY_SIDE}], got {v}")
    layout = windy_layout(env)  # raises a ValueError naming the layout keys
    if layout.num_cells > MAX_WINDY_CELLS:
        raise ValueError(
            f"env.layout has {layout.num_cells} cells; at most {MAX_WINDY_CELLS} (start cells are "
            "drawn from 24-bit integers)"
        )
    side = max(layout.height, layout.width)
    if env.patch_radius is not None and env.patch_radius > side:
        raise ValueError(
            f"env.patch_radius must be in [0, {side}] (the grid's side: a wider patch only adds "
            f"walls), got {env.patch_radius}"
        )


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


def _windy_oracle(cfg: Config) -> Any:
    """The exact oracle of a small one-hot windy layout (docs/oracle.md), else ``None``."""
    if cfg.env.obs_encoding != "onehot":
        return None
    layout = windy_layout(cfg.env)
    if layout.num_cells > EXACT_ORACLE_CELLS:
        return None
    from taskvar_torch.oracle.windy import WindyOracle

    return WindyOracle(
        layout, gamma=cfg.train.gamma, horizon=cfg.env.horizon, train_instances=cfg.env.instances
    )


def windy_sparse_oracle(cfg: Config) -> Any:
    """The exact oracle of a windy layout at any size (oracle/sparse.py)."""
    from taskvar_torch.oracle.sparse import SparseWindyOracle

    return SparseWindyOracle(
        windy_layout(cfg.env),
        gamma=cfg.train.gamma,
        horizon=cfg.env.horizon,
        train_instances=cfg.env.instances,
        device=cfg.device,
    )


def _windy_averaging_optimum(cfg: Config) -> Any:
    """The mean-MDP optimal averaging policy ``(cells,)``: dense on small layouts, successor
    tables beyond (the scale experiment's reference)."""
    oracle = _windy_oracle(cfg) if windy_layout(cfg.env).num_cells <= EXACT_ORACLE_CELLS else None
    if oracle is None:
        oracle = windy_sparse_oracle(cfg)
    return oracle.averaging_policy()


def _windy_head_report(cfg: Config, heads: Any, with_max_value: bool = True) -> dict[str, Any]:
    """Every head against the exact values at any size (oracle/head_report.py)."""
    from taskvar_torch.oracle.head_report import head_report

    return head_report(
        heads,
        windy_sparse_oracle(cfg),
        cfg.env.obs_encoding,
        cfg.env.patch_radius,
        with_max_value=with_max_value,
    )


def _windy_summary(heads: Any, cfg: Config) -> list[str]:
    """The learnt heads beside the exact oracle on the training instances (docs/oracle.md), each
    figure labelled: what it compares, and an option the budget has not learnt (its greedy policy
    never reaches an exit within the horizon)."""
    oracle = _windy_oracle(cfg)
    if oracle is None:
        return []
    from taskvar_torch.heads.validate import compare_with_oracle

    r = compare_with_oracle(heads.cpu(), oracle)
    horizon = cfg.env.horizon
    lines = [
        "learnt heads vs exact oracle (exact expected returns of the greedy policies, not sampled; "
        "training instances, uniform start):",
        f"  averaging policy  {r['averaging_return']:8.3f}   oracle {r['oracle_averaging_return']:8.3f}",
    ]
    unlearnt = []
    for name, a, b in zip(heads.option_names, r["option_returns"], r["oracle_option_returns"]):
        note = ""
        if a <= -horizon + 1e-6 < b:  # the option's greedy policy never reaches its exit
            unlearnt.append(name)
            note = f"   not learnt: never reaches its exit in {horizon} steps"
        lines.append(f"  option {name:<10} {a:8.3f}   oracle {b:8.3f}{note}")
    per_option = ", ".join(
        f"{n} {e:.3f}" for n, e in zip(heads.option_names, r["max_value_error_per_option"])
    )
    lines += [
        f"  mu_bar agreement            {r['mu_bar_agreement']:.3f} on {r['mu_bar_cells']} cells "
        "(share of them where the switching head picks the oracle's option)",
        f"  max |Q_hat - oracle|        {r['max_value_error']:.3f}   (max-value head, largest "
        f"error over the cells; per option: {per_option})",
        f"  interruption agreement      {r['interruption_agreement']:.3f} on "
        f"{r['interruption_pairs']} (cell, option) pairs (share where learnt and exact heads agree "
        "on whether Algorithm 1 interrupts)",
    ]
    if unlearnt:
        lines.append(
            f"  undertrained at {cfg.train.total_frames} training frames: option(s) "
            f"{', '.join(unlearnt)} not learnt yet"
        )
    return lines


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
    "heldout": TestDistribution(
        "sealed held-out episodes: the training distribution under the held-out seed",
        seed=HELDOUT_SEED,
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


def wargus_state_features(td: Any, size: int, num_patrols: int, num_items: int) -> torch.Tensor:
    """``(B, 2 * (num_items + num_patrols))``: every item's and every patrol's ``(row, col)``,
    divided by ``size - 1`` (so in ``[0, 1]`` on a grid of that size), from the transitions'
    ``("instance", "item_pos")`` (B, M, 2) and ``("instance", "patrol_pos")`` (B, K, 2): the
    whole state the agent does not see (its own position is in the observation; the instance
    seed is a random-stream key, not a feature). Read only by the ``informed`` baseline
    (docs/memory.md); an env with other counts is a one-line ``ValueError``."""
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
    w = cfg.env.wargus
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


HELDOUT_SEEDS = tuple(range(HELDOUT_SEED, HELDOUT_SEED + HELDOUT_SIZE))
"""Wargus's sealed held-out instance seeds (the whole held-out range)."""
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
    _one_of("env.instances", cfg.env.instances, WargusInstances.NAMES)
    _one_of("eval.test", cfg.eval.test, WargusInstances.NAMES)
    try:
        WargusConfig(**dataclasses.asdict(cfg.env.wargus))
    except ValueError as e:
        raise ValueError(f"env.wargus.{e}") from None


# --------------------------------------------------------------------------------------------
# the registry


def _entry_points() -> list[importlib.metadata.EntryPoint]:
    """The ``taskvar_torch.families`` entry points of every installed distribution.

    Every copy of a distribution's metadata is read, not only the first on ``sys.path`` (which
    ``importlib.metadata.entry_points`` keeps): a stale ``*.egg-info`` left in a source checkout
    would otherwise hide the installed package's entry points when run from that folder.
    """
    seen, out = set(), []
    for dist in importlib.metadata.distributions():
        for ep in dist.entry_points:
            if ep.group == ENTRY_POINT_GROUP and (ep.name, ep.value) not in seen:
                seen.add((ep.name, ep.value))
                out.append(ep)
    return out


class _Registry(Mapping):
    """Every family by name: the ones registered in this process and, loaded at the first lookup,
    those of installed packages' ``taskvar_torch.families`` entry points."""

    def __init__(self) -> None:
        self._families: dict[str, Family] = {}
        self._entry_points_loaded = False
        self.broken: dict[str, str] = {}
        """Entry points that failed to load: name -> the one-line reason (warned once)."""

    def _load_entry_points(self) -> None:
        if self._entry_points_loaded:
            return
        self._entry_points_loaded = True
        for ep in _entry_points():
            if ep.name in self._families:
                continue
            try:
                obj = ep.load()
                fam = obj if isinstance(obj, Family) else obj()
                if not isinstance(fam, Family):
                    raise TypeError(f"it gives {type(fam).__name__}, not a Family")
                if fam.name != ep.name:
                    raise ValueError(
                        f"the entry point is named {ep.name!r}, its family {fam.name!r}"
                    )
                _check_declaration(fam)
            except (Exception, SystemExit) as e:  # a broken plugin must not break the others
                reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
                if isinstance(e, SystemExit):  # sys.exit() on import: not the command's exit
                    reason = f"it called sys.exit({e.code!r}) on import"
                else:
                    reason = f"{type(e).__name__}: {reason}"
                self.broken[ep.name] = f"entry point {ep.value!r}: {reason}"
                warnings.warn(
                    f"taskvar_torch: family {ep.name!r} from {ep.value!r} could not be loaded: "
                    f"{reason}",
                    stacklevel=2,
                )
                continue
            self._families[fam.name] = fam

    def __getitem__(self, name: str) -> Family:
        if name not in self._families:
            self._load_entry_points()
        return self._families[name]

    def __iter__(self) -> Iterator[str]:
        self._load_entry_points()
        return iter(dict(self._families))

    def __len__(self) -> int:
        self._load_entry_points()
        return len(self._families)

    def __contains__(self, name: object) -> bool:
        if name not in self._families:
            self._load_entry_points()
        return name in self._families

    def __repr__(self) -> str:
        return f"FAMILIES({sorted(self)})"


FAMILIES = _Registry()
"""Every family, by its config name (a read-only mapping; add with :func:`register_family`)."""


def _check_declaration(fam: Family) -> None:
    """What :func:`register_family` checks without building anything: one-line errors."""
    if not isinstance(fam.name, str) or not fam.name.isidentifier():
        raise ValueError(f"family name must be an identifier such as 'taxi', got {fam.name!r}")
    if not (isinstance(fam.env_class, type) and issubclass(fam.env_class, EnvBase)):
        raise ValueError(f"family {fam.name!r}: env_class must be a torchrl EnvBase subclass")
    for attr in ("env_kwargs", "subtasks"):
        if not callable(getattr(fam, attr)):
            raise ValueError(f"family {fam.name!r}: {attr} must be callable")
    if not fam.instance_names or not all(isinstance(n, str) for n in fam.instance_names):
        raise ValueError(f"family {fam.name!r}: instance_names must name at least one distribution")
    if fam.config_class is not None:
        cls = fam.config_class
        params = getattr(cls, "__dataclass_params__", None)
        if params is None or not params.frozen:
            raise ValueError(
                f"family {fam.name!r}: config_class must be a frozen dataclass (env.{fam.name}.*)"
            )
        try:
            cls()
        except Exception as e:
            raise ValueError(
                f"family {fam.name!r}: config_class() must build with its defaults: {e}"
            ) from None
    if fam.informed_features is not None and not callable(fam.informed_features):
        raise ValueError(f"family {fam.name!r}: informed_features must be callable")
    if (fam.instance_dim is None) != (fam.instance_features is None):
        raise ValueError(
            f"family {fam.name!r}: instance_dim and instance_features go together (both or none)"
        )
    for name, dist in fam.tests.items():
        if not isinstance(dist, TestDistribution):
            raise ValueError(f"family {fam.name!r}: tests[{name!r}] must be a TestDistribution")


def register_family(fam: Family, *, replace: bool = False) -> Family:
    """Add ``fam`` to the registry, so every command, experiment and controller can use it.

    Args:
        fam: the family (see :class:`Family` and docs/families.md for the contract).
        replace: replace a family of the same name registered earlier (never a built-in one).

    Returns:
        ``fam``.

    Raises:
        ValueError: in one line, a declaration that breaks the contract, a name of a built-in
            family, or a name already taken (without ``replace``).

    Examples:
        >>> register_family(Family(name="corridor", env_class=CorridorEnv, ...))  # doctest: +SKIP
    """
    if not isinstance(fam, Family):
        raise ValueError(f"register_family takes a Family, got {type(fam).__name__}")
    _check_declaration(fam)
    existing = FAMILIES._families.get(fam.name)
    if existing is not None and existing is not fam:
        if fam.name in BUILTIN:
            raise ValueError(f"family {fam.name!r} is built in; choose another name")
        if not replace:
            raise ValueError(
                f"family {fam.name!r} is already registered; pass replace=True to replace it"
            )
    FAMILIES._families[fam.name] = fam
    return fam


def family(cfg_or_name: Config | str) -> Family:
    """The registry entry of a config (its ``family``) or of a family name."""
    name = cfg_or_name if isinstance(cfg_or_name, str) else cfg_or_name.family
    if name not in FAMILIES:
        broken = FAMILIES.broken.get(name)
        if broken:
            raise ValueError(f"family {name!r} is installed but could not be loaded: {broken}")
        raise ValueError(f"family must be one of {sorted(FAMILIES)}, got {name!r}")
    return FAMILIES[name]


register_family(
    Family(
        name="windy",
        description="windy gridworlds: wind strength and direction hidden (paper §3.3.1)",
        experiment="windy-fig2",
        env_kwargs=windy_env_kwargs,
        env_class=WindyGridEnv,
        subtasks=lambda cfg, env: WindySubtasks(env.model, obs_encoding=cfg.env.obs_encoding),
        instance_names=WindyInstances.NAMES,
        validate=_validate_windy,
        grid_side=_windy_side,
        cells=lambda cfg: windy_layout(cfg.env).num_cells,
        observation=lambda cfg: cfg.env.obs_encoding,
        observation_size=lambda cfg: windy_observation_size(
            windy_layout(cfg.env), cfg.env.obs_encoding, cfg.env.patch_radius
        ),
        instance_dim=WINDY_INSTANCE_DIM,
        instance_features=windy_instance_features,
        conv_patch=_windy_patch,
        option_inputs=True,
        oracle=_windy_oracle,
        oracle_summary=_windy_summary,
        averaging_optimum=_windy_averaging_optimum,
        head_report=_windy_head_report,
        tests=WINDY_TESTS,
        instance_fields=_windy_fields,
        make_instances=_windy_make_instances,
        shift_aliases=("p",),
    )
)
register_family(
    Family(
        name="wargus",
        description="Wargus resource gathering: item and patrol hidden (paper §3.5)",
        experiment="wargus-fig4",
        env_kwargs=_wargus_env_kwargs,
        env_class=WargusEnv,
        subtasks=lambda cfg, env: WargusSubtasks(composed_reward=cfg.train.composed_reward),
        instance_names=WargusInstances.NAMES,
        validate=_validate_wargus,
        grid_side=lambda cfg: int(cfg.env.wargus.size),
        cells=lambda cfg: int(cfg.env.wargus.size) ** 2,
        observation=lambda cfg: "wargus",
        informed_features=_wargus_informed,
        option_inputs=True,
        tests=WARGUS_TESTS,
        instance_fields=_wargus_fields,
        make_instances=_wargus_make_instances,
    )
)


__all__ = [
    "BUILTIN",
    "ENTRY_POINT_GROUP",
    "FAMILIES",
    "GENERATED",
    "HELDOUT_SEED",
    "HELDOUT_SEEDS",
    "HELDOUT_SIZE",
    "Family",
    "TestDistribution",
    "family",
    "register_family",
    "windy_env_kwargs",
    "wargus_state_features",
    "windy_sparse_oracle",
    "windy_layout",
]
