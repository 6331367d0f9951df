"""The config schema: frozen dataclasses mirrored by ``configs/*.yaml`` (docs/design.md, Configs).

:class:`Config` is a whole experiment; its sections are :class:`EnvConfig` (a family's own keys,
its ``Family.config_class``, under ``env.<family>``: :func:`~taskvar_torch.config.loader
.config_schema`), :class:`HeadsConfig`, :class:`TrainConfig`,
:class:`CollectorConfig`, :class:`EvalConfig` and :class:`ExperimentConfig`. Every field carries
a docstring (the string literal right below it), the source of ``taskvar train --help``
(:mod:`taskvar_torch.config.help`). Building a :class:`Config` in any way runs the range and
choice checks of :mod:`taskvar_torch.config.validate`; files and overrides are loaded strictly by
:mod:`taskvar_torch.config.loader`.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field, fields
from typing import ClassVar

from taskvar_torch.config.validate import validate_config
from taskvar_torch.contract import family


@dataclass(frozen=True)
class EnvConfig:
    """The environment: what every family shares at this level; the family's own keys under
    ``env.<family>`` (``env.windy``, ``env.wargus``, ``env.taxi``), added by the loader for that
    family only (:func:`~taskvar_torch.config.loader.config_schema`)."""

    num_envs: int = 16
    """Number of environments simulated in parallel for training (the batch size N)."""
    instances: str = "train"
    """Training instance distribution: one of the family's named distributions (each registered
    family's: taskvar train --help)."""


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
    lr_end: float | None = None
    """Final Adam learning rate: linear decay from train.lr at lr_decay_start_frames to lr_end at
    total_frames (measured at 51x51 in docs/scale.md: it did not make every head's final greedy
    policy reliable); null: a constant lr."""
    lr_decay_start_frames: int = 0
    """Frames after which the learning rate starts decaying to lr_end (lr_end set only)."""
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
    option_coverage: float = 0.0
    """Least probability that the behaviour's option pick is uniform over the initiable options
    rather than mu_bar's (at least epsilon anyway), so every option runs its own trajectories."""
    replay_sampling: str = "uniform"
    """How a replay sample is drawn: ``uniform`` over the buffer, or ``per_option``: in equal shares
    from the transitions of each behaviour mode (the averaging policy's episodes, each option's;
    taskvar_torch/training/replay.py ``PerOptionSampler``)."""
    n_step: int = 1
    """Multi-step targets of the averaging and option heads: up to n rewards of the behaviour
    that ran that head (cut at the episode's end, the option's termination, a change of behaviour
    mode, the batch's end), then the bootstrap; 1: one-step targets (heads/nstep.py)."""
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
    mu_bar: str = "greedy"
    """mu_bar over Q_mu, the switching policy of the options and interruption controllers and the
    switching head's bootstrap: greedy or softmax. Changed at evaluation, it changes the
    controllers only."""
    mu_bar_temperature: float = 1.0
    """Softmax temperature of mu_bar (mu_bar='softmax'), in units of Q_mu."""
    robustness_gamma: float = 0.99
    """Discount of the robustness critics (any family whose options define a robustness reward;
    of the built-in ones, Wargus): 0.99 looks ~100 steps ahead, so on Wargus the root's R(TG+FE)
    reads survival and future sightings, not only whether the item is in sight now
    (heads/robustness.py "Scale")."""
    robustness_tau: float = 2.0
    """Robustness threshold tau of the hierarchy controller, in the robustness critics' units,
    when robustness_threshold='fixed' (the paper's 2, on Wargus), and the fallback of a calibration
    with no qualifying state. Read at evaluation: taskvar eval may change it."""
    robustness_threshold: str = "calibrated"
    """How the hierarchy controller's thresholds are set, in any family with a composition
    hierarchy: fixed (robustness_tau for every capability) or calibrated (per capability, on
    training states: a composed subtask keeps control on robustness_keep_share of the training
    states where its subgoals do not conflict, Subtasks.no_conflict; heads/robustness.py
    RobustnessCalibration). Never set on test seeds. Read at evaluation: taskvar eval may change
    it (the root's share per family: docs/evaluation.md)."""
    robustness_keep_share: float = 0.9
    """robustness_threshold='calibrated': share of no-conflict training states on which a composed
    subtask keeps control, in (0, 1). Read at evaluation."""
    robustness_until: str = "termination"
    """Horizon of the robustness critics (families with a robustness reward): termination (no
    bootstrap past the option's own termination beta_o or the episode's end) or episode
    (bootstrap through beta_o)."""
    robustness_target: str = "option"
    """Next action of the robustness critics' TD target (families with a robustness reward):
    option (pi^o(s'), R of following option o, paper §3.4.3) or greedy (argmax_a' R_o(s', a'),
    Q-learning on R)."""
    hierarchy_root_policy: str = "averaging"
    """Policy of a composition hierarchy's root (families with one), in the controllers and in
    the root's robustness target: averaging (the averaging head: paper §3.4.2, "the policy of
    this subtask is the full task averaging policy") or option (the root's own option head). The
    options and interruption controllers and the behaviour's option episodes use it too; no
    effect without a hierarchy. Changed at evaluation, it changes the controllers only (the root's
    critic was trained for the bundle's value)."""
    hierarchy_termination: bool = True
    """Hierarchy controller (any family with a composition hierarchy): honour the options'
    termination (a component whose beta holds hands control back up; the descent only picks
    components that can take control there). false: the paper's literal Algorithm 2."""
    hierarchy_descent: str = "normalised"
    """Hierarchy controller (any family with a composition hierarchy): metric of the descent to
    a component, raw (argmax R, the paper) or normalised ((R - tau) / scale per component, a
    common scale)."""
    max_grad_norm: float | None = 10.0
    """Gradient-norm clipping; null disables it."""
    seeds: int = 1
    """Independent training runs in one batched learner (``taskvar train --seeds N``): seeds
    ``seed, seed + 1, ..., seed + N - 1``, each with its own env instances, initial weights,
    replay, optimiser state and targets, written as ``seed<k>/`` bundles (docs/seeds.md)."""
    compile: bool = False
    """torch.compile the hot paths (taskvar_torch/compiling.py): the learner's losses, forward and
    backward of every head (the same losses up to float rounding), and in the wargus-fig4 learning
    loop the behaviour policy's choices and the Wargus dynamics step (the same bits). Cheaper
    trials after a compile of 20-30 s per process (docs/benchmarks.md); falls back to eager, with a
    warning, where compiling fails. On in ``configs/wargus.yaml`` (the Figure 4 protocol: 1.3x less
    CPU per trial), off in its ``--quick`` overrides and the other configs."""
    eval_ema_tau: float | None = None
    """Polyak averaging of the weights for evaluation: the learner keeps an exponential moving
    average of every head's weights (``ema <- ema + tau (online - ema)`` after each update) and
    the evaluation bundles (``heads.pt``, ``train.heads_every`` snapshots, what ``taskvar eval``
    and the experiments load from ``final.pt``) hold it; training acts and bootstraps with the
    online weights. null: off (the online weights are evaluated). Against the greedy-policy loops
    a single noisy weight snapshot can make (docs/scale.md)."""
    matmul_dtype: str = "float32"
    """Precision of the learner's network passes (float32 | bfloat16): bfloat16 runs the matmuls
    of every head's forward passes and their backward under ``torch.autocast`` (weights, optimiser
    and losses stay float32; the heads' values are cast back to float32 before any target or
    loss). Acting and evaluation always run float32. ~1.7x faster matmuls on a CPU with AVX-512
    BF16, 1.1-1.2x faster training (docs/benchmarks.md); changes what is learnt: at windy 51x51 the
    rounding is of the order of the near-ties that decide some heads (docs/scale.md)."""
    checkpoint_every: int = 50_000
    """Save a checkpoint every this many frames; 0: only the final one."""
    log_every: int = 5_000
    """Write a log row every this many frames."""
    logger: str = "csv"
    """Where log rows go besides the CSV files ``DIR/logs/scalars/<name>.csv`` (always written, one
    ``frame,value`` row each): csv (those only), tensorboard (also event files in
    ``DIR/logs/tensorboard``), wandb or mlflow (also a W&B run, an MLflow run in
    ``DIR/logs/mlruns``), through TorchRL's ``get_logger``; the last three need the pip extra of
    their name (``pip install 'taskvar-torch[tensorboard]'``)."""
    heads_every: int = 0
    """Save the heads alone (a small shareable bundle, ``heads/heads_<frames>.pt``, with the frames,
    updates and training seconds) every this many frames, for learning curves; 0: never."""
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
class BaselineConfig:
    """The baselines' own settings (``taskvar train-baselines``: recurrent, informed, blind;
    docs/memory.md). Every setting a baseline shares with the heads is read from ``heads`` and
    ``train``: the Q head's widths and activation, gamma, lr and its schedule, batch and buffer
    sizes, updates per batch, the target update, n-step targets (informed and blind), double Q,
    gradient clipping, the epsilon schedule, the frame budget and the evaluation weights
    (``train.eval_ema_tau``)."""

    hidden: int = 128
    """GRU hidden size of the recurrent Q-network."""
    slice_len: int = 16
    """Steps of each replay slice the recurrent loss is taken on (one sub-env's consecutive steps,
    within one episode)."""
    burn_in: int = 8
    """Steps before each slice that only warm the GRU up from the hidden state stored at
    collection (R2D2's burn-in); a slice that starts an episode needs none (its state is zero)."""
    recurrent_frames: int | None = None
    """The recurrent baseline's frame budget where it needs more than the heads' to deliver;
    null: train.total_frames, the heads' (an equal budget). Its epsilon decays over the same share
    of it as the heads' (train.eps_decay_frames scaled). A report labels a row whose budget differs
    from the heads' with its frames (docs/memory.md#budgets)."""
    informed_frames: int | None = None
    """The informed and blind baselines' frame budget (the same for both: blind is informed's
    control) where they need more than the heads' to converge; null: train.total_frames. Their
    epsilon decay and learning-rate decay start are scaled as recurrent_frames scales the
    recurrent one's; a row whose budget differs from the heads' is labelled with its frames."""
    informed_ema_tau: float | None = None
    """The informed and blind baselines' evaluation weights: a Polyak average of their online
    weights at this rate per update (null: train.eval_ema_tau, the heads'). A greedy policy read
    off one noisy iterate can bump a wall for ever where the action gap is about one step's cost
    (docs/memory.md#budgets)."""


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
    """The keys every config's ``experiment`` holds; the figure experiment of the config's family
    adds its own beside them (``Experiment.config_class``: windy Figure 2's, Wargus Figure 4's),
    read flat under ``experiment.*`` (:func:`experiment_class`)."""

    runs: int = 5
    """Independent repetitions (windy: test runs; Wargus: repetitions)."""
    quick_overrides: tuple[str, ...] = ()
    """key.sub=value overrides applied by load_config(..., quick=True) (smoke tests, notebooks)."""


