"""The windy family's declaration (paper §3.3.1, docs/windy-fig2.md): hidden ``(p, direction)``
instances, "exit by exit k" options, the exact oracle; :func:`family` is the ``windy`` entry point
(docs/families.md).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDictBase

from taskvar_torch import keys
from taskvar_torch.contract import (
    HELDOUT_SEED,
    Experiment,
    Family,
    PatchLayout,
    TestDistribution,
    one_of,
)
from taskvar_torch.families.windy import dynamics as windy
from taskvar_torch.families.windy.config import KEYS as LEGACY_KEYS
from taskvar_torch.families.windy.config import Fig2Config, WindyConfig, section
from taskvar_torch.families.windy.env import OBS_ENCODINGS, WindyGridEnv
from taskvar_torch.families.windy.env import observation_size as windy_observation_size
from taskvar_torch.families.windy.instances import WindyInstances, windy_instances
from taskvar_torch.families.windy.subtasks import WindySubtasks

if TYPE_CHECKING:
    from taskvar_torch.config import Config

WINDY_DIRECTIONS = 4  # north, south, east, west (families/windy/dynamics.py DIRECTIONS)
WINDY_INSTANCE_DIM = 1 + WINDY_DIRECTIONS  # (p, one_hot(direction))


def windy_instance_features(td: TensorDictBase) -> torch.Tensor | None:
    """``(B, F = 5)`` features ``(p, one_hot(direction))`` of each transition's hidden instance, or
    ``None`` without one; read only by the offline ``instance`` max-value estimator (Definition 1).
    """
    if (keys.INSTANCE, "p") not in td.keys(True, True):
        return None
    p = td.get((keys.INSTANCE, "p")).reshape(-1, 1).to(torch.float32)  # (B, 1)
    direction = td.get((keys.INSTANCE, "direction")).reshape(-1).to(torch.int64)  # (B,)
    one_hot = torch.nn.functional.one_hot(direction, WINDY_DIRECTIONS).to(torch.float32)  # (B, 4)
    return torch.cat([p, one_hot], dim=-1)


GENERATED = "generated"
"""``env.windy.layout`` value that builds the grid from ``env.windy.height``/``env.windy.width``/... (make_layout)."""
_GENERATOR_KEYS = ("height", "width", "num_exits", "wall_col", "wind_cells_per_exit")
EXACT_ORACLE_CELLS = 400
"""Windy layouts up to this many cells get the exact oracle in reports (docs/oracle.md)."""
MAX_WINDY_SIDE = 4096
"""Largest height or width of a generated windy grid (``env.windy.layout=generated``)."""
MAX_WINDY_CELLS = (1 << 24) - 1
"""Most cells of a windy layout: start cells are drawn by ``rng.draw_index`` (n < 2^24)."""


def windy_layout(env: WindyConfig) -> windy.WindyLayout:
    """The windy layout ``env.windy`` describes (name, map string or generated); ``ValueError``
    naming the key at fault."""
    if env.layout != GENERATED:
        stray = [k for k in _GENERATOR_KEYS if getattr(env, k) is not None]
        if stray:
            raise ValueError(
                f"env.windy.{stray[0]} is only read when env.windy.layout={GENERATED!r}; "
                f"remove it or set env.windy.layout={GENERATED!r} (env.windy.layout is {env.layout!r})"
            )
        if env.layout in windy.LAYOUTS:
            return windy.WindyLayout.named(env.layout)
        if "\n" not in env.layout.strip():
            raise ValueError(
                f"env.windy.layout must be one of {sorted([*windy.LAYOUTS, GENERATED])} or a multi-line "
                f"map string, got {env.layout!r}"
            )
        try:
            return windy.WindyLayout.from_map(env.layout)
        except ValueError as e:
            raise ValueError(f"env.windy.layout: {e}") from None
    for k in ("height", "width"):
        if getattr(env, k) is None:
            raise ValueError(f"env.windy.{k} is required when env.windy.layout={GENERATED!r}")
    try:
        return windy.make_layout(
            env.height,
            env.width,
            num_exits=2 if env.num_exits is None else env.num_exits,
            wall_col=env.wall_col,
            wind_cells_per_exit=1 if env.wind_cells_per_exit is None else env.wind_cells_per_exit,
        )
    except ValueError as e:
        raise ValueError(f"env.windy (layout={GENERATED!r}): {e}") from None


def windy_env_kwargs(cfg: Config) -> dict[str, Any]:
    """Keyword arguments of ``WindyGridEnv`` for the training environment of ``cfg``."""
    if cfg.family != "windy":
        raise ValueError(f"windy_env_kwargs needs family='windy', got family={cfg.family!r}")
    e = section(cfg)
    return {
        "num_envs": cfg.env.num_envs,
        "layout": windy_layout(e),
        "instances": cfg.env.instances,
        "horizon": e.horizon,
        "obs_encoding": e.obs_encoding,
        "patch_radius": e.patch_radius,
        "seed": cfg.seed,
        "device": cfg.device,
    }


def _validate_windy(cfg: Config) -> None:
    env = section(cfg)
    one_of("env.instances", cfg.env.instances, WindyInstances.NAMES)
    one_of("eval.test", cfg.eval.test, WindyInstances.NAMES)
    if env.horizon is not None and env.horizon < 1:
        raise ValueError(f"env.windy.horizon must be >= 1, got {env.horizon}")
    one_of("env.windy.obs_encoding", env.obs_encoding, OBS_ENCODINGS)
    if env.patch_radius is not None and env.patch_radius < 0:
        raise ValueError(f"env.windy.patch_radius must be >= 0, got {env.patch_radius}")
    if cfg.heads.option_inputs == "subtask" and env.obs_encoding != "exits_patch":
        raise ValueError(
            "heads.option_inputs='subtask' on the windy family needs env.windy.obs_encoding="
            f"'exits_patch' (each exit's offset), got env.windy.obs_encoding={env.obs_encoding!r}"
        )
    if env.layout == GENERATED:  # the grid is built below: bound its size first
        for k in ("height", "width"):
            v = getattr(env, k)
            if v is not None and not 1 <= v <= MAX_WINDY_SIDE:
                raise ValueError(f"env.windy.{k} must be in [1, {MAX_WINDY_SIDE}], got {v}")
    layout = windy_layout(env)  # raises a ValueError naming the layout keys
    if layout.num_cells > MAX_WINDY_CELLS:
        raise ValueError(
            f"env.windy.layout has {layout.num_cells} cells; at most {MAX_WINDY_CELLS} (start cells are "
            "drawn from 24-bit integers)"
        )
    side = max(layout.height, layout.width)
    if env.patch_radius is not None and env.patch_radius > side:
        raise ValueError(
            f"env.windy.patch_radius must be in [0, {side}] (the grid's side: a wider patch only adds "
            f"walls), got {env.patch_radius}"
        )


def _windy_side(cfg: Config) -> int:
    lay = windy_layout(section(cfg))
    return max(lay.height, lay.width)


def _windy_patch(cfg: Config) -> PatchLayout:
    if section(cfg).obs_encoding != "coords_patch":
        raise ValueError(
            "heads.network='conv' needs env.windy.obs_encoding='coords_patch', "
            f"got env.windy.obs_encoding={section(cfg).obs_encoding!r}"
        )
    # coords_patch: (row, col), then 3 (2r+1)^2 channels
    return PatchLayout(coords_dim=2, channels=3, size=2 * section(cfg).patch_radius + 1)


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
    if section(cfg).obs_encoding != "onehot":
        return None
    layout = windy_layout(section(cfg))
    if layout.num_cells > EXACT_ORACLE_CELLS:
        return None
    from taskvar_torch.families.windy.oracle import WindyOracle

    return WindyOracle(
        layout,
        gamma=cfg.train.gamma,
        horizon=section(cfg).horizon,
        train_instances=cfg.env.instances,
    )


def windy_sparse_oracle(cfg: Config) -> Any:
    """The exact oracle of a windy layout at any size (families/windy/sparse_oracle.py)."""
    from taskvar_torch.families.windy.sparse_oracle import SparseWindyOracle

    return SparseWindyOracle(
        windy_layout(section(cfg)),
        gamma=cfg.train.gamma,
        horizon=section(cfg).horizon,
        train_instances=cfg.env.instances,
        device=cfg.device,
    )


def _windy_averaging_optimum(cfg: Config) -> Any:
    """The mean-MDP optimal averaging policy ``(cells,)``: dense on small layouts, successor
    tables beyond (the scale experiment's reference)."""
    oracle = (
        _windy_oracle(cfg) if windy_layout(section(cfg)).num_cells <= EXACT_ORACLE_CELLS else None
    )
    if oracle is None:
        oracle = windy_sparse_oracle(cfg)
    return oracle.averaging_policy()


def _windy_head_report(cfg: Config, heads: Any, with_max_value: bool = True) -> dict[str, Any]:
    """Every head against the exact values at any size (families/windy/head_report.py)."""
    from taskvar_torch.families.windy.head_report import head_report

    return head_report(
        heads,
        windy_sparse_oracle(cfg),
        section(cfg).obs_encoding,
        section(cfg).patch_radius,
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
    horizon = oracle.horizon  # the layout's default where env.windy.horizon is null
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
        overrides=("env.windy.layout=middle_exits",),
    ),
    "whole_column_windy": TestDistribution(
        "another 5x5 layout: wind in the whole column before the wall (training winds)",
        overrides=("env.windy.layout=whole_column_windy",),
    ),
    "heldout": TestDistribution(
        "sealed held-out episodes: the training distribution under the held-out seed",
        seed=HELDOUT_SEED,
    ),
}
"""Windy test distributions (docs/evaluation.md); the layouts need a bundle of the same size."""


