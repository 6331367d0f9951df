"""Wargus Figure 4: the lifelong protocol (paper §3.5.1-3.5.3; docs/wargus-fig4.md).

The protocol, top to bottom (:func:`wargus_fig4`), for each of R repetitions (own seed
``cfg.seed + rep``, own env streams, own replay and exploration generators, networks initialised
from its own seed; never one RNG shared between repetitions):

1. the agent starts with *no prior knowledge*: fresh networks for every head (averaging, options,
   mu_bar, max-value, robustness), an empty replay buffer, epsilon = 1;
2. for each of T trials:

   a. **learning** (learning on): ``L = experiment.learning_episodes_per_trial`` (30) episodes of
      the training instance distribution, played as L parallel sub-environments of one batched
      ``WargusEnv`` by the behaviour policy (``heads/behaviour.py``, epsilon from the trainer's
      schedule over the frames played so far); every transition of a live episode goes to the
      replay buffer (first visits only with ``train.first_visit``), and every
      ``train.frames_per_batch`` frames played trigger ``train.updates_per_batch`` gradient steps
      of the one multi-head learner (after ``train.init_random_frames``), which trains *every* head
      from the same stream;
   b. **test** (learning off): ``K = experiment.test_episodes_per_trial`` (5) nominal episodes
      (fixed instance seeds :data:`~taskvar_torch.families.wargus.dynamics.NOMINAL_SEEDS`) with each method --
      averaging (greedy Q_avg), options (mu_bar + option policies run to termination),
      interruption (Algorithm 1, max-value heads) and hierarchy (Algorithm 2, robustness critics,
      ``tau = train.robustness_tau``) -- all 4 x K episodes side by side in one batched env;
      score = items collected per test episode;
   c. **held-out test**, beside the nominal one: the same K x 4 episodes on the sealed held-out
      instance seeds (:data:`~taskvar_torch.families.HELDOUT_SEEDS`, K fresh ones per trial,
      cycled; :func:`make_heldout_test_env`), the same heads and calibration. Test episodes draw
      nothing from the global stream, so the nominal scores are those of a run without it.

The repetitions' per-trial test scores then go to the metrics
(:mod:`taskvar_torch.families.wargus.fig4_metrics`: ``metrics.json``'s final scores, trials to 90% and
the hierarchy's control split, with their definitions) and to the report
(:mod:`taskvar_torch.families.wargus.fig4_report`: ``per_trial.csv``, the table, ``fig4.png``): this
module is the protocol, and re-exports the public names of those two, of
:mod:`taskvar_torch.families.wargus.fig4_trial`, :mod:`taskvar_torch.controllers.side_by_side` and
:mod:`taskvar_torch.heads.snapshots`.

Repetitions run **batched** (:func:`run_repetitions_batched`): one loop steps every repetition's
learning episodes at once (one env, one behaviour pass over their heads stacked), while each keeps
its own learner, replay, generators and test phases, so each repetition gives the numbers it gives
alone (tested bit for bit). ``workers = W`` splits them into ``W`` batches in spawned processes
(:func:`repetition_batches`); any split gives the same numbers (each repetition depends on its own
seed only).

One trial's loops (the agent's state and update rule, :func:`learning_phase`, :func:`test_phase`,
:func:`test_trials` and their TorchRL references) are :mod:`taskvar_torch.families.wargus.fig4_trial`,
also re-exported here; it describes how they are made fast (docs/benchmarks.md). Here
:func:`run_repetition` tests :data:`TEST_GROUP` trials side by side on frozen copies of their
heads.

Writes ``config.yaml``, ``rep{r}/final.pt`` (every head, loadable by ``taskvar eval``),
``per_trial.csv`` (rep, trial, method, items, interruptions), ``per_trial_heldout.csv`` (the same
on the held-out instances), ``metrics.json`` (the held-out figures under ``heldout``),
``fig4.png``; prints a table. With ``experiment.baselines`` (``[recurrent]``), after the paper's
agents, each baseline's agents run the same protocol (:mod:`~taskvar_torch.families.wargus.fig4_recurrent`):
their curves join ``metrics.json`` and ``fig4.png`` beside the paper's methods, their test scores
go to ``per_trial_baselines.csv`` and each repetition's network to ``rep{r}/recurrent.pt``.

Examples:
    >>> cfg = load_config(default_config_path(), quick=True)  # doctest: +SKIP
    >>> metrics = wargus_fig4(cfg, "results/wargus-fig4-quick")  # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.multiprocessing as mp
from torchrl.envs import TransformedEnv

from taskvar_torch import keys
from taskvar_torch.checkpoint import make_bundle, rng_state, save_checkpoint
from taskvar_torch.config import Config, save_config_yaml
from taskvar_torch.controllers import Controller
from taskvar_torch.controllers.side_by_side import SideBySide
from taskvar_torch.experiments.curves import (
    trials_to_fraction_of_max,
)
from taskvar_torch.experiments.evaluation import run_episodes  # noqa: F401  (read from here)
from taskvar_torch.experiments.results import refuse_existing_results, write_csv, write_json
from taskvar_torch.factory import (
    build_heads,
    calibrate,
    make_env,
    make_learner,
    make_method_controller,
    make_subtasks,
    replay_states,
)
from taskvar_torch.families import FAMILIES, HELDOUT_SEEDS
from taskvar_torch.families.wargus.dynamics import WargusInstances
from taskvar_torch.families.wargus.env import WargusEnv
from taskvar_torch.families.wargus.family import section
from taskvar_torch.families.wargus.fig4_metrics import (
    EXPERIMENT,
    METHODS,
    mean_over_trials,
    method_summary,
    summarise,
)
from taskvar_torch.families.wargus.fig4_recurrent import PHASES as RECURRENT_PHASES
from taskvar_torch.families.wargus.fig4_recurrent import run_recurrent_batch
from taskvar_torch.families.wargus.fig4_report import (
    CSV_FIELDS,
    STYLES,
    csv_rows,
    format_table,
    is_results_folder,
    plot_results,
)
from taskvar_torch.families.wargus.fig4_trial import (
    LifelongAgent,
    learn_due,
    learning_phase,
    learning_phase_torchrl,
    learning_phases,
    nominal_seeds,
    repetition_seed,
    test_phase,
    test_phase_torchrl,
    test_trials,
    trial_seeds,
)
from taskvar_torch.heads.behaviour import BehaviourPolicy
from taskvar_torch.heads.first_visit import FirstVisitFilter
from taskvar_torch.heads.robustness import RobustnessCalibration
from taskvar_torch.heads.seeds import load_seed, stack_seeds
from taskvar_torch.heads.snapshots import HeadValues
from taskvar_torch.progress import progress_bar
from taskvar_torch.replay import make_replay_buffer
from taskvar_torch.run_folder import ResultsFolder

EXPLORATION_OFFSET = 1 << 32
"""A repetition's exploration generator is seeded ``seed + EXPLORATION_OFFSET``."""
TEST_GROUP = 25  # trials whose test phases run side by side (run_repetition)
HELDOUT_CSV = "per_trial_heldout.csv"
"""The held-out test phases' rows (``per_trial.csv``'s columns)."""
BASELINES_CSV = "per_trial_baselines.csv"
"""The baselines' test phases (``experiment.baselines``): rep, trial, method, nominal items and
held-out items per test episode."""
BASELINES_CSV_FIELDS = ("rep", "trial", "method", "items", "heldout_items")
HELDOUT_KEYS = ("items", "interruptions", "control_steps", "item_lost")
"""What a held-out test phase records per trial (``run_repetition``'s ``heldout_*``)."""
PHASES = ("learning_loop", "updates", "calibration", "test")
"""Where a repetition's CPU time goes (``metrics.json`` ``timing.cpu_seconds_per_trial``): the
learning phases' loop (behaviour, dynamics, replay writes), the gradient updates (replay samples
included), the hierarchy's calibration and the heads' snapshot after each trial, the test phases
(compiles, with ``train.compile``, fall in the phase that first runs the compiled code)."""


