"""Range and choice checks of a :class:`~taskvar_torch.config.schema.Config`
(docs/design.md, Configs).

:func:`validate_config` runs in ``Config.__post_init__``, so every way of building a config (YAML,
overrides, a checkpoint's dict, ``dataclasses.replace``) is checked. Each error is one line naming
the dotted key and what is allowed there. The family's own keys (``env.<family>.*``, its
experiment's ``experiment.*``) are checked by their classes and the family's ``validate``
(taskvar_torch/families/); another family's keys are never read.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import torch

from taskvar_torch import rng
from taskvar_torch.config.choices import (
    ACTIVATIONS,
    COLLECTOR_BACKENDS,
    HEAD_NETWORKS,
    HIERARCHY_DESCENTS,
    LOGGERS,
    MATMUL_DTYPES,
    MAX_VALUE_ESTIMATORS,
    METHODS,
    MU_BAR_MODES,
    OPTION_INPUTS,
    REPLAY_SAMPLINGS,
    ROBUSTNESS_TARGETS,
    ROBUSTNESS_THRESHOLDS,
    ROBUSTNESS_UNTIL,
    ROOT_POLICIES,
    TARGET_UPDATES,
)
from taskvar_torch.contract import FAMILIES as _REGISTRY
from taskvar_torch.contract import Family, family
from taskvar_torch.contract import one_of as _one_of

Config = Any
"""A :class:`taskvar_torch.config.schema.Config` (not imported: the schema calls
:func:`validate_config` in ``Config.__post_init__``, so this module is below it)."""


MAX_SEED = rng.MAX_SEED
"""Largest seed (``seed``, ``taskvar eval --seed``, Gymnasium ``reset(seed=...)``): the keyed
random streams (taskvar_torch/rng.py) take 32-bit keys, so seeds are integers in
``[0, 2**32 - 1]``, each its own stream; a larger one is refused rather than wrapped onto another."""
MAX_COUNT = 2**31 - 1
"""Largest count of things a run allocates or loops over (environments, batch and buffer rows,
layer widths, episodes, workers...): every such key is also bounded by the memory estimate
(:mod:`taskvar_torch.config.memory`)."""
MAX_FRAMES = 10**15
"""Largest frame count (``train.total_frames`` and the other ``*_frames`` / ``*_every`` keys):
exact in float64, far beyond any run."""
MAX_HORIZON = rng.RESET_COUNTER - 1
"""Largest episode horizon: step ``t`` draws from counters below ``rng.RESET_COUNTER``."""
MAX_REAL = 1e9
"""Largest magnitude of a real-valued key without a narrower range (thresholds, temperatures,
gradient norms)."""


def _at_least(
    key: str, value: int | float | None, low: int | float, high: int | float = MAX_COUNT
) -> None:
    """``value`` (``None`` passes) must be in ``[low, high]``; a NaN is refused too."""
    if value is not None and not low <= value <= high:
        raise ValueError(f"{key} must be in [{low}, {high}], got {value}")


def _within(
    key: str,
    value: float,
    low: float,
    high: float,
    open_low: bool = False,
    open_high: bool = False,
) -> None:
    """``value`` must be a finite number in the range (NaN and infinities refused)."""
    ok = (
        math.isfinite(value)
        and (low < value if open_low else low <= value)
        and (value < high if open_high else value <= high)
    )
    if not ok:
        left, right = "(" if open_low else "[", ")" if open_high else "]"
        raise ValueError(
            f"{key} must be a finite number in {left}{low}, {high}{right}, got {value}"
        )


def _families_with(feature: str) -> str:
    """``family='windy'`` (or several, joined by "or"): the families that support ``feature``."""
    families = _REGISTRY.loaded().values()  # an unused plugin is not imported for a message
    return " or ".join(f"family={f.name!r}" for f in families if getattr(f, feature))


def validate_config(cfg: Config) -> None:
    """Check value ranges and choices; every error names the dotted key and what is allowed.

    The sections are checked in schema order (top level and env, heads, train, collector, eval
    and experiment), so the first bad key of a config is the one reported.
    """
    fam = family(cfg)  # a one-line error naming the registered families
    rng.check_seed(cfg.seed, "seed")
    # seeds a config derives from its own: seed + k of train.seeds, seed + 1 + run of the
    # experiments' test runs (and the evaluation's seed + 1)
    _at_least("train.seeds", cfg.train.seeds, 1, 1024)
    _at_least("experiment.runs", cfg.experiment.runs, 1, 10**6)
    last = cfg.seed + max(cfg.train.seeds - 1, cfg.experiment.runs)
    if last > MAX_SEED:
        raise ValueError(
            f"seed={cfg.seed} with train.seeds={cfg.train.seeds} and experiment.runs="
            f"{cfg.experiment.runs} uses seeds up to {last}, above the largest seed {MAX_SEED} "
            "(2**32 - 1); choose a smaller seed"
        )
    try:
        torch.device(cfg.device)
    except (RuntimeError, ValueError) as e:
        raise ValueError(
            f"device must be a torch device such as 'cpu' or 'cuda:0', got {cfg.device!r}"
        ) from e
    _at_least("env.num_envs", cfg.env.num_envs, 1)
    _check_family_section(cfg, fam)
    _one_of("env.instances", cfg.env.instances, fam.instance_names)
    if fam.validate is not None:
        fam.validate(cfg)  # the family's own checks; another family's keys are never read
    _check_heads(cfg, fam)
    _check_train(cfg, fam)
    _check_collector(cfg)
    _check_eval_and_experiment(cfg, fam)
    _check_baseline(cfg)


def _check_family_section(cfg: Config, fam: Family) -> None:
    """``env.<family>.*``: the family's own keys, range-checked by its ``config_class``."""
    _check_own_keys(f"env.{fam.name}", fam.config_class, fam.env_config(cfg))