_GYM = "taskvar_torch.families.windy.gym_env:WindyGridGymEnv"


def _map(layout: windy.WindyLayout) -> str:
    return "\n".join(layout.rows)


def gym_ids() -> dict[str, tuple[str, dict[str, Any]]]:
    """The windy family's Gymnasium ids (``taskvar/WindyGrid-*``)."""
    return {
        "taskvar/WindyGrid-v0": (_GYM, {"layout": "default"}),
        "taskvar/WindyGrid-MiddleExits-v0": (_GYM, {"layout": "middle_exits"}),
        "taskvar/WindyGrid-WholeColumnWindy-v0": (_GYM, {"layout": "whole_column_windy"}),
        "taskvar/WindyGrid-25x25-v0": (
            _GYM,
            {
                "layout": _map(windy.make_layout(25, 25, num_exits=2)),
                "obs_encoding": "coords_patch",
            },
        ),
        "taskvar/WindyGrid-51x51-4Exits-v0": (
            _GYM,
            {
                "layout": _map(windy.make_layout(51, 51, num_exits=4)),
                "obs_encoding": "coords_patch",
            },
        ),
    }


FIG2 = Experiment(
    "windy-fig2",
    "taskvar_torch.families.windy.fig2",
    run="windy_fig2",
    description="paired rollouts of interruption vs averaging on windy grids (paper Figure 2)",
    config_class=Fig2Config,
)
"""Windy's figure experiment (paper Figure 2, docs/windy-fig2.md)."""