def default_config_path() -> Path:
    """``configs/wargus.yaml`` of the repository (or of the working directory)."""
    here = Path(__file__).resolve().parents[3] / "configs" / "wargus.yaml"
    return here if here.is_file() else Path("configs") / "wargus.yaml"


# --------------------------------------------------------------------------------------------
# a fresh agent (paper §3.5.1: no prior knowledge), its test env and test controllers


def exploration_generator(seed: int) -> torch.Generator:
    """The behaviour's own random stream of the repetition seeded ``seed`` (option picks,
    exploration, option episodes, epsilon-greedy actions): ``seed + EXPLORATION_OFFSET``, apart
    from every replay generator (``seed + 1``)."""
    return torch.Generator(device="cpu").manual_seed(int(seed) + EXPLORATION_OFFSET)


def make_behaviour(
    cfg: Config, heads: Any, subtasks: Any, action_spec: Any, generators: list[torch.Generator]
) -> BehaviourPolicy:
    """The behaviour policy of ``heads`` (one repetition's, or several stacked), drawing block
    ``s`` of its rows from ``generators[s]``."""
    return BehaviourPolicy(
        heads,
        subtasks,
        action_spec,
        option_prob=cfg.train.option_behaviour_prob,
        root_policy=cfg.train.hierarchy_root_policy,
        compile=cfg.train.compile,
        generators=generators,
    )


