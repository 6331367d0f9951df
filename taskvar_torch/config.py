"""Strict experiment configs: frozen dataclasses mirrored by ``configs/*.yaml``.

Loading goes through OmegaConf structured configs: the YAML file is merged into the schema built
from :class:`Config`, then Hydra-style ``key.sub=value`` overrides are merged on top, and the result
is converted back to frozen dataclasses. An unknown or misspelt key anywhere, or a value of the
wrong type, is a one-line ``ValueError`` naming the full dotted key (and, for unknown keys, the keys
allowed at that level); values outside their allowed set or range are checked in
``Config.__post_init__`` and name the field and the allowed values.

Every field carries a docstring (the string literal right below it); :func:`config_help` turns them
into ``--help`` text.

Examples:
    >>> cfg = load_config("configs/windy.yaml", ["train.lr=0.01"])
    >>> cfg.train.lr
    0.01
    >>> config_from_dict(config_to_dict(cfg)) == cfg
    True
"""

from __future__ import annotations

import ast
import dataclasses
import difflib
import inspect
import os
import secrets
import textwrap
import typing
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import torch
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from taskvar_torch.families import FAMILIES as _REGISTRY
from taskvar_torch.families import (  # noqa: F401  (GENERATED and the windy helpers: re-exported)
    GENERATED,
    family,
    windy_env_kwargs,
    windy_layout,
)

FAMILIES = tuple(sorted(_REGISTRY))  # the family registry's names (taskvar_torch/families.py)
ACTIVATIONS = ("elu", "gelu", "relu", "silu", "tanh")
HEAD_NETWORKS = ("mlp", "conv")  # taskvar_torch/heads/networks.py NETWORKS
OPTION_INPUTS = ("full", "subtask")
TARGET_UPDATES = ("hard", "soft")
SWITCHING_MODES = ("intra",)
MU_BAR_MODES = ("greedy", "softmax")
MAX_VALUE_ESTIMATORS = ("expectile", "instance")
ROBUSTNESS_TARGETS = ("greedy", "option")  # mirrors heads/robustness.py
ROOT_POLICIES = ("averaging", "option")  # mirrors controllers/base.py
ROBUSTNESS_THRESHOLDS = ("calibrated", "fixed")
ROBUSTNESS_UNTIL = ("episode", "termination")  # mirrors heads/robustness.py
HIERARCHY_DESCENTS = ("normalised", "raw")  # mirrors controllers/hierarchy.py
COMPOSED_REWARDS = ("env", "sum")  # mirrors subtasks/wargus.py
METHODS = ("averaging", "hierarchy", "interruption", "options")
COLLECTOR_BACKENDS = ("process", "ray")  # taskvar_torch/train.py make_collector


@dataclass(frozen=True)
class WargusConfig:
    """Wargus resource-gathering family (paper §3.5); read only when ``family='wargus'``."""

    size: int = 32
    """Grid side length (size x size cells, no obstacles)."""
    num_patrols: int = 1
    """Number of enemy patrols."""
    num_items: int = 1
    """Number of items present at a time."""
    sight: int = 8
    """An object is seen when its Chebyshev distance to the viewer is < sight."""
    shoot_range: int = 5
    """A patrol shoots when the agent is within this Chebyshev distance."""
    hit_prob: float = 1.0
    """Probability that a shot destroys the agent."""
    patrol_speed: float = 0.8
    """Probability that a patrol moves on a given step."""
    horizon: int = 500
    """Steps before truncation."""
    noop: bool = False
    """Add a no-op action to the 8 compass moves."""