def experiment_class(family_name: str) -> type[ExperimentConfig]:
    """The ``experiment`` section of a config of family ``family_name``: :class:`ExperimentConfig`,
    or, where the family's experiment declares its own keys (``Experiment.config_class``), its
    subclass with them too (``experiment.trials``), made once per class. Range checks of the own
    keys run in the config's validation, which names ``experiment.<key>``."""
    fam = family(family_name)  # an unknown family is a one-line error naming the known ones
    own = fam.experiment.config_class if fam.experiment is not None else None
    return ExperimentConfig if own is None else _with_own_keys(own)


@functools.cache
def _with_own_keys(own: type) -> type[ExperimentConfig]:
    shared = {f.name for f in fields(ExperimentConfig)} & {f.name for f in fields(own)}
    if shared:
        raise ValueError(f"{own.__name__} redeclares the shared experiment keys {sorted(shared)}")
    return dataclasses.make_dataclass(
        own.__name__,
        [],
        bases=(own, ExperimentConfig),
        frozen=True,
        namespace={
            "__module__": __name__,
            "__post_init__": lambda self: None,  # checked by validate_config, naming the key
            "__reduce__": lambda self: (_experiment_of, (own, dataclasses.asdict(self))),
        },
    )


def _experiment_of(own: type, values: dict) -> ExperimentConfig:
    """Unpickle an experiment section with own keys (its class is made at run time)."""
    return _with_own_keys(own)(**values)