def make_agent(cfg: Config, env: WargusEnv | TransformedEnv, seed: int) -> LifelongAgent:
    """Fresh heads, learner, behaviour policy and an empty replay buffer (seeded by ``seed``:
    the networks' initialisation from the global stream, the replay sampler and the behaviour
    from their own generators)."""
    subtasks = make_subtasks(cfg, getattr(env, "base_env", env))
    heads = build_heads(cfg, env, subtasks)
    learner = make_learner(cfg, heads, subtasks)
    explore = exploration_generator(seed)
    behaviour = make_behaviour(cfg, heads, subtasks, env.action_spec, [explore])
    generator = torch.Generator(device="cpu").manual_seed(seed + 1)
    obs_dim = env.observation_spec[keys.OBSERVATION].shape[-1]
    return LifelongAgent(
        cfg=cfg,
        heads=heads,
        subtasks=subtasks,
        learner=learner,
        behaviour=behaviour,
        buffer=make_replay_buffer(cfg, generator),
        replay_generator=generator,
        first_visit=FirstVisitFilter(env.batch_size.numel(), obs_dim, device=cfg.device),
        explore_generator=explore,
    )


def make_test_env(
    cfg: Config, k: int, seed: int, first_trial: int = 0, trials: int = 1
) -> WargusEnv:
    """The test env of ``trials`` trials from ``first_trial`` on: rows ``(g, method, j)``, where
    episode ``j`` of trial ``t`` plays nominal seed ``(j + t) % k``, so every method plays all
    ``k`` seeds every trial. With ``trials = 1`` the env can be reused: its next reset is the next
    trial (the seeds cycle)."""
    rows = tuple(
        s for g in range(trials) for _ in METHODS for s in trial_seeds(k, first_trial + g)[0]
    )
    return make_env(
        cfg, len(rows), seed=seed, instances=WargusInstances(seeds=rows), validate_actions=False
    )


def make_heldout_test_env(
    cfg: Config, k: int, seed: int, first_trial: int = 0, trials: int = 1
) -> WargusEnv:
    """:func:`make_test_env` on the sealed held-out instances: episode ``j`` of trial ``t`` plays
    ``HELDOUT_SEEDS[(t k + j) % len(HELDOUT_SEEDS)]``, the same seed for every method (paired), so
    the trials walk through every held-out instance in turn."""
    rows = tuple(
        s for g in range(trials) for _ in METHODS for s in trial_seeds(k, first_trial + g)[1]
    )
    return make_env(
        cfg, len(rows), seed=seed, instances=WargusInstances(seeds=rows), validate_actions=False
    )


def make_test_controllers(agent: LifelongAgent) -> list[Controller]:
    """The four methods on the agent's live heads (paper §3.5.2), in :data:`METHODS` order. The
    hierarchy's calibration (``train.robustness_threshold = "calibrated"``) is set per trial from
    the replay (:func:`trial_calibration`)."""
    cal = None
    if agent.cfg.train.robustness_threshold == "calibrated":  # placeholder until the first trial
        O = agent.subtasks.num_options  # noqa: E741
        cal = RobustnessCalibration(
            torch.full((O,), agent.cfg.train.robustness_tau), torch.ones(O)
        ).to(agent.cfg.device)
    return [
        make_method_controller(agent.cfg, m, agent.heads, agent.subtasks, calibration=cal)
        for m in METHODS
    ]


def trial_calibration(agent: LifelongAgent) -> RobustnessCalibration | None:
    """The hierarchy's thresholds after a trial, on training states of the replay (never the
    nominal test seeds); ``None`` with ``train.robustness_threshold = "fixed"``."""
    if agent.cfg.train.robustness_threshold != "calibrated" or len(agent.buffer) == 0:
        return None
    return calibrate(agent.cfg, agent.heads, agent.subtasks, replay_states(agent.buffer))


# --------------------------------------------------------------------------------------------
# one repetition


@dataclasses.dataclass
class _Repetition:
    """One repetition's protocol state around its agent: its test policy, the rows recorded so
    far, the frozen heads and calibrations of trials not tested yet, CPU seconds per phase."""

    rep: int
    seed: int
    agent: LifelongAgent
    learn_env: WargusEnv
    policy: SideBySide
    group: int
    rows: dict[str, list]
    updates: list[int] = dataclasses.field(default_factory=list)
    snapshots: list[list[torch.Tensor]] = dataclasses.field(default_factory=list)
    calibrations: list[RobustnessCalibration | None] = dataclasses.field(default_factory=list)
    cpu: dict[str, float] = dataclasses.field(default_factory=lambda: dict.fromkeys(PHASES, 0.0))