@dataclass(frozen=True)
class EnvConfig:
    """The environment: shared and windy fields at this level, Wargus fields under ``env.wargus``.

    Only the keys of ``family`` are validated and read; the other family's are ignored.
    """

    num_envs: int = 16
    """Number of environments simulated in parallel for training (the batch size N)."""
    layout: str = "default"
    """Windy layout: a name (default, middle_exits, whole_column_windy), a multi-line map string,
    or 'generated' to build it from height/width/num_exits/wall_col/wind_cells_per_exit."""
    height: int | None = None
    """Generated windy grid: number of rows (only with layout='generated')."""
    width: int | None = None
    """Generated windy grid: number of columns (only with layout='generated')."""
    num_exits: int | None = None
    """Generated windy grid: exits in the wall, >= 2 (only with layout='generated'; default 2)."""
    wall_col: int | None = None
    """Generated windy grid: column of the wall (only with layout='generated'; default width // 2)."""
    wind_cells_per_exit: int | None = None
    """Generated windy grid: windy cells west of each exit (only with layout='generated'; default 1)."""
    instances: str = "train"
    """Training instance distribution; windy: train, test, south or north; Wargus: train, test or
    nominal."""
    horizon: int | None = None
    """Windy steps before truncation; null: max(100, 4 * (height + width))."""
    obs_encoding: str = "onehot"
    """Windy observation: onehot (one-hot cell) or coords_patch (coordinates + local patch)."""
    patch_radius: int = 2
    """Windy coords_patch encoding: radius r of the (2r+1)^2 local patch."""
    wargus: WargusConfig = field(default_factory=WargusConfig)
    """Wargus family parameters."""


@dataclass(frozen=True)
class HeadsConfig:
    """Network shapes shared by every head (averaging, options, switching, max-value, robustness)."""

    hidden: tuple[int, ...] = (64, 64)
    """MLP hidden layer widths; [] gives a linear head."""
    activation: str = "relu"
    """Hidden-layer activation: elu, gelu, relu, silu or tanh."""
    network: str = "mlp"
    """mlp (over the whole observation) or conv (windy coords_patch only: 3x3 convs over the local
    patch, flattened, plus the coordinates, then the MLP; one conv trunk per head)."""
    conv_channels: tuple[int, ...] = (16, 32)
    """heads.network=conv: output channels of each 3x3 conv layer (same padding)."""
    option_inputs: str = "full"
    """full (every option's policy sees the whole observation) or subtask (wargus, mlp: each
    option's policy is its own network that sees its subtask's features only: TG the item's, FE
    the patrol's, both the agent's position; the composed root sees everything)."""


