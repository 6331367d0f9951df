"""Scaled-up grids (docs/scale.md): training time and final performance of the four
methods against grid size and against the number of parallel environments.

The protocol, top to bottom (:func:`scale`), for each *case* (a family config: windy 5x5, 25x25,
51x51 with 4 exits; Wargus 32x32, 64x64 with 3 patrols) and each ``num_envs`` value (a *cell*):

1. train every head with the real trainer (``train.train``) on the case's config with
   ``env.num_envs = N`` and the same frame budget for every cell (``total_frames``); the
   exploration schedule is scaled to the budget (``init_random_fraction``,
   ``eps_decay_fraction``), ``frames_per_batch`` is rounded to a multiple of N and
   ``updates_per_batch`` scaled with it, so every cell makes the same number of updates per frame
   as its family config; wall-clock training time and frames/s are recorded (one torch thread);
2. evaluate each method -- averaging (paper §3.1), options (§3.2), interruption (Algorithm 1) and
   hierarchy (Algorithm 2; Wargus only: the windy family has no composition hierarchy, "n/a") --
   on ``eval_episodes`` fresh test instances (``instances=test``, test seed ``seed + 1000``): mean
   return with a 95% CI (Wargus: the return is the number of items collected);
3. references on the *same* test episodes (same env seed: same instances, starts; paired): the
   uniformly random policy, and for windy the exact mean-MDP averaging optimum (the oracle's
   ``averaging_policy``, paper §3.1; value iteration on the mean MDP, a few seconds at 51x51),
   rolled out like the methods. ``gap_closed = (R - R_random) / (R_oracle - R_random)``: 0 is
   random, 1 is the best averaging policy (interruption may exceed 1).

Held-out (``heldout_episodes``, default ``eval_episodes``; 0: off): every cell also plays the same
methods on the family's sealed held-out test distribution (``Family.tests["heldout"]``, the
episodes of ``taskvar eval --test heldout``: windy and Taxi the training distribution under env
seed ``HELDOUT_SEED``, Wargus the held-out instance seeds ``HELDOUT_SEEDS``, cycled), paired
across methods, with the random policy and the exact averaging optimum (where the family has one)
on the same held-out episodes; new keys only (:func:`heldout_block`): ``metrics["heldout"]`` (the
distribution, its seed, the references per case) and each cell's ``heldout`` (``methods``, like
the cell's own, and with ``seeds > 1`` ``per_seed`` and ``over_seeds``). It draws no random number
the nominal evaluation uses (:func:`isolated_rng`), so every other value is what it was without it.

Baselines (``baselines``, default none; docs/scale.md#baselines): each cell (each seed's bundle
folder) also trains the listed baselines of docs/memory.md (``recurrent``, ``informed``) with
``train_recurrent.train_baseline`` on the cell's own config and frame budget, as ``taskvar
train-baselines`` does, and plays them on the same test episodes (and held-out ones) as new
``methods`` entries (:func:`baseline_phase`), under :func:`isolated_rng`: the methods' values are
unchanged. A family a listed baseline is unavailable on (``informed`` where the family gives no
features) is refused before any training (:func:`check_case_baselines`).

Writes ``config.yaml`` (this experiment's config), ``cells/<case>-n<N>/`` (the trainer's logs and
config; ``final.pt`` only with ``keep_checkpoints``), ``scale.csv`` (one row per cell and method),
``metrics.json``, ``scale.png``; prints a table. ``taskvar plot OUT`` redraws ``scale.png``.

Seeds (``seeds = k > 1``): each cell is trained *once* with ``train.seeds = k`` (the batched
trainer, docs/seeds.md: training seeds ``seed .. seed + k - 1``, bundles in
``cells/<case>-n<N>/seed<i>/``) and every seed's bundle is evaluated on the same test episodes.
A cell's existing keys (``methods``, ``curve``, ``heads``) are then seed ``seed``'s run (the
learning curve and the exact head report of seed 0 only: per seed they would cost k times the
evaluation); new keys hold the rest: ``seeds``, ``per_seed`` (every seed's methods) and
``over_seeds`` (each method's mean return over the seeds with rliable's stratified-bootstrap 95%
CI, :func:`over_seeds`); ``scale.csv`` gets a ``seed`` column and one row per seed; the printed
table adds each cell's aggregate, and ``scale.png``'s final-return panels draw it.

This module is the config, the protocol and the references; the report (``scale.csv``'s rows,
the table, ``scale.png``) is :mod:`taskvar_torch.experiments.scale_report`, whose public names are
re-exported here.

Examples:
    >>> cfg = load_scale_config(default_config_path(), quick=True)  # doctest: +SKIP
    >>> metrics = scale(cfg, "results/scale-quick")  # doctest: +SKIP
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import random
import resource
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.modules import RandomPolicy

from taskvar_torch import keys, rng
from taskvar_torch.checkpoint import load_checkpoint
from taskvar_torch.config import (
    METHODS,
    Config,
    apply_overrides,
    config_to_dict,
    load_config,
    load_strict,
    save_config_yaml,
)
from taskvar_torch.experiments.evaluation import mean_ci95, run_episodes
from taskvar_torch.experiments.results import write_csv, write_json
from taskvar_torch.experiments.scale_report import (
    COLOURS,
    CSV_FIELDS,
    CSV_NAME,
    CURVES_FIGURE,
    EXPERIMENT,
    FAMILY_STYLE,
    FIGURE,
    METRICS_NAME,
    SEED_FIELD,
    csv_fields,
    csv_rows,
    final_return,
    format_heads,
    format_heldout,
    format_seeds,
    format_table,
    is_results_folder,
    plot_curves,
    plot_results,
    report_methods,
)
from taskvar_torch.experiments.shift import shift_points
from taskvar_torch.factory import load_heads, make_env, make_method_controller, make_subtasks
from taskvar_torch.families import family
from taskvar_torch.heads.informed import informed_features
from taskvar_torch.heads.recurrent import (
    BASELINES,
    BaselineController,
    baseline_path,
    load_baseline,
)
from taskvar_torch.progress import progress_bar
from taskvar_torch.run_folder import ResultsFolder
from taskvar_torch.train_recurrent import train_baseline
from taskvar_torch.training import HEADS_SNAPSHOTS, seed_config, train

TEST_SEED_OFFSET = 1000
"""Test episodes use env seed ``seed + TEST_SEED_OFFSET`` (never a training seed)."""
HELDOUT_TEST = "heldout"
"""The family test distribution (``Family.tests``) the held-out block plays: the sealed instances
(``families.HELDOUT_SEED``, docs/claims.md)."""
SEED_CI_REPS = 2000
"""Bootstrap replications of :func:`over_seeds`' 95% CIs (rliable's default; ~0.5-2 s a method)."""


# --------------------------------------------------------------------------------------------
# config (mirrored by configs/scale.yaml, loaded strictly by taskvar_torch.config.load_strict)


@dataclass(frozen=True)
class ScaleCase:
    """One scaled family: a label, a family config and overrides applied to it."""

    name: str = ""
    """Label of the case in the table and plots (e.g. windy-25x25); unique."""
    config: str = ""
    """Family YAML (configs/*.yaml); a relative path is read beside the scale config."""
    overrides: tuple[str, ...] = ()
    """key.sub=value overrides of the family config for this case."""
    total_frames: int | None = None
    """Training frames of this case's cells; null: the experiment's ``total_frames``."""


@dataclass(frozen=True)
class ScaleConfig:
    """The scaled-up grids experiment: which cases, num_envs values, budgets."""

    override_example: ClassVar[str] = "total_frames=20000"
    """An override shown in the error for a malformed one (a class constant, not a config key)."""
    seed: int = 0
    """Seed of every cell's training (cfg.seed); test episodes use seed + 1000."""
    seeds: int = 1
    """Training seeds per cell: ``seed .. seed + seeds - 1``, trained at once by the batched
    trainer (``train.seeds``, docs/seeds.md), each evaluated on the same test episodes; > 1 adds
    per-seed results and their aggregate over seeds to every cell (``per_seed``, ``over_seeds``)."""
    total_frames: int = 100_000
    """Training frames per cell (the same budget for every case and num_envs)."""
    init_random_fraction: float = 0.1
    """train.init_random_frames = this x total_frames."""
    eps_decay_fraction: float = 0.5
    """train.eps_decay_frames = this x total_frames."""
    updates_per_frame: float | None = None
    """Gradient updates per training frame in every cell (train.updates_per_batch =
    round(this x frames_per_batch)); null keeps each family config's own ratio."""
    num_envs: tuple[int, ...] = (16, 64, 256)
    """Parallel training environments (env.num_envs) of each cell."""
    eval_episodes: int = 500
    """Test episodes per method, per cell (fresh test instances)."""
    eval_batch_size: int = 500
    """Test environments run in parallel."""
    heldout_episodes: int | None = None
    """Held-out test episodes per method, per cell: the family's sealed held-out distribution
    (``taskvar eval --test heldout``), beside the nominal test; null: ``eval_episodes``; 0: off."""
    baselines: tuple[str, ...] = ()
    """Baselines (``heads.recurrent.BASELINES``: recurrent, informed; docs/memory.md) each cell
    (and seed) also trains on its own config and frame budget and scores on the same test
    episodes, as new ``methods`` entries (:func:`baseline_phase`); empty: none."""
    cases: list[ScaleCase] = field(default_factory=list)
    """The scaled families, smallest grid first within a family."""
    only: tuple[str, ...] = ()
    """Names of the cases to run; empty: all."""
    overrides: tuple[str, ...] = ()
    """key.sub=value overrides applied to every case's family config (before the case's own)."""
    keep_checkpoints: bool = False
    """Keep each cell's cells/<case>-n<N>/final.pt (with its replay buffer: large)."""
    curve_points: int = 10
    """Learning curves: the heads are saved this many times per cell (train.heads_every) and every
    method is evaluated on each snapshot; 0: no curves."""
    curve_episodes: int = 100
    """Test episodes per method per learning-curve point (the first of the final evaluation's)."""
    head_report: bool = True
    """Windy cells: every learnt head against its exact optimum (families/windy/head_report.py)."""
    head_report_max_value: bool = True
    """With head_report: compare the learnt interruption condition too (the slowest exact solve)."""
    quick_overrides: tuple[str, ...] = ()
    """Overrides of this config applied by --quick."""

    def __post_init__(self):
        if self.total_frames < 1:
            raise ValueError(f"total_frames must be >= 1, got {self.total_frames}")
        if isinstance(self.seeds, bool) or not isinstance(self.seeds, int) or self.seeds < 1:
            raise ValueError(f"seeds must be an integer >= 1, got {self.seeds!r}")
        top = rng.MAX_SEED - TEST_SEED_OFFSET - self.seeds  # the test episodes' seed + 1000
        if (
            isinstance(self.seed, bool)
            or not isinstance(self.seed, int)
            or not 0 <= self.seed <= top
        ):
            raise ValueError(f"seed must be an integer in [0, {top}], got {self.seed!r}")
        for name in ("init_random_fraction", "eps_decay_fraction"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {v}")
        if self.updates_per_frame is not None and not 0 < self.updates_per_frame <= 64:
            raise ValueError(
                f"updates_per_frame must be in (0, 64] or null, got {self.updates_per_frame}"
            )
        if not self.num_envs or min(self.num_envs) < 1:
            raise ValueError(
                f"num_envs must be a non-empty list of ints >= 1, got {list(self.num_envs)}"
            )
        if self.curve_points < 0:
            raise ValueError(f"curve_points must be >= 0, got {self.curve_points}")
        for name in ("eval_episodes", "eval_batch_size", "curve_episodes"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        h = self.heldout_episodes
        if h is not None and (isinstance(h, bool) or not isinstance(h, int) or h < 0):
            raise ValueError(
                f"heldout_episodes must be an integer >= 0 (0: off) or null, got {h!r}"
            )
        bad = [b for b in self.baselines if b not in BASELINES]
        if bad or len(set(self.baselines)) != len(self.baselines):
            raise ValueError(
                f"baselines must be distinct names among {list(BASELINES)}, got "
                f"{list(self.baselines)}"
            )
        if not self.cases:
            raise ValueError("cases must list at least one {name, config} case")
        names = [c.name for c in self.cases]
        for i, c in enumerate(self.cases):
            if not c.name or not c.config:
                raise ValueError(f"cases[{i}] needs a name and a config, got {c}")
            if c.total_frames is not None and c.total_frames < 1:
                raise ValueError(
                    f"cases[{i}].total_frames must be >= 1 or null, got {c.total_frames}"
                )
        if len(set(names)) != len(names):
            raise ValueError(f"case names must be unique, got {names}")
        unknown = [n for n in self.only if n not in names]
        if unknown:
            raise ValueError(f"only must name cases among {names}, got {unknown}")

    def selected(self) -> tuple[ScaleCase, ...]:
        """The cases to run (``only``, or all)."""
        return tuple(c for c in self.cases if not self.only or c.name in self.only)

    def heldout_count(self) -> int:
        """Held-out episodes per method and cell (``heldout_episodes``; null: ``eval_episodes``;
        0: no held-out block)."""
        return self.eval_episodes if self.heldout_episodes is None else self.heldout_episodes


def default_config_path() -> Path:
    """``configs/scale.yaml`` of the repository (or of the working directory)."""
    here = Path(__file__).resolve().parents[2] / "configs" / "scale.yaml"
    return here if here.is_file() else Path("configs") / "scale.yaml"


def load_scale_config(
    path: str | os.PathLike, overrides: Sequence[str] = (), quick: bool = False
) -> ScaleConfig:
    """Load ``configs/scale.yaml`` strictly (unknown keys and bad types are one-line errors), apply
    ``quick_overrides`` with ``quick``, then ``key=value`` overrides; case config paths are resolved
    beside the YAML file, and every case's family config is loaded (strictly) to fail early.

    Loading is :func:`taskvar_torch.config.load_strict`, the training configs' loader; the quick
    overrides are read (and checked) only with ``quick``.
    """
    path = Path(path)
    cfg = load_strict(
        ScaleConfig,
        path,
        overrides,
        quick=quick,
        quick_overrides=lambda c: c.quick_overrides,
        check_quick=False,
    )
    cases = []
    for c in cfg.cases:
        p = Path(c.config)
        if not p.is_absolute():
            p = path.parent / p
        cases.append(dataclasses.replace(c, config=str(p)))
    cfg = dataclasses.replace(cfg, cases=cases)
    for c in cfg.selected():  # a typo in a case fails now, not after an hour
        check_case_baselines(cfg, c, case_config(cfg, c, cfg.num_envs[0]))
    return cfg


def supported_baselines(ccfg: Config) -> tuple[str, ...]:
    """The baselines ``ccfg``'s family can train (docs/memory.md): ``recurrent`` on every family,
    ``informed`` only where the family gives features of the hidden instance
    (``heads.informed.informed_features``; every built-in family does)."""
    out = []
    for b in BASELINES:
        if b == "informed":
            try:
                informed_features(ccfg)
            except ValueError:
                continue
        out.append(b)
    return tuple(out)


def check_case_baselines(cfg: ScaleConfig, case: ScaleCase, ccfg: Config) -> None:
    """A one-line ``ValueError`` where ``cfg.baselines`` names a baseline ``case``'s family cannot
    train (:func:`supported_baselines`), raised before any cell trains."""
    ok = supported_baselines(ccfg)
    missing = [b for b in cfg.baselines if b not in ok]
    if missing:
        raise ValueError(
            f"baselines: family {ccfg.family!r} (case {case.name}) supports only {list(ok)} of "
            f"the baselines, not {missing}; drop it from baselines or the case from only"
        )


def scale_config_to_dict(cfg: ScaleConfig) -> dict[str, Any]:
    """Plain nested data of ``cfg`` (tuples as lists)."""
    return config_to_dict(cfg)


def case_config(cfg: ScaleConfig, case: ScaleCase, num_envs: int) -> Config:
    """The family config of one cell: the case's YAML, the budget, ``num_envs`` and the overrides.

    ``frames_per_batch`` becomes a multiple of ``num_envs`` (at least one step of every env) and
    ``updates_per_batch`` is scaled with it, keeping the config's updates per frame (or
    ``cfg.updates_per_frame`` when set).
    """
    base = load_config(case.config, [*cfg.overrides, *case.overrides])
    t = base.train
    n = int(num_envs)
    total = case_frames(cfg, case)
    fpb = max(n, round(t.frames_per_batch / n) * n)
    fpb = min(fpb, max(n, (total // n) * n))  # at least two batches when the budget allows
    ratio = (
        t.updates_per_batch / t.frames_per_batch
        if cfg.updates_per_frame is None
        else cfg.updates_per_frame
    )
    upb = max(1, round(ratio * fpb)) if ratio > 0 else 0
    return apply_overrides(
        base,
        [
            f"seed={cfg.seed}",
            f"train.seeds={cfg.seeds}",
            f"env.num_envs={n}",
            f"train.total_frames={total}",
            f"train.init_random_frames={int(cfg.init_random_fraction * total)}",
            f"train.eps_decay_frames={int(cfg.eps_decay_fraction * total)}",
            f"train.frames_per_batch={fpb}",
            f"train.updates_per_batch={upb}",
            f"train.buffer_size={max(min(t.buffer_size, total), t.batch_size)}",
            "train.checkpoint_every=0",
            f"train.log_every={max(total // 10, 1)}",
            f"train.heads_every={total // cfg.curve_points if cfg.curve_points else 0}",
        ]
        + [o for o in case.overrides if o.split("=", 1)[0] in SCHEDULE_KEYS],
    )


SCHEDULE_KEYS = ("train.init_random_frames", "train.eps_decay_frames", "train.updates_per_batch")
"""Keys a case's own overrides may set instead of the experiment's budget-derived values."""


def case_frames(cfg: ScaleConfig, case: ScaleCase) -> int:
    """The training budget of a case's cells (its own ``total_frames``, else the experiment's)."""
    return case.total_frames if case.total_frames is not None else cfg.total_frames


# --------------------------------------------------------------------------------------------
# evaluation on fresh test instances


def _family_figure(cfg: Config, name: str) -> Any:
    """A family's table figure (``grid_side``, ``cells``, ``observation``), ``None`` if it has
    none."""
    f = getattr(family(cfg), name)
    return None if f is None else f(cfg)


def grid_side(cfg: Config) -> int:
    """The grid's side length (windy: max of height and width; Wargus: ``size``)."""
    return _family_figure(cfg, "grid_side")


def make_test_env(
    cfg: Config, num_envs: int, seed: int, index_offset: int = 0, instances: Any = "test"
) -> EnvBase:
    """The family env on fresh test instances (or ``instances``: the held-out ones,
    :class:`HeldoutTest`); the same ``seed`` gives the same episodes."""
    return make_env(
        cfg,
        num_envs,
        seed=seed,
        index_offset=index_offset,
        instances=instances,
        validate_actions=False,
    )


@dataclass(frozen=True)
class HeldoutTest:
    """The family's sealed held-out test distribution (``Family.tests["heldout"]``) for a cell's
    config: the env config, the instances and the sealed env seed its episodes play
    (docs/scale.md#held-out-instances)."""

    cfg: Config
    instances: Any
    seed: int
    description: str


def heldout_test(cfg: Config) -> HeldoutTest | None:
    """The held-out test of ``cfg``'s family, as ``taskvar eval --test heldout`` plays it (its
    overrides and instances, :func:`taskvar_torch.experiments.shift.shift_points`; its sealed
    seed); ``None`` where the family declares no sealed ``heldout`` distribution."""
    dist = family(cfg).tests.get(HELDOUT_TEST)
    if dist is None or dist.seed is None:
        return None
    (point,) = shift_points(cfg, HELDOUT_TEST)
    return HeldoutTest(point.cfg, point.instances, int(dist.seed), dist.description)


@contextlib.contextmanager
def isolated_rng(device: str | torch.device) -> Iterator[None]:
    """Run a block without touching the global random streams the nominal protocol draws from:
    torch's (CPU and the device's), NumPy's and Python's states are restored on exit."""
    dev = torch.device(device)
    devices = []
    if dev.type == "cuda":
        devices = [dev.index if dev.index is not None else torch.cuda.current_device()]
    np_state, py_state = np.random.get_state(), random.getstate()
    try:
        with torch.random.fork_rng(devices=devices):
            yield
    finally:
        np.random.set_state(np_state)
        random.setstate(py_state)


class TablePolicy(nn.Module):
    """``action = table[cell]``: a tabular deterministic policy (the oracle's averaging optimum)."""

    def __init__(self, table: torch.Tensor):
        super().__init__()
        self.register_buffer("table", table.to(torch.int64))

    def forward(self, cell: torch.Tensor) -> torch.Tensor:
        return self.table[cell]


def make_policy(name: str, cfg: Config, heads: Any = None, subtasks: Any = None, env: Any = None):
    """A TorchRL policy: a method's controller on ``heads``, ``random`` or ``oracle_averaging``;
    for a baseline (``recurrent``, ``informed``) ``heads`` is its trained
    :class:`~taskvar_torch.heads.recurrent.BaselineController`, played as it is."""

    if name in BASELINES:
        if not isinstance(heads, BaselineController):
            raise ValueError(f"the {name} baseline plays its trained controller, got {heads!r}")
        return heads
    if name == "random":
        return RandomPolicy(env.action_spec)
    if name == "oracle_averaging":  # the family's exact mean-MDP averaging policy over cell
        table = family(cfg).needs("averaging_optimum", "the oracle_averaging reference")(cfg)
        return TensorDictModule(TablePolicy(table.to(cfg.device)), [keys.CELL], [keys.ACTION])
    return make_method_controller(cfg, name, heads, subtasks)


def evaluate(
    cfg: Config,
    policy_name: str,
    episodes: int,
    batch_size: int,
    heads: Any = None,
    test: HeldoutTest | None = None,
) -> dict[str, float] | None:
    """Mean return (95% CI), length and interruptions of ``policy_name`` over ``episodes`` test
    episodes (global indices ``0..episodes-1`` at the test seed: the same for every policy).

    ``test``: play the held-out test's episodes instead (:func:`heldout_test`: its config,
    instances and sealed seed; docs/scale.md#held-out-instances).
    ``None`` where the method does not apply (hierarchy without a composition hierarchy)."""

    instances: Any = "test"
    if test is None:
        seed = cfg.seed + TEST_SEED_OFFSET
    else:
        cfg, instances, seed = test.cfg, test.instances, test.seed
    probe = make_test_env(cfg, 1, seed, instances=instances)
    subtasks = make_subtasks(cfg, probe)
    if policy_name == "hierarchy" and subtasks.hierarchy is None:
        return None
    torch.manual_seed(seed)  # the random policy's action stream
    policy = make_policy(policy_name, cfg, heads, subtasks, probe)
    returns, lengths, inter = [], [], []
    for lo in range(0, int(episodes), int(batch_size)):
        n = min(int(batch_size), int(episodes) - lo)
        env = make_test_env(cfg, n, seed, lo, instances)
        if hasattr(policy, "primer"):
            env = TransformedEnv(env, policy.primer())
        if policy_name == "random":
            policy = RandomPolicy(env.action_spec)
        out = run_episodes(env, policy)
        returns.append(out["return"].double().cpu())
        lengths.append(out["length"].double().cpu())
        inter.append(out["interruptions"].double().cpu())
    r = torch.cat(returns)
    mean, ci = mean_ci95(r)
    result = {
        "mean_return": mean,
        "ci95": ci,
        "mean_length": float(torch.cat(lengths).mean()),
        "episodes": int(r.numel()),
    }
    if policy_name in ("options", "interruption", "hierarchy"):
        result["interruptions_per_episode"] = float(torch.cat(inter).mean())
    return result


def references(
    cfg: Config, episodes: int, batch_size: int, test: HeldoutTest | None = None
) -> dict[str, Any]:
    """The random policy and, where the family brings one (``Family.averaging_optimum``), the
    exact mean-MDP averaging optimum on the same test episodes (``test``: the held-out ones)."""
    t0 = time.perf_counter()
    refs: dict[str, Any] = {"random": evaluate(cfg, "random", episodes, batch_size, test=test)}
    if family(cfg).averaging_optimum is not None:
        refs["oracle_averaging"] = evaluate(
            cfg, "oracle_averaging", episodes, batch_size, test=test
        )
        refs["oracle_note"] = (
            "mean-MDP optimal averaging policy (exact value iteration, paper "
            "§3.1), rolled out on the same test episodes"
        )
    else:
        refs["oracle_averaging"] = None
        refs["oracle_note"] = f"no exact oracle for the {cfg.family} family"
    refs["seconds"] = time.perf_counter() - t0
    return refs


def gap_closed(ret: float, random_ret: float, oracle_ret: float | None) -> float | None:
    """``(ret - random) / (oracle - random)``; ``None`` without an oracle or a gap."""
    if oracle_ret is None or abs(oracle_ret - random_ret) < 1e-9:
        return None
    return (ret - random_ret) / (oracle_ret - random_ret)


# --------------------------------------------------------------------------------------------
# the experiment


def run_cell(
    cfg: ScaleConfig,
    case: ScaleCase,
    num_envs: int,
    out: Path,
    refs: dict[str, Any],
    overwrite: bool = False,
    heldout_refs: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Train one (case, num_envs) cell with the real trainer, time it, evaluate every method.

    With ``cfg.seeds > 1`` the cell's ``train.seeds`` runs train at once and each seed's bundle is
    evaluated on the same test episodes (``per_seed``, ``over_seeds``); ``methods``, the learning
    curve and the head report are seed ``cfg.seed``'s (the first of the batch). ``heldout_refs``
    (the case's held-out references, :func:`heldout_references`): every seed's methods on the
    held-out episodes too, after everything else, under the new key ``heldout``
    (:func:`heldout_block`). ``cfg.baselines``: each seed's bundle folder also trains and scores
    them (:func:`baseline_phase`), after the methods' evaluation and before the held-out block."""

    ccfg = case_config(cfg, case, num_envs)
    ecfg = seed_config(ccfg, 0)  # seed `seed` as one run: the test episodes of every seed
    cell_dir = out / "cells" / f"{case.name}-n{num_envs}"
    # final.pt is deleted after evaluation unless kept: then it needs no replay buffer (~1.3 GB)
    result = train(
        ccfg, cell_dir, progress=False, overwrite=overwrite, keep_replay=cfg.keep_checkpoints
    )
    finals = [Path(p) for p in result.get("seeds", [result["final"]])]
    seed_heads = [load_heads(p, device=ccfg.device)[0] for p in finals]
    if not cfg.keep_checkpoints:
        for p in {Path(result["final"]), *finals}:
            p.unlink(missing_ok=True)
    t0 = time.perf_counter()
    rand = refs["random"]["mean_return"]
    orc = refs["oracle_averaging"]["mean_return"] if refs["oracle_averaging"] else None
    per_seed = []
    for heads in seed_heads:
        methods = {
            m: evaluate(ecfg, m, cfg.eval_episodes, cfg.eval_batch_size, heads) for m in METHODS
        }
        for r in methods.values():
            if r is not None:
                r["gap_closed"] = gap_closed(r["mean_return"], rand, orc)
        per_seed.append(methods)
    methods, heads = per_seed[0], seed_heads[0]
    curve = learning_curve(cfg, ecfg, finals[0].parent, rand, orc)
    for other in finals[1:]:  # seed 0's curve only (each point evaluates every method)
        if not cfg.keep_checkpoints:
            for path in (other.parent / HEADS_SNAPSHOTS).glob("heads_*.pt"):
                path.unlink(missing_ok=True)
    curve.append(
        {
            "frames": int(result["frames"]),
            "updates": int(result["updates"]),
            "seconds": float(result["seconds"]),
            "methods": {m: _curve_point(r) for m, r in methods.items()},
        }
    )
    report = None
    if cfg.head_report and family(ccfg).head_report is not None:
        report = family(ccfg).head_report(ecfg, heads, with_max_value=cfg.head_report_max_value)
    secs = float(result["seconds"])
    cell = {
        **peak_memory(ccfg.device),
        "case": case.name,
        "family": ccfg.family,
        "grid_side": grid_side(ccfg),
        "cells": _family_figure(ccfg, "cells"),
        "num_envs": int(num_envs),
        "frames": int(result["frames"]),
        "updates": int(result["updates"]),
        "frames_per_batch": ccfg.train.frames_per_batch,
        "updates_per_batch": ccfg.train.updates_per_batch,
        "hidden": list(ccfg.heads.hidden),
        "obs_encoding": _family_figure(ccfg, "observation"),
        "train_seconds": secs,
        "frames_per_second": result["frames"] / secs if secs > 0 else None,
        "eval_seconds": time.perf_counter() - t0,
        "methods": methods,
        "curve": curve,
        "heads": report,
    }
    if cfg.seeds > 1:  # new keys only: with one seed the cell is what it always was
        seeds = [ccfg.seed + k for k in range(cfg.seeds)]
        cell["seeds"] = seeds
        cell["frames_per_second_all_seeds"] = (
            result["frames"] * cfg.seeds / secs if secs > 0 else None
        )
        cell["per_seed"] = [{"seed": s, "methods": m} for s, m in zip(seeds, per_seed)]
        cell["over_seeds"] = over_seeds(per_seed, rand, orc)
    seed_baselines: list[dict[str, BaselineController]] = []
    if cfg.baselines:  # new keys only, after the methods' own (docs/scale.md#baselines)
        folders = [p.parent for p in finals]
        seed_baselines = baseline_phase(cfg, ccfg, ecfg, folders, cell, per_seed, rand, orc)
    if heldout_refs is not None and cfg.heldout_count() > 0:  # new key only, after the rest
        cell["heldout"] = heldout_block(cfg, ecfg, seed_heads, heldout_refs, seed_baselines)
    return cell


def _heads_informed(folder: Path) -> dict[str, Any]:
    """The informed head the cell's heads trained (``folder/informed.pt``), in
    ``train_baseline``'s result layout (its training is the heads')."""
    path = baseline_path(folder / "final.pt", "informed")
    counters = load_checkpoint(path).get("counters", {})
    return {
        "path": str(path),
        "frames": int(counters.get("frames", 0)),
        "updates": int(counters.get("updates", 0)),
        "seconds": 0.0,  # its time is the heads' (train_seconds of the cell)
        "mean_train_return": float("nan"),
        "with_heads": True,
    }


def baseline_phase(
    cfg: ScaleConfig,
    ccfg: Config,
    ecfg: Config,
    folders: Sequence[Path],
    cell: dict[str, Any],
    per_seed: Sequence[dict[str, Any]],
    random_ret: float,
    oracle_ret: float | None,
) -> list[dict[str, BaselineController]]:
    """Train and score a cell's baselines (``cfg.baselines``; docs/scale.md#baselines,
    docs/memory.md); returns each seed's greedy controllers by name.

    Training: for seed ``k`` of the cell, ``train_recurrent.train_baseline`` on
    ``seed_config(ccfg, k)`` into that seed's bundle folder (``folders[k]``, beside the heads'
    ``final.pt``), exactly as ``taskvar train-baselines CONFIG --out FOLDER --method NAME`` does:
    the cell's own config, so the **same frame budget** and settings as the heads
    (``train_recurrent``'s module docstring); ``informed`` where the heads trained it
    (``heads.informed``) is their ``informed.pt``, not trained again. The bundles (``recurrent.pt``, ``informed.pt``) are removed
    once loaded unless ``keep_checkpoints``.

    Scoring: each baseline on the cell's test episodes (``evaluate`` at the test seed: the
    methods' paired episodes), with ``gap_closed``, added to every seed's ``methods`` as a new
    entry (so to ``cell["methods"]`` and ``per_seed``) and, with several seeds, to
    ``over_seeds``. New keys: ``baseline_training`` (per seed and baseline: frames, updates,
    seconds, the mean training return of the last tenth, ``with_heads``: trained as one more head,
    its seconds counted in the heads'), ``baseline_train_seconds`` (their
    total) and ``baseline_eval_seconds``. Every call runs under :func:`isolated_rng`, so the
    methods' numbers are bit for bit those of a run without baselines."""
    controllers: list[dict[str, BaselineController]] = []
    training = []
    for k, folder in enumerate(folders):
        scfg = seed_config(ccfg, k)
        ctrls = {}
        for b in cfg.baselines:
            with isolated_rng(ccfg.device):  # loading draws too: the network's initial weights
                if b == "informed" and ccfg.heads.informed:  # trained with the heads
                    r = _heads_informed(folder)
                else:
                    r = train_baseline(scfg, b, folder)
                ctrls[b], _ = load_baseline(r["path"], device=ccfg.device)
            if not cfg.keep_checkpoints:
                Path(r["path"]).unlink(missing_ok=True)
            last = r["mean_train_return"]
            training.append(
                {
                    "seed": scfg.seed,
                    "method": b,
                    "frames": int(r["frames"]),
                    "updates": int(r["updates"]),
                    "train_seconds": float(r["seconds"]),
                    "mean_train_return": None if last != last else float(last),  # NaN: none ended
                    "with_heads": bool(r.get("with_heads", False)),
                }
            )
        controllers.append(ctrls)
    t0 = time.perf_counter()
    with isolated_rng(ecfg.device):
        for methods, ctrls in zip(per_seed, controllers):
            for b, ctrl in ctrls.items():
                r = evaluate(ecfg, b, cfg.eval_episodes, cfg.eval_batch_size, ctrl)
                r["gap_closed"] = gap_closed(r["mean_return"], random_ret, oracle_ret)
                methods[b] = r
        if cfg.seeds > 1:
            cell["over_seeds"].update(over_seeds(per_seed, random_ret, oracle_ret, cfg.baselines))
    cell["baseline_training"] = training
    cell["baseline_train_seconds"] = sum(t["train_seconds"] for t in training)
    cell["baseline_eval_seconds"] = time.perf_counter() - t0
    return controllers


def heldout_references(cfg: ScaleConfig, ccfg: Config) -> dict[str, Any] | None:
    """A case's held-out references (:func:`references` on the held-out episodes of
    :func:`heldout_test`, ``cfg.heldout_count()`` of them) with the distribution's ``test``,
    ``seed`` and ``description``; ``None`` where the family has no held-out test. Drawn under
    :func:`isolated_rng`: the nominal protocol's random streams are left as they were."""
    test = heldout_test(ccfg)
    if test is None:
        return None
    n = cfg.heldout_count()
    with isolated_rng(ccfg.device):
        refs = references(test.cfg, n, min(n, cfg.eval_batch_size), test)
    return {
        "test": HELDOUT_TEST,
        "description": test.description,
        "seed": test.seed,
        "episodes": n,
        **refs,
    }


def heldout_block(
    cfg: ScaleConfig,
    ecfg: Config,
    seed_heads: Sequence[Any],
    refs: dict[str, Any],
    seed_baselines: Sequence[dict[str, BaselineController]] = (),
) -> dict[str, Any]:
    """A cell's ``heldout``: every method on the held-out episodes (the same episodes for every
    method and seed: paired), shaped like the cell's own keys -- ``methods`` (seed ``seed``'s,
    with ``gap_closed`` against the held-out references ``refs``) and, with several seeds,
    ``per_seed`` and ``over_seeds``; ``seconds`` its evaluation time. Run under
    :func:`isolated_rng` (docs/scale.md#held-out-instances). ``seed_baselines`` (each seed's
    baseline controllers, :func:`baseline_phase`): played on the same episodes after the methods,
    new entries of the same blocks."""
    t0 = time.perf_counter()
    test = heldout_test(ecfg)
    n = cfg.heldout_count()
    rand = refs["random"]["mean_return"]
    orc = refs["oracle_averaging"]["mean_return"] if refs["oracle_averaging"] else None
    per_seed = []
    with isolated_rng(ecfg.device):
        for heads in seed_heads:
            methods = {
                m: evaluate(ecfg, m, n, min(n, cfg.eval_batch_size), heads, test) for m in METHODS
            }
            for r in methods.values():
                if r is not None:
                    r["gap_closed"] = gap_closed(r["mean_return"], rand, orc)
            per_seed.append(methods)
        block: dict[str, Any] = {"methods": per_seed[0]}
        if cfg.seeds > 1:
            seeds = [ecfg.seed + k for k in range(cfg.seeds)]
            block["per_seed"] = [{"seed": s, "methods": m} for s, m in zip(seeds, per_seed)]
            block["over_seeds"] = over_seeds(per_seed, rand, orc)
        for methods, ctrls in zip(per_seed, seed_baselines):  # after the methods': new entries
            for b, ctrl in ctrls.items():
                r = evaluate(ecfg, b, n, min(n, cfg.eval_batch_size), ctrl, test)
                r["gap_closed"] = gap_closed(r["mean_return"], rand, orc)
                methods[b] = r
        if cfg.seeds > 1 and seed_baselines:
            block["over_seeds"].update(over_seeds(per_seed, rand, orc, list(seed_baselines[0])))
    block["seconds"] = time.perf_counter() - t0
    return block


def over_seeds(
    per_seed: Sequence[dict[str, Any]],
    random_ret: float,
    oracle_ret: float | None,
    methods: Sequence[str] = METHODS,
) -> dict[str, dict[str, Any] | None]:
    """Each method's mean test return per seed (``per_seed[i][method]["mean_return"]``, same
    episodes for every seed), aggregated over the seeds with rliable
    (:func:`taskvar_torch.experiments.aggregate.interval_estimates`: one task, the seeds as runs):
    ``mean_return`` with ``mean_ci95`` = [lo, hi] (stratified bootstrap, percentile), the IQM with
    its CI, the per-seed means (``returns``) and the gap closed by the mean and by the CI's ends;
    ``None`` where the method does not apply. ``methods``: which entries (default the paper's; a
    cell's baselines are aggregated in a call of their own, :func:`baseline_phase`)."""
    from taskvar_torch.experiments.aggregate import interval_estimates

    scores = {
        m: [[s[m]["mean_return"]] for s in per_seed]
        for m in methods
        if all(s.get(m) is not None for s in per_seed)
    }
    est = interval_estimates(scores, reps=SEED_CI_REPS) if scores else {}
    out: dict[str, dict[str, Any] | None] = {}
    for m in methods:
        if m not in est:
            out[m] = None
            continue
        e = est[m]
        gaps = [gap_closed(x, random_ret, oracle_ret) for x in e["mean_ci95"]]
        out[m] = {
            "seeds": e["runs"],
            "returns": [row[0] for row in scores[m]],
            "mean_return": e["mean"],
            "mean_ci95": e["mean_ci95"],
            "iqm_return": e["iqm"],
            "iqm_ci95": e["iqm_ci95"],
            "gap_closed": gap_closed(e["mean"], random_ret, oracle_ret),
            "gap_closed_ci95": None if gaps[0] is None else sorted(gaps),
        }
    return out


def peak_memory(device: str | torch.device) -> dict[str, float | None]:
    """``peak_rss_mb``: this process's peak resident memory so far (a high-water mark: with
    several cells in one process, the largest cell run so far; Linux and macOS), and on CUDA
    ``peak_cuda_mb``, the peak of tensors allocated on the device so far (else ``None``)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux, bytes on macOS
    rss_mb = rss / 2**20 if sys.platform == "darwin" else rss / 2**10
    dev = torch.device(device)
    cuda = torch.cuda.max_memory_allocated(dev) / 2**20 if dev.type == "cuda" else None
    return {"peak_rss_mb": float(rss_mb), "peak_cuda_mb": cuda}


def _curve_point(r: dict[str, Any] | None) -> dict[str, Any] | None:
    return None if r is None else {k: r.get(k) for k in ("mean_return", "ci95", "gap_closed")}


def learning_curve(
    cfg: ScaleConfig, ccfg: Config, cell_dir: Path, random_ret: float, oracle_ret: float | None
) -> list[dict[str, Any]]:
    """Every method on each heads snapshot of a cell (``train.heads_every``), on the first
    ``curve_episodes`` test episodes; the snapshots are removed once read."""
    points = []
    snapshots = sorted((cell_dir / HEADS_SNAPSHOTS).glob("heads_*.pt"))
    n = min(cfg.curve_episodes, cfg.eval_episodes)
    for path in snapshots:
        heads, _ = load_heads(path, device=ccfg.device)
        counters = load_checkpoint(path)["counters"]
        methods = {}
        for m in METHODS:
            r = evaluate(ccfg, m, n, min(n, cfg.eval_batch_size), heads)
            if r is not None:
                r["gap_closed"] = gap_closed(r["mean_return"], random_ret, oracle_ret)
            methods[m] = _curve_point(r)
        points.append(
            {
                "frames": int(counters["frames"]),
                "updates": int(counters["updates"]),
                "seconds": float(counters["seconds"]),
                "methods": methods,
            }
        )
    if not cfg.keep_checkpoints:
        for path in snapshots:
            path.unlink(missing_ok=True)
    return points


def scale(
    cfg: ScaleConfig,
    out_dir: str | os.PathLike,
    progress: bool = True,
    quick: bool = False,
    plots: bool = True,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Run every (case, num_envs) cell, write the results folder, print the table.

    ``overwrite``: replace the results (and cell runs) already in ``out_dir``; without it such a
    folder is refused. ``out_dir`` is written like every results folder
    (:class:`~taskvar_torch.run_folder.ResultsFolder`: locked, filled in a staging folder and
    swapped in whole).

    Returns:
        The metrics dict written to ``metrics.json``.
    """
    folder = ResultsFolder(out_dir, overwrite, "taskvar experiment scale")
    folder.check()
    with folder as staging:
        metrics = _scale(cfg, staging, progress, quick, plots)
    where = folder.out  # printed once the staging folder is swapped in
    print(
        f"wrote {where / METRICS_NAME}, {where / CSV_NAME}"
        + (f", {where / FIGURE}" if plots else "")
    )
    return metrics


def _scale(cfg: ScaleConfig, out: Path, progress: bool, quick: bool, plots: bool) -> dict[str, Any]:
    """:func:`scale` writing into the folder ``out``."""
    save_config_yaml(cfg, out / "config.yaml")
    t0 = time.perf_counter()
    cases = cfg.selected()
    refs: dict[str, Any] = {}
    held_refs: dict[str, Any] = {}
    cells: list[dict[str, Any]] = []
    if cfg.baselines:  # a baseline a family lacks fails before any training
        for case in cases:
            check_case_baselines(cfg, case, case_config(cfg, case, cfg.num_envs[0]))
    bar = progress_bar(
        total=len(cases) * len(cfg.num_envs), disable=not progress, desc="scale", unit="cell"
    )
    for case in cases:
        ccfg = case_config(cfg, case, cfg.num_envs[0])
        refs[case.name] = references(ccfg, cfg.eval_episodes, cfg.eval_batch_size)
        held = heldout_references(cfg, ccfg) if cfg.heldout_count() > 0 else None
        if held is not None:
            held_refs[case.name] = held
        for n in cfg.num_envs:
            bar.set_postfix_str(f"{case.name} N={n}")
            cells.append(run_cell(cfg, case, n, out, refs[case.name], False, held))  # new folder
            bar.update(1)
    bar.close()
    metrics = {
        "experiment": EXPERIMENT,
        "quick": bool(quick),
        "methods": list(METHODS),
        "total_frames": cfg.total_frames,
        "num_envs": list(cfg.num_envs),
        "eval_episodes": cfg.eval_episodes,
        "test_seed": cfg.seed + TEST_SEED_OFFSET,
        "threads": torch.get_num_threads(),
        "references": refs,
        "cells": cells,
        "wall_seconds": time.perf_counter() - t0,
        "notes": {
            "return": "undiscounted test return (windy: -steps to the goal; Wargus: items collected)",
            "ci95": "half-width of a normal-approximation 95% confidence interval of the mean",
            "gap_closed": "(R - R_random) / (R_oracle_averaging - R_random) on the same episodes",
            "hierarchy": "n/a for a family without a composition hierarchy (windy, taxi)",
        },
    }
    if cfg.seeds > 1:  # new keys only: with one seed metrics.json is what it always was
        metrics["seeds"] = cfg.seeds
        metrics["notes"]["over_seeds"] = (
            "per cell: methods, curve and heads are seed `seed`'s run; per_seed holds every "
            "seed's methods on the same test episodes, over_seeds each method's mean over the "
            "seeds with rliable's stratified-bootstrap 95% CI [lo, hi] (mean_ci95)"
        )
    if cfg.baselines:  # new keys only: without baselines metrics.json is what it always was
        metrics["baselines"] = list(cfg.baselines)
        metrics["notes"]["baselines"] = (
            "per cell, methods (and per_seed, over_seeds, heldout) also hold the listed baselines "
            "(docs/memory.md), trained per seed on the cell's config and frame budget and played "
            "on the same test episodes; baseline_training, baseline_train_seconds: their training"
        )
    if held_refs:  # new keys only: with heldout_episodes=0 metrics.json is what it always was
        metrics["heldout"] = {
            "test": HELDOUT_TEST,
            "episodes": cfg.heldout_count(),
            "references": held_refs,
            "note": (
                "per cell, heldout holds every method on the family's sealed held-out test "
                "distribution (taskvar eval --test heldout: its sealed seed, HELDOUT_SEED), the "
                "same episodes for every method and seed; gap_closed against these references"
            ),
        }
    write_csv(out / CSV_NAME, csv_rows(metrics), csv_fields(metrics))
    write_json(out / METRICS_NAME, metrics)
    if plots:  # else ``taskvar plot DIR`` draws it from the folder
        plot_results(out)
    print(format_table(metrics))
    return metrics


__all__ = [  # the config and the protocol, then the names of scale_report it re-exports
    "METHODS",
    "HELDOUT_TEST",
    "SEED_CI_REPS",
    "TEST_SEED_OFFSET",
    "HeldoutTest",
    "ScaleCase",
    "ScaleConfig",
    "TablePolicy",
    "baseline_phase",
    "case_config",
    "check_case_baselines",
    "default_config_path",
    "evaluate",
    "gap_closed",
    "grid_side",
    "heldout_block",
    "heldout_references",
    "heldout_test",
    "isolated_rng",
    "load_scale_config",
    "make_policy",
    "make_test_env",
    "over_seeds",
    "peak_memory",
    "references",
    "run_cell",
    "scale",
    "scale_config_to_dict",
    "supported_baselines",
    "COLOURS",
    "CSV_FIELDS",
    "CSV_NAME",
    "CURVES_FIGURE",
    "EXPERIMENT",
    "FAMILY_STYLE",
    "FIGURE",
    "METRICS_NAME",
    "SEED_FIELD",
    "csv_fields",
    "csv_rows",
    "final_return",
    "format_heads",
    "format_heldout",
    "format_seeds",
    "format_table",
    "is_results_folder",
    "plot_curves",
    "plot_results",
    "report_methods",
]