def _start_repetition(cfg: Config, rep: int, test_group: int) -> _Repetition:
    """A fresh agent (paper §3.5.1), its learning env and test policy; draws the networks'
    initialisation from the global stream seeded :func:`repetition_seed` (the caller's
    ``fork_rng`` scope)."""
    x = cfg.experiment
    seed = repetition_seed(cfg, rep)
    rep_cfg = dataclasses.replace(cfg, seed=seed)
    torch.manual_seed(seed)
    learn_env = make_env(rep_cfg, num_envs=x.learning_episodes_per_trial, seed=seed)
    learn_env.validate_actions = False  # the behaviour's actions are in range by construction
    if cfg.train.compile:  # the learning loop's dynamics too (the learner: make_agent)
        learn_env.compile_dynamics()
    agent = make_agent(rep_cfg, learn_env, seed)
    policy = SideBySide(make_test_controllers(agent), x.test_episodes_per_trial)
    keys_ = ("items", "interruptions", "control_steps", "item_lost", "learn_items", "frames")
    rows = {k: [] for k in (*keys_, *(f"heldout_{k}" for k in HELDOUT_KEYS))}
    group = test_group if policy.batchable else 1
    return _Repetition(rep, seed, agent, learn_env, policy, group, rows)


def _test_env(
    make: Callable[..., WargusEnv], cfg: Config, runs: Sequence[_Repetition], first: int, G: int
) -> WargusEnv:
    """``make`` (:func:`make_test_env` or :func:`make_heldout_test_env`) of ``G`` trials from
    ``first`` for every repetition of ``runs`` at once: their rows in seed-major blocks, block
    ``s`` drawing what repetition ``s``'s own test env draws (:meth:`WargusEnv.set_seed_blocks`)."""
    k = cfg.experiment.test_episodes_per_trial
    if len(runs) == 1:
        return make(cfg, k, runs[0].seed, first_trial=first, trials=G)
    one = make(cfg, k, runs[0].seed, first_trial=first, trials=G)
    rows = one.instances.seeds * len(runs)
    env = make_env(
        cfg,
        len(rows),
        seed=runs[0].seed,
        instances=WargusInstances(seeds=rows),
        validate_actions=False,
    )
    env.set_seed_blocks([r.seed for r in runs])
    return env


def _test_pending(cfg: Config, runs: Sequence[_Repetition]) -> None:
    """The nominal and held-out test phases of the trials not tested yet, of every repetition of
    ``runs`` (each with the same number pending) side by side in one batch: repetition ``s``'s
    frozen heads and calibrations on its own block of rows (:func:`_test_env`), so each gets the
    episodes it gets alone. Without snapshots (``group = 1``: the live heads) one at a time."""
    tick = time.process_time()
    k = cfg.experiment.test_episodes_per_trial
    if runs[0].group == 1 and len(runs) > 1:
        for r in runs:
            _test_pending(cfg, [r])
        return
    G = len(runs[0].snapshots)
    policy = runs[0].policy
    snaps = [snap for r in runs for snap in r.snapshots] if runs[0].group > 1 else None
    cals = [c for r in runs for c in r.calibrations]
    if runs[0].group == 1 and cals[0] is not None:
        policy.controllers[METHODS.index("hierarchy")].calibration = cals[0]
    first = len(runs[0].rows["items"])
    env = _test_env(make_test_env, cfg, runs, first, G)
    tested = test_trials(policy, env, k, snaps, cals)
    for i, r in enumerate(runs):
        for one in tested[i * G : (i + 1) * G]:
            for key, v in one.items():
                r.rows[key].append(v)
    first = len(runs[0].rows["heldout_items"])
    env = _test_env(make_heldout_test_env, cfg, runs, first, G)
    tested = test_trials(policy, env, k, snaps, cals)
    for i, r in enumerate(runs):
        for one in tested[i * G : (i + 1) * G]:
            for key in HELDOUT_KEYS:
                r.rows[f"heldout_{key}"].append(one[key])
        r.snapshots.clear()
        r.calibrations.clear()
    spent = (time.process_time() - tick) / len(runs)
    for r in runs:
        r.cpu["test"] += spent


def _end_trial(cfg: Config, r: _Repetition, learned: dict[str, float]) -> None:
    """Record a learning phase, freeze the heads and calibrate."""
    for key, v in learned.items():
        r.rows[key].append(v)
    r.updates.append(r.agent.updates)
    tick = time.process_time()
    r.snapshots.append(r.policy.head_values.snapshot() if r.group > 1 else [])
    r.calibrations.append(trial_calibration(r.agent))
    r.cpu["calibration"] += time.process_time() - tick