def _check_own_keys(where: str, cls: type | None, section: Any) -> None:
    """A family's own keys (``env.<family>``, or its experiment's under ``experiment``) checked
    by rebuilding their class ``cls`` from ``section``; an error names ``where.<field>``."""
    if cls is None or section is None:
        return
    values = {f.name: getattr(section, f.name) for f in dataclasses.fields(cls)}
    try:
        cls(**values)
    except (TypeError, ValueError) as e:
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        first = msg.split(" ", 1)[0].rstrip(":")
        sep = "." if first in values else ": "
        raise ValueError(f"{where}{sep}{msg}") from None


def _check_heads(cfg: Config, fam: Family) -> None:
    """``heads.*``: layer sizes, activation, network kind and what the family supports."""
    if len(cfg.heads.hidden) > 64:
        raise ValueError(f"heads.hidden must have at most 64 layers, got {len(cfg.heads.hidden)}")
    for i, h in enumerate(cfg.heads.hidden):
        _at_least(f"heads.hidden[{i}]", h, 1, 2**20)
    _one_of("heads.activation", cfg.heads.activation, ACTIVATIONS)
    _one_of("heads.network", cfg.heads.network, HEAD_NETWORKS)
    if cfg.heads.network == "conv":
        if not cfg.heads.conv_channels:
            raise ValueError("heads.conv_channels must name at least one layer, got []")
        if len(cfg.heads.conv_channels) > 64:
            raise ValueError(
                f"heads.conv_channels must have at most 64 layers, got "
                f"{len(cfg.heads.conv_channels)}"
            )
        for i, c in enumerate(cfg.heads.conv_channels):
            _at_least(f"heads.conv_channels[{i}]", c, 1, 2**16)
        if fam.conv_patch is None:
            raise ValueError(
                "heads.network='conv' needs a family with a patch observation "
                f"({_families_with('conv_patch')}), got family={cfg.family!r}"
            )
        fam.conv_patch(cfg)  # raises naming the observation key it needs
    _one_of("heads.option_inputs", cfg.heads.option_inputs, OPTION_INPUTS)
    if cfg.heads.option_inputs == "subtask" and (
        not fam.option_inputs or cfg.heads.network != "mlp"
    ):
        raise ValueError(
            "heads.option_inputs='subtask' needs a family whose options define input features "
            f"({_families_with('option_inputs')}) and heads.network='mlp', "
            f"got family={cfg.family!r}, heads.network={cfg.heads.network!r}"
        )