@dataclass(frozen=True)
class TrainConfig:
    """Offline training of every head from one stream of experience (docs/design.md, Training)."""

    gamma: float = 0.99
    """Discount of the environment and subtask rewards."""
    lr: float = 1e-3
    """Adam learning rate."""
    batch_size: int = 256
    """Transitions per gradient step (one shared sample for all heads)."""
    buffer_size: int = 100_000
    """Replay buffer capacity in transitions."""
    frames_per_batch: int = 256
    """Environment steps (summed over the N environments) collected between update phases."""
    total_frames: int = 200_000
    """Total environment steps to collect."""
    updates_per_batch: int = 4
    """Gradient steps after each collected batch (update-to-data ratio)."""
    init_random_frames: int = 5_000
    """Steps of uniformly random actions collected before learning starts."""
    eps_start: float = 1.0
    """Initial epsilon of epsilon-greedy exploration."""
    eps_end: float = 0.05
    """Final epsilon."""
    eps_decay_frames: int = 100_000
    """Steps over which epsilon decays linearly from eps_start to eps_end."""
    option_behaviour_prob: float = 0.5
    """Share of training episodes whose behaviour runs mu_bar-picked options (epsilon-greedy in
    their option heads) instead of epsilon-greedy in the averaging head."""
    first_visit: bool = True
    """Replay only the first visit of each (observation, action) per episode, so every instance
    weighs equally at a state-action as in the mean MDP (taskvar_torch/heads/first_visit.py)."""
    target_update: str = "soft"
    """Target-network update: soft (Polyak, target_tau) or hard (copy every target_period)."""
    target_tau: float = 0.01
    """Soft target update rate (target_update='soft')."""
    target_period: int = 500
    """Gradient steps between hard target copies (target_update='hard')."""
    double_q: bool = True
    """Use double Q-learning targets."""
    max_value_expectile: float = 0.95
    """Expectile level of the max-value head's upper estimator, in (0, 1)."""
    switching: str = "intra"
    """Option-switching learner: intra (intra-option Q-learning; SMDP learning is not built yet)."""
    mu_bar: str = "greedy"
    """mu_bar over Q_mu: greedy or softmax."""
    mu_bar_temperature: float = 1.0
    """Softmax temperature of mu_bar (mu_bar='softmax')."""
    robustness_gamma: float = 0.99
    """Discount of the robustness critics (Wargus): 0.99 looks ~100 steps ahead, so the root's
    R(TG+FE) reads survival and future sightings, not only whether the item is in sight now
    (heads/robustness.py "Scale")."""
    robustness_tau: float = 2.0
    """Robustness threshold tau of the hierarchy controller (Wargus) when
    robustness_threshold='fixed' (the paper's 2), and the fallback of a calibration with no
    qualifying state."""
    robustness_threshold: str = "calibrated"
    """How the hierarchy's thresholds are set (Wargus): fixed (robustness_tau for every
    capability) or calibrated (per capability, on training states: a composed subtask keeps
    control on robustness_keep_share of the training states where its subgoals do not conflict;
    heads/robustness.py RobustnessCalibration). Never set on the nominal test seeds."""
    robustness_keep_share: float = 0.9
    """robustness_threshold='calibrated': share of no-conflict training states on which a composed
    subtask keeps control, in (0, 1)."""
    robustness_until: str = "termination"
    """Horizon of the robustness critics (Wargus): termination (no bootstrap past the option's own
    termination beta_o or the episode's end) or episode (bootstrap through beta_o)."""
    robustness_target: str = "option"
    """Next action of the robustness critics' TD target (Wargus): option (pi^o(s'), R of following
    option o, paper §3.4.3) or greedy (argmax_a' R_o(s', a'), Q-learning on R)."""
    hierarchy_root_policy: str = "averaging"
    """Policy of the hierarchy's root (Wargus), in the controller and in its robustness target:
    averaging (the averaging head: paper §3.4.2, "the policy of this subtask is the full task
    averaging policy") or option (the root's own option head). The same root policy is used by
    the options and interruption controllers and by the behaviour's option episodes."""
    hierarchy_termination: bool = True
    """Hierarchy controller (Wargus): honour the options' termination (a component whose beta
    holds hands control back up; the descent only picks components that can take control there).
    false: the paper's literal Algorithm 2."""
    hierarchy_descent: str = "normalised"
    """Hierarchy controller (Wargus): metric of the descent to a component, raw (argmax R, the
    paper) or normalised ((R - tau) / scale per component, a common scale)."""
    composed_reward: str = "env"
    """Subtask reward of the composed option TG+FE (Wargus): env (the environment reward: it is
    the full task, paper §3.4.2) or sum (TG's plus FE's subtask rewards)."""
    max_grad_norm: float | None = 10.0
    """Gradient-norm clipping; null disables it."""
    checkpoint_every: int = 50_000
    """Save a checkpoint every this many frames; 0: only the final one."""
    log_every: int = 5_000
    """Write a log row every this many frames."""
    max_value_estimator: str = "expectile"
    """Estimator of the max-value head Q_hat (Definition 1; taskvar_torch/heads/max_value.py):
    expectile (expectile-TD upper estimator, max_value_expectile: optimistic over all randomness,
    any family) or instance (an instance-conditioned critic Q(s, o | z) learnt by intra-option TD
    under mu_bar, its max over the training instances in the sample distilled into Q_hat: optimism
    over instances only; windy only, the instance z = (p, direction) is read from the replay)."""
    max_value_instances: int = 64
    """max_value_estimator=instance: training instances (from the sampled batch) the max of
    Definition 1 is taken over at each update."""