def _finish(cfg: Config, r: _Repetition, out_dir: str | os.PathLike) -> dict[str, Any]:
    """Save ``rep{rep}/final.pt``, return the repetition's result (every trial tested)."""
    r.rows["updates"] = r.updates
    agent = r.agent
    save_checkpoint(
        Path(out_dir) / f"rep{r.rep}" / "final.pt",
        make_bundle(
            agent.cfg,
            models={"heads": agent.heads, "targets": agent.learner.loss.target_heads},
            optimizers={"adam": agent.learner.optimizer},
            counters={
                "frames": agent.frames,
                "updates": agent.updates,
                "trials": cfg.experiment.trials,
            },
            rng=rng_state({"replay": agent.replay_generator, "explore": agent.explore_generator}),
            heads_spec=agent.heads.spec.to_dict(),
        ),
    )
    result = {key: np.asarray(v) for key, v in r.rows.items()}
    result["option_names"] = list(agent.heads.option_names)
    result["option_depths"] = hierarchy_depths(agent.subtasks.hierarchy, agent.heads.option_names)
    result["cpu_seconds"] = r.cpu
    return result


def run_repetitions_batched(
    cfg: Config,
    reps: Sequence[int],
    out_dir: str | os.PathLike,
    on_trial: Callable[[int, int], None] | None = None,
    test_group: int = TEST_GROUP,
) -> list[dict[str, Any]]:
    """Repetitions ``reps`` of the lifelong protocol (module docstring) in one batched loop;
    saves each ``rep{rep}/final.pt``.

    Each repetition keeps its own agent (heads, learner, replay buffer and generator, exploration
    generator, counters), its own test policy and test phases; their learning phases run as one
    loop (:func:`learning_phases`): one env of ``len(reps) x L`` sub-environments in seed-major
    blocks, one behaviour pass over the repetitions' heads stacked (heads/seeds.py), each block at
    its own epsilon and drawing from its own repetition's generators, each repetition updating on
    its own schedule, after which its new weights are copied into the acting stack. Every
    repetition's numbers are therefore those it gives alone (tested equal), whatever it shares a
    batch with; only the per-step work is shared.

    The test phases of ``test_group`` consecutive trials run side by side after their learning
    phases, each with a frozen copy of the heads taken at the end of its trial
    (:func:`test_trials`): the same episodes as testing each trial at once (``test_group = 1``).

    Runs inside :func:`torch.random.fork_rng`, repetition ``r``'s networks initialised from the
    global stream seeded :func:`repetition_seed`, so the caller's stream is left untouched.

    Returns, per repetition:
        ``items``, ``interruptions`` and ``item_lost`` ``(T, M)``, ``control_steps`` ``(T, O)``,
        ``learn_items``, ``frames``, ``updates`` ``(T,)``, ``option_names``, ``seconds`` (the
        batch's wall) and ``cpu_seconds``: CPU seconds per phase (:data:`PHASES`; the shared
        learning loop split evenly between the repetitions).
    """
    start = time.perf_counter()
    S = len(reps)
    with torch.random.fork_rng(devices=[]):
        runs = [_start_repetition(cfg, rep, test_group) for rep in reps]
        agents = [r.agent for r in runs]
        if S == 1:
            env, behaviour, first_visit, on_update = (
                runs[0].learn_env,
                agents[0].behaviour,
                agents[0].first_visit,
                None,
            )
        else:
            env = make_env(cfg, num_envs=S * cfg.experiment.learning_episodes_per_trial)
            env.set_seed_blocks([r.seed for r in runs])
            env.validate_actions = False
            if cfg.train.compile:
                env.compile_dynamics()
            acting = stack_seeds([a.heads for a in agents])
            generators = [a.explore_generator for a in agents]
            behaviour = make_behaviour(cfg, acting, agents[0].subtasks, env.action_spec, generators)
            obs_dim = env.observation_spec[keys.OBSERVATION].shape[-1]
            first_visit = FirstVisitFilter(env.num_envs, obs_dim, device=cfg.device)

            def on_update(s: int) -> None:  # repetition s learnt: the acting stack follows
                load_seed(acting, s, agents[s].heads)

        for trial in range(cfg.experiment.trials):
            tick, before = time.process_time(), [a.update_seconds for a in agents]
            learned = learning_phases(agents, env, behaviour, first_visit, on_update)
            spent = [a.update_seconds - b for a, b in zip(agents, before)]
            loop = (time.process_time() - tick - sum(spent)) / S
            for r, u, one in zip(runs, spent, learned):
                r.cpu["updates"] += u
                r.cpu["learning_loop"] += loop
                _end_trial(cfg, r, one)
            if len(runs[0].snapshots) >= runs[0].group:
                _test_pending(cfg, runs)
            for r in runs:
                if on_trial is not None:
                    on_trial(r.rep, trial)
        if runs[0].snapshots:
            _test_pending(cfg, runs)
        results = [_finish(cfg, r, out_dir) for r in runs]
    for result in results:
        result["seconds"] = time.perf_counter() - start
    return results