@dataclass(frozen=True)
class Config:
    """A whole experiment: family, seed, device, environment, heads, training, evaluation."""

    override_example: ClassVar[str] = "train.lr=0.01"
    """An override shown in the error for a malformed one (a class constant, not a config key)."""
    family: str = "windy"
    """MDP family: a registered family's name, built in or from an installed package (the
    registered ones: taskvar train --help)."""
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
    baseline: BaselineConfig = field(default_factory=BaselineConfig)
    """The recurrent baseline's own settings (the rest are the heads' and train's)."""

    def __post_init__(self):
        """Give ``experiment`` its family's own keys where it was built without them
        (``Config(family="wargus")``: the defaults, the shared keys kept), then run the range and
        choice checks. A loaded config's family does not change by ``dataclasses.replace`` (its
        sections are the old family's): a one-line ``ValueError`` naming ``apply_overrides``."""
        was = getattr(type(self), "_schema_family", None)  # a loaded config's own family
        if was is not None and was != self.family:
            raise ValueError(
                f"family: a {was} config does not become a {self.family} one by "
                f"dataclasses.replace; use apply_overrides(cfg, ['family={self.family}', ...]) "
                "or load_config"
            )
        section = experiment_class(self.family)
        if type(self.experiment) is not section:
            kept = {f.name: getattr(self.experiment, f.name) for f in fields(self.experiment)}
            own = {f.name for f in fields(section)}
            kept = {k: v for k, v in kept.items() if k in own}
            object.__setattr__(self, "experiment", section(**kept))
        validate_config(self)