@dataclass(frozen=True)
class CollectorConfig:
    """Experience collection: one process, TorchRL's MultiSyncCollector, or Ray collector actors
    (docs/design.md, Many processes and Ray actors)."""

    num_workers: int = 1
    """Collector workers; > 1 gives each a slice of env.num_envs (behaviour weights and epsilon
    synced after every update phase, no exact resume)."""
    backend: str = "process"
    """process: the workers are spawned processes on this machine (MultiSyncCollector; with
    num_workers = 1 collection runs in the trainer's own process); ray: each worker is a Ray actor
    (TorchRL Collector(backend="ray"), even with num_workers = 1), on a new local Ray or the
    cluster at ray_address."""
    ray_address: str | None = None
    """backend=ray: the Ray cluster to join ("auto", "HOST:6379"); null starts a local Ray (an
    already running Ray in the process is reused)."""


@dataclass(frozen=True)
class EvalConfig:
    """Evaluation of a trained bundle on an instance distribution."""

    method: str = "interruption"
    """Controller: averaging, options, interruption or hierarchy."""
    episodes: int = 1_000
    """Evaluation episodes."""
    test: str = "test"
    """Test instance distribution (names as for env.instances)."""
    batch_size: int = 1_000
    """Environments evaluated in parallel."""


@dataclass(frozen=True)
class ExperimentConfig:
    """The paper's experiments: windy Figure 2, Wargus Figure 4."""

    runs: int = 5
    """Independent repetitions (windy: test runs; Wargus: repetitions)."""
    episodes_per_run: int = 10_000
    """Windy Figure 2: test episodes per run."""
    trials: int = 500
    """Wargus Figure 4: trials per repetition."""
    learning_episodes_per_trial: int = 30
    """Wargus Figure 4: learning episodes per trial."""
    test_episodes_per_trial: int = 5
    """Wargus Figure 4: nominal test episodes per trial (fixed seeds, no learning)."""
    quick_overrides: tuple[str, ...] = ()
    """key.sub=value overrides applied by load_config(..., quick=True) (smoke tests, notebooks)."""


@dataclass(frozen=True)
class Config:
    """A whole experiment: family, seed, device, environment, heads, training, evaluation."""

    family: str = "windy"
    """MDP family: wargus or windy."""
    seed: int = 0
    """Master seed of environments, networks and exploration."""
    device: str = "cpu"
    """Torch device for environments and networks (cpu, cuda, cuda:1...)."""
    env: EnvConfig = field(default_factory=EnvConfig)
    """Environment family."""
    heads: HeadsConfig = field(default_factory=HeadsConfig)
    """Network shapes."""
    train: TrainConfig = field(default_factory=TrainConfig)
    """Training."""
    collector: CollectorConfig = field(default_factory=CollectorConfig)
    """Experience collection workers (processes or Ray actors)."""
    eval: EvalConfig = field(default_factory=EvalConfig)
    """Evaluation."""
    experiment: ExperimentConfig = field(default_factory=ExperimentConfig)
    """Experiments."""

    def __post_init__(self):
        _validate(self)


# --------------------------------------------------------------------------------------------
# validation


def _one_of(key: str, value: Any, allowed: Sequence[str]) -> None:
    if value not in allowed:
        raise ValueError(f"{key} must be one of {sorted(allowed)}, got {value!r}")


def _at_least(key: str, value: int | float | None, low: int | float) -> None:
    if value is not None and value < low:
        raise ValueError(f"{key} must be >= {low}, got {value}")


def _within(key: str, value: float, low: float, high: float, open_low: bool = False) -> None:
    ok = (low < value if open_low else low <= value) and value <= high
    if not ok:
        raise ValueError(f"{key} must be in {'(' if open_low else '['}{low}, {high}], got {value}")


def _families_with(feature: str) -> str:
    """``family='windy'`` (or several, joined by "or"): the families that support ``feature``."""
    return " or ".join(f"family={f.name!r}" for f in _REGISTRY.values() if getattr(f, feature))