def _check_baseline(cfg: Config) -> None:
    """``baseline.*``: the recurrent baseline's own sizes, the baselines' budgets and the informed
    and blind baselines' evaluation average."""
    _at_least("baseline.hidden", cfg.baseline.hidden, 1, 2**20)  # as heads.hidden's widths
    _at_least("baseline.slice_len", cfg.baseline.slice_len, 1, MAX_HORIZON)
    _at_least("baseline.burn_in", cfg.baseline.burn_in, 0, MAX_HORIZON)
    if cfg.baseline.recurrent_frames is not None:
        _at_least("baseline.recurrent_frames", cfg.baseline.recurrent_frames, 1, MAX_FRAMES)
    if cfg.baseline.informed_frames is not None:
        _at_least("baseline.informed_frames", cfg.baseline.informed_frames, 1, MAX_FRAMES)
    tau = cfg.baseline.informed_ema_tau
    if tau is not None and not 0.0 < tau <= 1.0:
        raise ValueError(f"baseline.informed_ema_tau must be in (0, 1] or null, got {tau}")


def _check_train(cfg: Config, fam: Family) -> None:
    """``train.*``: discounts, rates, schedules, target updates and the estimators' choices."""
    t = cfg.train
    _within("train.gamma", t.gamma, 0.0, 1.0, open_high=True)
    _within("train.robustness_gamma", t.robustness_gamma, 0.0, 1.0, open_high=True)
    _within("train.robustness_tau", t.robustness_tau, -MAX_REAL, MAX_REAL)
    _one_of("train.robustness_target", t.robustness_target, ROBUSTNESS_TARGETS)
    _one_of("train.hierarchy_root_policy", t.hierarchy_root_policy, ROOT_POLICIES)
    _one_of("train.robustness_threshold", t.robustness_threshold, ROBUSTNESS_THRESHOLDS)
    if not 0.0 < t.robustness_keep_share < 1.0:
        raise ValueError(
            f"train.robustness_keep_share must be in (0, 1), got {t.robustness_keep_share}"
        )
    _one_of("train.robustness_until", t.robustness_until, ROBUSTNESS_UNTIL)
    _one_of("train.hierarchy_descent", t.hierarchy_descent, HIERARCHY_DESCENTS)
    _within("train.lr", t.lr, 0.0, MAX_REAL, open_low=True)
    if t.lr_end is not None and not (math.isfinite(t.lr_end) and 0 < t.lr_end <= t.lr):
        raise ValueError(f"train.lr_end must be in (0, train.lr={t.lr}] or null, got {t.lr_end}")
    _at_least("train.lr_decay_start_frames", t.lr_decay_start_frames, 0, MAX_FRAMES)
    _at_least("train.batch_size", t.batch_size, 1)
    _at_least("train.buffer_size", t.buffer_size, t.batch_size, MAX_FRAMES)
    _at_least("train.frames_per_batch", t.frames_per_batch, 1)
    _at_least("train.total_frames", t.total_frames, 0, MAX_FRAMES)
    _at_least("train.updates_per_batch", t.updates_per_batch, 0, 2**20)
    _at_least("train.init_random_frames", t.init_random_frames, 0, MAX_FRAMES)
    _within("train.eps_start", t.eps_start, 0.0, 1.0)
    _within("train.eps_end", t.eps_end, 0.0, 1.0)
    _at_least("train.eps_decay_frames", t.eps_decay_frames, 0, MAX_FRAMES)
    _within("train.option_behaviour_prob", t.option_behaviour_prob, 0.0, 1.0)
    _within("train.option_coverage", t.option_coverage, 0.0, 1.0)
    _one_of("train.replay_sampling", t.replay_sampling, REPLAY_SAMPLINGS)
    _at_least("train.n_step", t.n_step, 1, 1024)
    _one_of("train.target_update", t.target_update, TARGET_UPDATES)
    _within("train.target_tau", t.target_tau, 0.0, 1.0, open_low=True)
    _at_least("train.target_period", t.target_period, 1, MAX_FRAMES)
    if not 0.0 < t.max_value_expectile < 1.0:
        raise ValueError(
            f"train.max_value_expectile must be in (0, 1), got {t.max_value_expectile}"
        )
    _one_of("train.max_value_estimator", t.max_value_estimator, MAX_VALUE_ESTIMATORS)
    _one_of("train.matmul_dtype", t.matmul_dtype, MATMUL_DTYPES)
    if t.eval_ema_tau is not None and not 0.0 < t.eval_ema_tau <= 1.0:
        raise ValueError(f"train.eval_ema_tau must be in (0, 1] or null, got {t.eval_ema_tau}")
    _at_least("train.max_value_instances", t.max_value_instances, 1)
    _one_of("train.logger", t.logger, LOGGERS)
    if t.max_value_estimator == "instance" and fam.instance_dim is None:
        raise ValueError(
            "train.max_value_estimator='instance' needs instance features "
            f"({_families_with('instance_dim')}), got "
            f"family={cfg.family!r}: use 'expectile' (taskvar_torch/heads/max_value.py)"
        )
    _one_of("train.mu_bar", t.mu_bar, MU_BAR_MODES)
    _within("train.mu_bar_temperature", t.mu_bar_temperature, 0.0, MAX_REAL, open_low=True)
    if t.max_grad_norm is not None:
        _within("train.max_grad_norm", t.max_grad_norm, 0.0, MAX_REAL, open_low=True)
    _at_least("train.checkpoint_every", t.checkpoint_every, 0, MAX_FRAMES)
    _at_least("train.log_every", t.log_every, 1, MAX_FRAMES)
    _at_least("train.heads_every", t.heads_every, 0, MAX_FRAMES)
    if isinstance(t.seeds, bool) or not isinstance(t.seeds, int) or not 1 <= t.seeds <= 1024:
        raise ValueError(f"train.seeds must be an integer in [1, 1024], got {t.seeds!r}")
    if t.seeds > 1 and (cfg.collector.num_workers > 1 or cfg.collector.backend == "ray"):
        raise ValueError(
            f"train.seeds={t.seeds} runs in one collector process: set collector.num_workers=1 "
            f"and collector.backend=process (got {cfg.collector.num_workers} and "
            f"{cfg.collector.backend!r})"
        )
    if t.seeds > 1 and cfg.heads.network != "mlp":
        raise ValueError(
            f"train.seeds={t.seeds} needs heads.network=mlp (the conv trunk has no seed axis), "
            f"got {cfg.heads.network!r}"
        )