def run_repetition(
    cfg: Config,
    rep: int,
    out_dir: str | os.PathLike,
    on_trial: Callable[[int, int], None] | None = None,
    test_group: int = TEST_GROUP,
) -> dict[str, Any]:
    """Repetition ``rep`` of the lifelong protocol alone: :func:`run_repetitions_batched` of one
    (module docstring; saves ``rep{rep}/final.pt``)."""
    return run_repetitions_batched(cfg, [rep], out_dir, on_trial, test_group)[0]


def _add_baseline(
    metrics: dict[str, Any], name: str, results: Sequence[dict[str, Any]], seconds: float
) -> None:
    """A baseline's curves (``experiment.baselines``) into ``metrics``: its entry beside the
    paper's methods, nominal (``methods``) and held-out (``heldout.methods``), and its cost
    (``timing.baselines``)."""
    items = np.stack([r["items"] for r in results])  # (R, T)
    held = np.stack([r["heldout_items"] for r in results])
    metrics["methods"][name] = method_summary(items)
    metrics["heldout"]["methods"][name] = {**method_summary(held), **heldout_extras(held)}
    n = max(items.size, 1)
    metrics["timing"].setdefault("baselines", {})[name] = {
        "wall_seconds": seconds,
        "frames_per_repetition": [int(r["frames"].sum()) for r in results],
        "updates_per_repetition": [int(r["updates"][-1]) for r in results],
        "cpu_seconds_per_trial": {
            phase: sum(r["cpu_seconds"][phase] for r in results) / n for phase in RECURRENT_PHASES
        },
    }