def _validate(cfg: Config) -> None:
    """Check value ranges and choices; every error names the dotted key and what is allowed."""
    _one_of("family", cfg.family, FAMILIES)
    try:
        torch.device(cfg.device)
    except (RuntimeError, ValueError) as e:
        raise ValueError(
            f"device must be a torch device such as 'cpu' or 'cuda:0', got {cfg.device!r}"
        ) from e
    env = cfg.env
    _at_least("env.num_envs", env.num_envs, 1)
    fam = family(cfg)
    fam.validate(cfg)  # the family's own keys; the other family's are never read

    for i, h in enumerate(cfg.heads.hidden):
        _at_least(f"heads.hidden[{i}]", h, 1)
    _one_of("heads.activation", cfg.heads.activation, ACTIVATIONS)
    _one_of("heads.network", cfg.heads.network, HEAD_NETWORKS)
    if cfg.heads.network == "conv":
        if not cfg.heads.conv_channels:
            raise ValueError("heads.conv_channels must name at least one layer, got []")
        for i, c in enumerate(cfg.heads.conv_channels):
            _at_least(f"heads.conv_channels[{i}]", c, 1)
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

    t = cfg.train
    _within("train.gamma", t.gamma, 0.0, 1.0, open_low=True)
    _within("train.robustness_gamma", t.robustness_gamma, 0.0, 1.0, open_low=True)
    _one_of("train.robustness_target", t.robustness_target, ROBUSTNESS_TARGETS)
    _one_of("train.hierarchy_root_policy", t.hierarchy_root_policy, ROOT_POLICIES)
    _one_of("train.robustness_threshold", t.robustness_threshold, ROBUSTNESS_THRESHOLDS)
    if not 0.0 < t.robustness_keep_share < 1.0:
        raise ValueError(
            f"train.robustness_keep_share must be in (0, 1), got {t.robustness_keep_share}"
        )
    _one_of("train.robustness_until", t.robustness_until, ROBUSTNESS_UNTIL)
    _one_of("train.hierarchy_descent", t.hierarchy_descent, HIERARCHY_DESCENTS)
    _one_of("train.composed_reward", t.composed_reward, COMPOSED_REWARDS)
    if not t.lr > 0:
        raise ValueError(f"train.lr must be > 0, got {t.lr}")
    _at_least("train.batch_size", t.batch_size, 1)
    _at_least("train.buffer_size", t.buffer_size, t.batch_size)
    _at_least("train.frames_per_batch", t.frames_per_batch, 1)
    _at_least("train.total_frames", t.total_frames, 0)
    _at_least("train.updates_per_batch", t.updates_per_batch, 0)
    _at_least("train.init_random_frames", t.init_random_frames, 0)
    _within("train.eps_start", t.eps_start, 0.0, 1.0)
    _within("train.eps_end", t.eps_end, 0.0, 1.0)
    _at_least("train.eps_decay_frames", t.eps_decay_frames, 0)
    _within("train.option_behaviour_prob", t.option_behaviour_prob, 0.0, 1.0)
    _one_of("train.target_update", t.target_update, TARGET_UPDATES)
    _within("train.target_tau", t.target_tau, 0.0, 1.0, open_low=True)
    _at_least("train.target_period", t.target_period, 1)
    if not 0.0 < t.max_value_expectile < 1.0:
        raise ValueError(
            f"train.max_value_expectile must be in (0, 1), got {t.max_value_expectile}"
        )
    _one_of("train.switching", t.switching, SWITCHING_MODES)
    _one_of("train.max_value_estimator", t.max_value_estimator, MAX_VALUE_ESTIMATORS)
    _at_least("train.max_value_instances", t.max_value_instances, 1)
    if t.max_value_estimator == "instance" and fam.instance_dim is None:
        raise ValueError(
            "train.max_value_estimator='instance' needs instance features "
            f"({_families_with('instance_dim')}), got "
            f"family={cfg.family!r}: use 'expectile' (taskvar_torch/heads/max_value.py)"
        )
    _one_of("train.mu_bar", t.mu_bar, MU_BAR_MODES)
    if not t.mu_bar_temperature > 0:
        raise ValueError(f"train.mu_bar_temperature must be > 0, got {t.mu_bar_temperature}")
    if t.max_grad_norm is not None and not t.max_grad_norm > 0:
        raise ValueError(f"train.max_grad_norm must be > 0 or null, got {t.max_grad_norm}")
    _at_least("train.checkpoint_every", t.checkpoint_every, 0)
    _at_least("train.log_every", t.log_every, 1)

    w = cfg.collector.num_workers
    _at_least("collector.num_workers", w, 1)
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

    _one_of("eval.method", cfg.eval.method, METHODS)
    _at_least("eval.episodes", cfg.eval.episodes, 1)
    _at_least("eval.batch_size", cfg.eval.batch_size, 1)

    x = cfg.experiment
    for name in ("runs", "episodes_per_run", "trials", "learning_episodes_per_trial"):
        _at_least(f"experiment.{name}", getattr(x, name), 1)
    _at_least("experiment.test_episodes_per_trial", x.test_episodes_per_trial, 1)