FAILED_BELOW = None
"""No failure rule for windy (``Family.failed_below``, docs/report.md#failed-seeds): its reward is
-1 a step until the goal, so a return counts the steps taken; an episode that never reaches the
goal is truncated at the horizon, which each config sets (``max(100, 4 * (height + width))`` by
default, larger on the large layouts). One number cannot separate "never reaches the goal" from a
long route on every windy layout, so a low return stays a low score: the cell is unchanged."""


def family() -> Family:
    """The windy :class:`Family` (the package's ``taskvar_torch.families`` entry point)."""
    return Family(
        name="windy",
        description="windy gridworlds: wind strength and direction hidden (paper §3.3.1)",
        experiment=FIG2,
        env_kwargs=windy_env_kwargs,
        env_class=WindyGridEnv,
        subtasks=lambda cfg, env: WindySubtasks(env.model, obs_encoding=section(cfg).obs_encoding),
        instance_names=WindyInstances.NAMES,
        validate=_validate_windy,
        config_class=WindyConfig,
        legacy_env_keys=LEGACY_KEYS,  # at env.* until the families became packages
        grid_side=_windy_side,
        cells=lambda cfg: windy_layout(section(cfg)).num_cells,
        observation=lambda cfg: section(cfg).obs_encoding,
        observation_size=lambda cfg: windy_observation_size(
            windy_layout(section(cfg)), section(cfg).obs_encoding, section(cfg).patch_radius
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
        gym_ids=gym_ids(),
        failed_below=FAILED_BELOW,
    )
