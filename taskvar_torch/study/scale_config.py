"""The scale experiment's config (docs/scale.md; configs/scale.yaml): the cases, ``num_envs``
values, budget and evaluation sizes (:class:`ScaleConfig`), each cell's training config
(:func:`case_config`) and the baselines a family supports.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from taskvar_torch import rng
from taskvar_torch.config import (
    Config,
    apply_overrides,
    load_config,
)
from taskvar_torch.config.loader import overrides_for
from taskvar_torch.heads.informed import informed_features
from taskvar_torch.heads.recurrent import (
    BASELINES,
)

TEST_SEED_OFFSET = 1000
"""Test episodes use env seed ``seed + TEST_SEED_OFFSET`` (never a training seed)."""


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
    """key.sub=value overrides applied to every case's family config (before the case's own); a
    family's own keys (``env.<family>.*``) reach its cases only."""
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


def case_config(cfg: ScaleConfig, case: ScaleCase, num_envs: int) -> Config:
    """The family config of one cell: the case's YAML, the budget, ``num_envs`` and the overrides;
    ``frames_per_batch`` a multiple of ``num_envs``, updates per frame kept.
    """
    family = load_config(case.config).family  # the experiment's overrides hit its keys only
    base = load_config(case.config, [*overrides_for(cfg.overrides, family), *case.overrides])
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


__all__ = [
    "SCHEDULE_KEYS",
    "TEST_SEED_OFFSET",
    "ScaleCase",
    "ScaleConfig",
    "case_config",
    "case_frames",
    "check_case_baselines",
    "supported_baselines",
]