# --------------------------------------------------------------------------------------------
# strict loading


def _schema_class(dotted: str) -> type | None:
    """The dataclass that holds the last component of ``dotted`` (``train.lr`` -> TrainConfig)."""
    cls: type = Config
    for part in [p for p in dotted.split(".") if p][:-1]:
        hints = typing.get_type_hints(cls)
        if part not in hints or not dataclasses.is_dataclass(hints[part]):
            return None
        cls = hints[part]
    return cls


def _first_non_mapping(node: Any, cls: type, prefix: str = "") -> str | None:
    """First dotted key whose value should be a section (mapping) but is not."""
    if not isinstance(node, Mapping):
        return None
    hints = typing.get_type_hints(cls)
    for k, v in node.items():
        t = hints.get(k)
        if t is not None and dataclasses.is_dataclass(t):
            if not isinstance(v, Mapping):
                return f"{prefix}{k}"
            found = _first_non_mapping(v, t, f"{prefix}{k}.")
            if found:
                return found
    return None


def _config_error(e: OmegaConfBaseException, source: str, raw: Any) -> ValueError:
    """Turn an OmegaConf error into a one-line ValueError naming the dotted key."""
    key = getattr(e, "full_key", None)
    first = (
        str(getattr(e, "msg", None) or e).strip().splitlines()[0]
        if str(e).strip()
        else type(e).__name__
    )
    if not key:
        key = _first_non_mapping(raw, Config)
        if key:
            cls = _schema_class(key + ".x")
            return ValueError(
                f"config key {key!r} ({source}) must be a section of "
                f"{[f.name for f in dataclasses.fields(cls)]}, got {_raw_value(raw, key)!r}"
            )
        key = _failing_leaf(raw)
        if not key:
            return ValueError(f"invalid config ({source}): {first}")
        value = _raw_value(raw, key)
        if "$VALUE" in first:  # an unformatted OmegaConf template: "... converted to Integer"
            first = f"{value!r} could not be converted to {first.rsplit(' ', 1)[-1]}"
    leaf = key.split(".")[-1]
    cls = _schema_class(key)
    allowed = [f.name for f in dataclasses.fields(cls)] if cls is not None else []
    if cls is not None and leaf not in allowed:
        level = key.rsplit(".", 1)[0] if "." in key else "the top level"
        hint = difflib.get_close_matches(leaf, allowed, n=1)
        mean = f" (did you mean {hint[0]!r}?)" if hint else ""
        return ValueError(
            f"unknown config key {key!r} ({source}){mean}; allowed keys in {level}: {', '.join(allowed)}"
        )
    return ValueError(f"bad value for config key {key!r} ({source}): {first}")


def _failing_leaf(raw: Any) -> str | None:
    """The first dotted leaf of ``raw`` that fails to merge on its own (OmegaConf sometimes loses
    the key, e.g. for a bad list element)."""
    if not isinstance(raw, Mapping):
        return None

    def leaves(node: Mapping, prefix: str = ""):
        for k, v in node.items():
            if isinstance(v, Mapping) and v:
                yield from leaves(v, f"{prefix}{k}.")
            else:
                yield f"{prefix}{k}", v

    for dotted, value in leaves(raw):
        single: Any = value
        for part in reversed(dotted.split(".")):
            single = {part: single}
        try:
            OmegaConf.merge(_schema(), single)
        except OmegaConfBaseException:
            return dotted
    return None