def _check_collector(cfg: Config) -> None:
    """``collector.*``: workers, backend, and that the workers split the batch evenly."""
    env, t = cfg.env, cfg.train
    w = cfg.collector.num_workers
    _at_least("collector.num_workers", w, 1, 1024)
    _one_of("collector.backend", cfg.collector.backend, COLLECTOR_BACKENDS)
    if cfg.collector.ray_address is not None and cfg.collector.backend != "ray":
        raise ValueError(
            f"collector.ray_address is for collector.backend=ray, got backend "
            f"{cfg.collector.backend!r}"
        )
    if env.num_envs % w or t.frames_per_batch % w:
        raise ValueError(
            f"collector.num_workers={w} must divide env.num_envs ({env.num_envs}) and "
            f"train.frames_per_batch ({t.frames_per_batch})"
        )


def _check_eval_and_experiment(cfg: Config, fam: Family) -> None:
    """``eval.*``: the method and positive episode counts; ``experiment.*``: the family's
    experiment's own keys, range-checked by its ``config_class`` (``experiment.runs`` is checked
    first, with the seeds)."""
    _one_of("eval.method", cfg.eval.method, METHODS)
    _at_least("eval.episodes", cfg.eval.episodes, 1)
    _at_least("eval.batch_size", cfg.eval.batch_size, 1)
    if fam.experiment is not None:
        _check_own_keys("experiment", fam.experiment.config_class, cfg.experiment)