def heldout_extras(items: np.ndarray) -> dict[str, Any]:
    """What a held-out method entry adds to :func:`method_summary` for the claims (``taskvar
    report``), from ``items`` ``(R, T)``: the mean over the first half of the trials and each
    repetition's trials to 90% of its own maximum."""
    items = np.asarray(items, dtype=float)
    return {
        "mean_first_half": mean_over_trials(items, max(items.shape[1] // 2, 1)),
        "trials_to_90pct_of_max_per_rep": [trials_to_fraction_of_max(c) for c in items],
    }


def heldout_summary(held: dict[str, np.ndarray], first: dict[str, Any]) -> dict[str, Any]:
    """``metrics.json``'s ``heldout``: :func:`summarise` of the held-out test phases (the same
    keys as the nominal figures at the top level), and which instances they played."""
    m = summarise(
        held["items"],
        held["interruptions"],
        held["control_steps"],
        first["option_names"],
        first["option_depths"],
        held["item_lost"],
    )
    m.pop("experiment")
    m["definitions"]["score"] = "items collected per held-out test episode"
    for i, name in enumerate(METHODS):  # the claims' figures (taskvar report), per repetition
        m["methods"][name].update(heldout_extras(held["items"][:, :, i]))
    m["definitions"]["mean_first_half"] = "mean_over_trials over trials 1..T/2"
    m["definitions"]["trials_to_90pct_of_max_per_rep"] = (
        "trials_to_90pct_of_max of each repetition's own curve"
    )
    m["instances"] = {
        "first_seed": HELDOUT_SEEDS[0],
        "count": len(HELDOUT_SEEDS),
        "order": "trial t, episode j plays seed (t K + j) mod count (every method the same)",
    }
    return m


def hierarchy_depths(hierarchy: Any, option_names: Sequence[str]) -> list[int]:
    """Depth of each option in the composition tree (0: the root; -1: outside the tree)."""
    depth, stack = {hierarchy.root: 0}, [hierarchy.root]
    while stack:
        o = stack.pop()
        for c in hierarchy.children.get(o, ()):
            depth[c] = depth[o] + 1
            stack.append(c)
    return [depth.get(o, -1) for o in option_names]


def repetition_batches(reps: int, workers: int) -> list[list[int]]:
    """The repetitions ``0 .. reps - 1`` in ``min(workers, reps)`` contiguous batches of sizes
    differing by at most one (each batch one process, one batched loop)."""
    w = max(1, min(workers, reps))
    size, extra = divmod(reps, w)
    out, first = [], 0
    for i in range(w):
        n = size + (1 if i < extra else 0)
        out.append(list(range(first, first + n)))
        first += n
    return out


RunBatch = Callable[..., list[dict[str, Any]]]
"""``(cfg, reps, out_dir, on_trial) -> results``: :func:`run_repetitions_batched`, or a baseline's
(``fig4_recurrent.run_recurrent_batch``)."""


def _worker(
    cfg: Config, reps: list[int], out_dir: str, threads: int, queue: Any, run_batch: RunBatch
) -> None:
    """Process entry: one batch of repetitions, progress and results through ``queue``."""
    torch.set_num_threads(threads)
    try:
        done = run_batch(cfg, reps, out_dir, lambda r, t: queue.put(("trial", r, None)))
        for rep, result in zip(reps, done):
            queue.put(("done", rep, result))
    except BaseException as e:  # report, so the parent does not wait forever
        queue.put(("error", reps[0], f"{type(e).__name__}: {e}"))


def run_repetitions(
    cfg: Config,
    out_dir: str | os.PathLike,
    workers: int = 1,
    progress: bool = True,
    run_batch: RunBatch = run_repetitions_batched,
    desc: str = EXPERIMENT,
) -> list[dict[str, Any]]:
    """Every repetition, batched (``run_batch``: :func:`run_repetitions_batched`, or a baseline's
    agents): in this process (``workers = 1``: one batch of all of them) or as ``workers``
    batches in spawned processes (:func:`repetition_batches`). Each repetition gives the same
    numbers either way."""
    reps = cfg.experiment.runs
    bar = progress_bar(
        total=reps * cfg.experiment.trials, disable=not progress, desc=desc, unit="trial"
    )
    results: dict[int, dict[str, Any]] = {}
    batches = repetition_batches(reps, workers)
    if len(batches) == 1:
        done = run_batch(cfg, batches[0], out_dir, lambda r, t: bar.update(1))
        results = dict(zip(batches[0], done))
    else:
        ctx = mp.get_context("spawn")
        queue = ctx.Queue()
        threads = max(1, torch.get_num_threads() // len(batches))
        procs = [
            ctx.Process(
                target=_worker,
                args=(cfg, b, str(out_dir), threads, queue, run_batch),
                daemon=True,
            )
            for b in batches
        ]
        try:
            for proc in procs:
                proc.start()
            while len(results) < reps:
                kind, rep, payload = queue.get()
                if kind == "trial":
                    bar.update(1)
                elif kind == "error":
                    raise RuntimeError(f"repetition {rep} failed: {payload}")
                else:
                    results[rep] = payload
            for proc in procs:
                proc.join()
        finally:  # an error or Ctrl-C here stops the other batches too
            for proc in procs:
                if proc.is_alive():
                    proc.terminate()
    bar.close()
    return [results[r] for r in range(reps)]


# --------------------------------------------------------------------------------------------
# the experiment


def wargus_fig4(
    cfg: Config,
    out_dir: str | os.PathLike,
    workers: int = 1,
    progress: bool = True,
    plots: bool = True,
    overwrite: bool = False,
    staged: bool = True,
) -> dict[str, Any]:
    """Run the lifelong protocol (module docstring), write the results folder, print the table.

    ``workers`` processes run the repetitions; ``plots=False`` skips ``fig4.png`` (``taskvar plot
    DIR`` draws it later from the folder); ``overwrite`` replaces results already in ``out_dir``
    (without it such a folder is refused). ``out_dir`` is written like every results folder
    (:class:`~taskvar_torch.run_folder.ResultsFolder`: locked, filled in a staging folder and
    swapped in whole); ``staged=False`` writes into it directly (a sweep's point: the sweep holds
    its folder).
    """
    FAMILIES["wargus"].require(cfg, "wargus-fig4")
    if cfg.train.eval_ema_tau is not None:
        raise ValueError(
            f"train.eval_ema_tau={cfg.train.eval_ema_tau}: wargus-fig4 tests the live heads after "
            "every trial (paper §3.5.1), it has no averaged weights to test; set it to null"
        )
    if cfg.heads.informed:
        raise ValueError(
            "heads.informed=true: wargus-fig4 runs the paper's lifelong agents (its baselines are "
            "experiment.baselines' curves); set heads.informed=false"
        )
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if not staged:
        out = Path(out_dir)
        refuse_existing_results(out, overwrite, "taskvar experiment wargus-fig4")
        out.mkdir(parents=True, exist_ok=True)
        return _wargus_fig4(cfg, out, workers, progress, plots)
    folder = ResultsFolder(out_dir, overwrite, "taskvar experiment wargus-fig4")
    folder.check()
    with folder as staging:
        return _wargus_fig4(cfg, staging, workers, progress, plots)


def _wargus_fig4(
    cfg: Config, out: Path, workers: int, progress: bool, plots: bool
) -> dict[str, Any]:
    """:func:`wargus_fig4` writing into the folder ``out``."""
    save_config_yaml(cfg, out / "config.yaml")

    start = time.perf_counter()
    results = run_repetitions(cfg, out, workers=workers, progress=progress)
    wall = time.perf_counter() - start
    baselines = {}  # the baselines' agents after the paper's (their own streams: fig4_recurrent)
    for name in cfg.experiment.baselines:
        tick = time.perf_counter()
        run_batch = {"recurrent": run_recurrent_batch}[name]
        done = run_repetitions(cfg, out, workers, progress, run_batch=run_batch, desc=name)
        baselines[name] = (done, time.perf_counter() - tick)

    items = np.stack([r["items"] for r in results])  # (R, T, M)
    inter = np.stack([r["interruptions"] for r in results])  # (R, T, M)
    control = np.stack([r["control_steps"] for r in results])  # (R, T, O)
    lost = np.stack([r["item_lost"] for r in results])  # (R, T, M)
    write_csv(out / "per_trial.csv", csv_rows(items, inter), CSV_FIELDS)
    metrics = summarise(
        items, inter, control, results[0]["option_names"], results[0]["option_depths"], lost
    )
    held = {k: np.stack([r[f"heldout_{k}"] for r in results]) for k in HELDOUT_KEYS}
    write_csv(out / HELDOUT_CSV, csv_rows(held["items"], held["interruptions"]), CSV_FIELDS)
    metrics["heldout"] = heldout_summary(held, results[0])
    metrics["protocol"] = {
        "repetitions": cfg.experiment.runs,
        "trials": cfg.experiment.trials,
        "learning_episodes_per_trial": cfg.experiment.learning_episodes_per_trial,
        "test_episodes_per_trial": cfg.experiment.test_episodes_per_trial,
        "seeds": [repetition_seed(cfg, r) for r in range(cfg.experiment.runs)],
        "tau": cfg.train.robustness_tau,
        "threshold": cfg.train.robustness_threshold,
        "keep_share": cfg.train.robustness_keep_share,
        "grid": section(cfg).size,
        "horizon": section(cfg).horizon,
        "workers": workers,
    }
    metrics["timing"] = {
        "wall_seconds": wall,
        "seconds_per_trial": wall / max(cfg.experiment.runs * cfg.experiment.trials, 1),
        "repetition_seconds": [r["seconds"] for r in results],
        "frames_per_repetition": [int(r["frames"].sum()) for r in results],
        "updates_per_repetition": [int(r["updates"][-1]) for r in results],
        # where a trial's CPU goes, per phase, over every repetition and trial
        "cpu_seconds_per_trial": {
            phase: sum(r["cpu_seconds"][phase] for r in results)
            / max(cfg.experiment.runs * cfg.experiment.trials, 1)
            for phase in PHASES
        },
    }
    learn = np.stack([r["learn_items"] for r in results])  # (R, T)
    metrics["learning_items"] = {
        "curve_mean": learn.mean(0).tolist(),
        "curve_per_rep": learn.tolist(),
    }
    for name, (done, seconds) in baselines.items():
        _add_baseline(metrics, name, done, seconds)
    if baselines:
        rows = [
            {"rep": r, "trial": t + 1, "method": name, "items": float(a), "heldout_items": float(b)}
            for name, (done, _) in baselines.items()
            for r, one in enumerate(done)
            for t, (a, b) in enumerate(zip(one["items"], one["heldout_items"]))
        ]
        write_csv(out / BASELINES_CSV, rows, BASELINES_CSV_FIELDS)
    write_json(out / "metrics.json", metrics)
    if plots:  # else ``taskvar plot DIR`` draws them from the folder
        plot_results(out)
    print(format_table(metrics))
    return metrics


__all__ = [  # the protocol, then the names of fig4_trial, side_by_side, snapshots, fig4_metrics,
    # fig4_report it re-exports
    "EXPERIMENT",
    "METHODS",
    "PHASES",
    "TEST_GROUP",
    "default_config_path",
    "hierarchy_depths",
    "make_agent",
    "make_test_controllers",
    "make_test_env",
    "make_heldout_test_env",
    "heldout_summary",
    "heldout_extras",
    "BASELINES_CSV",
    "HELDOUT_CSV",
    "HELDOUT_KEYS",
    "nominal_seeds",
    "trial_seeds",
    "method_summary",
    "repetition_seed",
    "repetition_batches",
    "run_repetition",
    "run_repetitions",
    "run_repetitions_batched",
    "exploration_generator",
    "make_behaviour",
    "EXPLORATION_OFFSET",
    "trial_calibration",
    "wargus_fig4",
    "LifelongAgent",
    "learn_due",
    "learning_phase",
    "learning_phases",
    "learning_phase_torchrl",
    "test_phase",
    "test_phase_torchrl",
    "test_trials",
    "HeadValues",
    "SideBySide",
    "mean_over_trials",
    "summarise",
    "CSV_FIELDS",
    "STYLES",
    "csv_rows",
    "format_table",
    "is_results_folder",
    "plot_results",
]