def _raw_value(raw: Any, dotted: str) -> Any:
    """Value at ``dotted`` in a nested mapping, or None."""
    node = raw
    for part in dotted.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return None
        node = node[part]
    return node


def _merge(base: DictConfig, update: Any, source: str) -> DictConfig:
    raw = OmegaConf.to_container(update) if isinstance(update, DictConfig) else update
    if not isinstance(raw, Mapping):
        raise ValueError(
            f"config ({source}) must be a mapping of keys to values, got {type(raw).__name__}"
        )
    try:
        return OmegaConf.merge(base, update)
    except OmegaConfBaseException as e:
        raise _config_error(e, source, raw) from None


def _to_config(node: DictConfig, source: str) -> Config:
    try:
        cfg = OmegaConf.to_object(node)
    except OmegaConfBaseException as e:
        raise _config_error(e, source, None) from None
    except ValueError as e:  # Config.__post_init__: range and choice checks
        raise ValueError(f"{e} ({source})") from None
    assert isinstance(cfg, Config)
    return cfg


def _parse_override(item: str) -> DictConfig:
    if not isinstance(item, str) or "=" not in item or item.startswith(("+", "~")):
        raise ValueError(f"override {item!r} must look like key.sub=value (e.g. train.lr=0.01)")
    try:
        return OmegaConf.from_dotlist([item])
    except OmegaConfBaseException as e:
        raise ValueError(f"override {item!r} cannot be parsed: {str(e).splitlines()[0]}") from None


def _apply_overrides(node: DictConfig, overrides: Sequence[str]) -> DictConfig:
    if isinstance(overrides, str):
        overrides = [overrides]
    parsed = [_parse_override(item) for item in overrides]
    if not parsed:
        return node
    try:  # one merge; on failure, redo them one by one to name the culprit
        return OmegaConf.merge(node, *parsed)
    except OmegaConfBaseException:
        for item, update in zip(overrides, parsed):
            node = _merge(node, update, f"override {item!r}")
        return node


def _schema() -> DictConfig:
    node = OmegaConf.structured(Config)
    OmegaConf.set_readonly(node, False)
    return node


def load_config(
    path: str | os.PathLike, overrides: Sequence[str] = (), quick: bool = False
) -> Config:
    """Load a YAML config strictly, then apply ``key.sub=value`` overrides.

    Args:
        path: YAML file mirroring :class:`Config`; keys left out take the dataclass defaults.
        overrides: Hydra-style dotlist strings, applied in order after the file.
        quick: apply ``experiment.quick_overrides`` (before ``overrides``).

    Returns:
        The frozen :class:`Config`.

    Raises:
        ValueError: a missing file, an unknown key, a wrong type or a value out of range, in one
            line naming the dotted key.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"config file {str(path)!r} does not exist")
    try:
        data = OmegaConf.load(path)
    except Exception as e:  # yaml.YAMLError and friends
        raise ValueError(
            f"config file {str(path)!r} is not valid YAML: {_yaml_problem(e)}"
        ) from None
    if not isinstance(data, DictConfig):
        raise ValueError(f"config file {str(path)!r} must hold a mapping, got a list")
    node = _merge(_schema(), data, f"in {path}")
    cfg = _to_config(node, f"in {path}")
    if quick:
        node = _apply_overrides(node, cfg.experiment.quick_overrides)
    else:  # still validate the quick overrides, so a typo there fails now, not in CI later
        _to_config(_apply_overrides(node.copy(), cfg.experiment.quick_overrides), "quick_overrides")
    node = _apply_overrides(node, overrides)
    return _to_config(node, f"in {path} with overrides")


def _yaml_problem(e: BaseException) -> str:
    """``line L, column C: problem`` of a YAML syntax error (1-based), else its first line."""
    mark = getattr(e, "problem_mark", None) or getattr(e, "context_mark", None)
    problem = getattr(e, "problem", None) or getattr(e, "context", None)
    if mark is not None and problem:
        return f"line {mark.line + 1}, column {mark.column + 1}: {problem}"
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


def apply_overrides(cfg: Config, overrides: Sequence[str]) -> Config:
    """``cfg`` with Hydra-style ``key.sub=value`` overrides applied (same strict errors)."""
    node = _merge(_schema(), OmegaConf.structured(cfg), "config")
    return _to_config(_apply_overrides(node, overrides), "with overrides")


def config_to_dict(cfg: Config) -> dict[str, Any]:
    """Plain nested dict of str/int/float/bool/None/list (tuples become lists), e.g. for checkpoints."""

    def plain(x: Any) -> Any:
        if isinstance(x, Mapping):
            return {k: plain(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [plain(v) for v in x]
        return x

    return plain(OmegaConf.to_container(OmegaConf.structured(cfg), resolve=True))


def config_from_dict(d: Mapping[str, Any], source: str = "config dict") -> Config:
    """Strictly rebuild a :class:`Config` from :func:`config_to_dict` output (same errors as YAML)."""
    if not isinstance(d, Mapping):
        raise ValueError(f"config ({source}) must be a mapping, got {type(d).__name__}")
    try:
        data = OmegaConf.create(dict(d))
    except OmegaConfBaseException as e:
        raise ValueError(f"config ({source}) is not plain data: {str(e).splitlines()[0]}") from None
    return _to_config(_merge(_schema(), data, source), source)


def config_to_yaml(cfg: Config) -> str:
    """YAML text of ``cfg`` (every key), loadable by :func:`load_config`."""
    return OmegaConf.to_yaml(OmegaConf.create(config_to_dict(cfg)))


def save_config_yaml(cfg: Config, path: str | os.PathLike) -> None:
    """Write ``cfg`` as YAML atomically (see :func:`atomic_write`)."""
    text = config_to_yaml(cfg).encode()
    atomic_write(path, lambda f: f.write(text))


def atomic_write(path: str | os.PathLike, write: Callable[[BinaryIO], Any]) -> Path:
    """Call ``write(f)`` on a temporary file beside ``path``, fsync it, then rename it to ``path``.

    Readers see the old file or the new one, never a partial one; on any failure (exceptions and
    KeyboardInterrupt included) the temporary file is removed and ``path`` is untouched. The new
    file gets the usual permissions (0666 minus the umask). Parent folders are created.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        tmp = path.parent / f".{path.name}.{secrets.token_hex(6)}.tmp"
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            break
        except FileExistsError:  # pragma: no cover - 48 random bits
            continue
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    try:  # make the rename itself durable
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    except OSError:
        pass
    return path


# --------------------------------------------------------------------------------------------
# --help


def field_docs(cls: type) -> dict[str, str]:
    """The docstring below each field of a config dataclass, by field name."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = tree.body[0].body  # type: ignore[attr-defined]
    docs: dict[str, str] = {}
    for stmt, nxt in zip(body, body[1:]):
        if (
            isinstance(stmt, ast.AnnAssign)
            and isinstance(stmt.target, ast.Name)
            and isinstance(nxt, ast.Expr)
            and isinstance(nxt.value, ast.Constant)
            and isinstance(nxt.value.value, str)
        ):
            docs[stmt.target.id] = " ".join(nxt.value.value.split())
    return docs


def config_help(cls: type = Config, prefix: str = "") -> str:
    """``--help`` text: one line per dotted key with its type, default and docstring."""
    lines = []
    docs = field_docs(cls)
    hints = typing.get_type_hints(cls)
    default = cls()
    for f in dataclasses.fields(cls):
        t = hints[f.name]
        if dataclasses.is_dataclass(t):
            lines.append(f"{prefix}{f.name}: {docs.get(f.name, '')}")
            lines.append(config_help(t, f"{prefix}{f.name}."))
            continue
        value = getattr(default, f.name)
        shown = list(value) if isinstance(value, tuple) else value
        tname = t.__name__ if isinstance(t, type) else str(t).replace("typing.", "")
        lines.append(f"  {prefix}{f.name} ({tname}, default {shown!r}): {docs.get(f.name, '')}")
    return "\n".join(lines)
