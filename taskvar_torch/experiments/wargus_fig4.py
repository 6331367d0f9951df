"""Wargus Figure 4: the lifelong protocol (paper §3.5.1-3.5.3; docs/wargus-fig4.md).

The protocol, top to bottom (:func:`wargus_fig4`), for each of R repetitions (own seed
``cfg.seed + rep``, own env streams, own replay generator, own torch RNG stream; never one RNG
shared between repetitions):

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
      (fixed instance seeds :data:`~taskvar_torch.envs.wargus.NOMINAL_SEEDS`) with each method --
      averaging (greedy Q_avg), options (mu_bar + option policies run to termination),
      interruption (Algorithm 1, max-value heads) and hierarchy (Algorithm 2, robustness critics,
      ``tau = train.robustness_tau``) -- all 4 x K episodes side by side in one batched env;
      score = items collected per test episode.

Definitions used in ``metrics.json``:

- ``curve_mean`` / ``curve_std``: per trial, mean and standard deviation over repetitions of the
  mean items per test episode (raw, unsmoothed);
- ``curve_smoothed``: trailing moving average of ``curve_mean`` over ``smoothing_window`` trials
  (``max(1, T // 20)``, 25 for 500 trials); trailing, so the value at trial t uses trials <= t;
- ``final_score``: mean of ``curve_mean`` over the last 10% of trials (at least one);
- ``trials_to_90pct``: first trial (1-based) at which ``curve_smoothed`` reaches 90% of
  ``final_score`` (``T`` and ``reached_90pct = false`` if it never does);
- ``hierarchy_trace``: fraction of the hierarchy's (alive) test steps at which each level / each
  subtask held control (Algorithm 2's decision), over all trials and over the last 10%.

Repetitions run sequentially or, with ``workers > 1``, in spawned processes (one torch thread
each); both give the same numbers (each repetition depends on its own seed only).

Speed (docs/benchmarks.md, ``benchmarks/wargus_trial.py``): the loops step the pure
dynamics through :meth:`WargusEnv.reset_all` / :meth:`WargusEnv.step_all` (no ``EnvBase``
checks, transforms or ``step_mdp``), write replay once per update phase, run every head in one
stacked pass (:class:`~taskvar_torch.heads.snapshots.HeadValues`), and test :data:`TEST_GROUP`
trials side by side on frozen copies of their heads (:func:`test_trials` with
:class:`~taskvar_torch.controllers.side_by_side.SideBySide`). The TorchRL loops :func:`learning_phase_torchrl` /
:func:`test_phase_torchrl` are kept as the reference the tests check them bit-equal to.

Writes ``config.yaml``, ``rep{r}/final.pt`` (every head, loadable by ``taskvar eval``),
``per_trial.csv`` (rep, trial, method, items, interruptions), ``metrics.json``, ``fig4.png``;
prints a table.

Examples:
    >>> cfg = load_config(default_config_path(), quick=True)  # doctest: +SKIP
    >>> metrics = wargus_fig4(cfg, "results/wargus-fig4-quick")  # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.multiprocessing as mp
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import step_mdp
from tqdm.auto import tqdm

from taskvar_torch import keys
from taskvar_torch.checkpoint import make_bundle, rng_state, save_checkpoint
from taskvar_torch.config import Config, save_config_yaml
from taskvar_torch.controllers import Controller
from taskvar_torch.controllers.side_by_side import SideBySide
from taskvar_torch.envs.wargus import ITEM_LOST, NOMINAL_SEEDS, WargusInstances
from taskvar_torch.envs.wargus_env import WargusEnv
from taskvar_torch.experiments.evaluation import run_episodes
from taskvar_torch.experiments.plots import _pyplot, save_figure
from taskvar_torch.experiments.results import refuse_existing_results, write_csv, write_json
from taskvar_torch.factory import calibrate, make_method_controller, replay_states
from taskvar_torch.heads.behaviour import BEHAVIOUR, IS_INIT, BehaviourPolicy
from taskvar_torch.heads.first_visit import FirstVisitFilter
from taskvar_torch.heads.robustness import RobustnessCalibration
from taskvar_torch.heads.snapshots import HeadValues
from taskvar_torch.train import (
    build_heads,
    epsilon_at,
    make_env,
    make_learner,
    make_replay_buffer,
    make_subtasks,
)

METHODS = ("averaging", "options", "interruption", "hierarchy")
EXPERIMENT = "wargus-fig4"
CSV_FIELDS = ("rep", "trial", "method", "items", "interruptions")
FINAL_FRACTION = 0.1  # "final" performance: the mean of the last 10% of trials
TEST_GROUP = 25  # trials whose test phases run side by side (run_repetition)


def default_config_path() -> Path:
    """``configs/wargus.yaml`` of the repository (or of the working directory)."""
    here = Path(__file__).resolve().parents[2] / "configs" / "wargus.yaml"
    return here if here.is_file() else Path("configs") / "wargus.yaml"


def repetition_seed(cfg: Config, rep: int) -> int:
    """Seed of repetition ``rep``: ``cfg.seed + rep`` (networks, envs, replay, exploration)."""
    return int(cfg.seed) + int(rep)


def nominal_seeds(k: int) -> tuple[int, ...]:
    """The ``k`` fixed test instance seeds: :data:`NOMINAL_SEEDS`, extended by consecutive ints."""
    extra = tuple(
        range(max(NOMINAL_SEEDS) + 1, max(NOMINAL_SEEDS) + 1 + max(k - len(NOMINAL_SEEDS), 0))
    )
    return (NOMINAL_SEEDS + extra)[:k]


# --------------------------------------------------------------------------------------------
# the agent: every head, one learner, one replay buffer (paper §3.5.1: no prior knowledge)


@dataclasses.dataclass
class LifelongAgent:
    """Everything one repetition learns, from scratch, plus its counters."""

    cfg: Config
    heads: Any
    subtasks: Any
    learner: Any
    behaviour: BehaviourPolicy
    buffer: Any
    replay_generator: torch.Generator
    first_visit: FirstVisitFilter
    frames: int = 0
    pending: int = 0  # frames stored since the last update phase
    updates: int = 0


def learn_due(agent: LifelongAgent, t: Any) -> None:
    """``train.updates_per_batch`` updates for every ``train.frames_per_batch`` frames played (after
    ``train.init_random_frames``), each on one shared sample for every head."""
    while agent.pending >= t.frames_per_batch:
        agent.pending -= t.frames_per_batch
        if agent.frames >= t.init_random_frames and len(agent.buffer) >= t.batch_size:
            for _ in range(t.updates_per_batch):
                agent.learner.update(agent.buffer.sample())
                agent.updates += 1


def make_agent(cfg: Config, env: WargusEnv | TransformedEnv, seed: int) -> LifelongAgent:
    """Fresh heads, learner, behaviour policy and an empty replay buffer (seeded by ``seed``)."""
    subtasks = make_subtasks(cfg, getattr(env, "base_env", env))
    heads = build_heads(cfg, env, subtasks)
    learner = make_learner(cfg, heads, subtasks)
    behaviour = BehaviourPolicy(
        heads,
        subtasks,
        env.action_spec,
        option_prob=cfg.train.option_behaviour_prob,
        root_policy=cfg.train.hierarchy_root_policy,
    )
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
    )


def make_test_env(
    cfg: Config, k: int, seed: int, first_trial: int = 0, trials: int = 1
) -> WargusEnv:
    """The test env of ``trials`` trials from ``first_trial`` on: rows ``(g, method, j)``, where
    episode ``j`` of trial ``t`` plays nominal seed ``(j + t) % k``, so every method plays all
    ``k`` seeds every trial. With ``trials = 1`` the env can be reused: its next reset is the next
    trial (the seeds cycle)."""
    seeds = nominal_seeds(k)
    rows = tuple(
        seeds[(j + first_trial + g) % k] for g in range(trials) for _ in METHODS for j in range(k)
    )
    return WargusEnv(
        len(rows),
        config=dataclasses.asdict(cfg.env.wargus),
        instances=WargusInstances(seeds=rows),
        seed=seed,
        validate_actions=False,
        device=cfg.device,
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
# one trial: learning phase, then test phase


def learning_phase(agent: LifelongAgent, env: WargusEnv) -> dict[str, float]:
    """One episode per sub-environment (training instances) with learning on (paper §3.5.1).

    Transitions of live episodes are replayed; every ``frames_per_batch`` frames played the learner
    takes ``updates_per_batch`` gradient steps on every head. Returns the mean items per episode
    and the frames played.

    The fast loop: it steps ``env``'s dynamics directly (:meth:`WargusEnv.reset_all` /
    :meth:`WargusEnv.step_all`, no ``EnvBase`` checks, transforms or ``step_mdp``), carries
    ``is_init`` and the behaviour mode itself, and writes the kept transitions to the replay buffer
    in one ``extend`` per update phase (before any sample, so the buffer holds the same rows in the
    same order). Same draws, same transitions, same updates as the TorchRL loop
    :func:`learning_phase_torchrl` (tested equal).
    """
    t = agent.cfg.train
    n = env.num_envs
    dev = env.device
    td = env.reset_all()  # every sub-env starts a new episode with a fresh training instance
    td.set(IS_INIT, torch.ones(n, 1, dtype=torch.bool, device=dev))
    not_init = torch.zeros(n, 1, dtype=torch.bool, device=dev)
    if t.first_visit:
        agent.first_visit.clear()
    alive = torch.ones(n, dtype=torch.bool, device=dev)
    items = torch.zeros(n, device=dev)
    frames = 0
    staged: list[TensorDictBase] = []  # transitions of this update phase, not yet in the buffer
    masks: list[torch.Tensor] = []  # (n,) which of them to keep
    for _ in range(env.horizon):
        agent.behaviour.set_epsilon(epsilon_at(agent.frames, t))
        td = agent.behaviour(td)
        action = td.get(keys.ACTION)
        nxt = env.step_all(action)
        nxt.set(IS_INIT, not_init)
        # ---- stage this step's transitions of the live episodes ------------------------------
        keep = alive
        if t.first_visit:
            keep = keep & agent.first_visit.visit(td.get(keys.OBSERVATION), action)
        staged.append(_transition(td, nxt))
        masks.append(keep)
        n_alive = int(alive.sum())
        agent.frames += n_alive
        agent.pending += n_alive
        frames += n_alive
        items += torch.where(alive, nxt.get(keys.REWARD).reshape(n), 0.0)
        # ---- learn: every head from one shared sample per update ----------------------------
        if agent.pending >= t.frames_per_batch:
            _flush(agent, staged, masks)
        learn_due(agent, t)
        alive = alive & ~nxt.get(keys.DONE).reshape(n)
        if not bool(alive.any()):
            break
        nxt.set(BEHAVIOUR, td.get(BEHAVIOUR))  # carried, like step_mdp(keep_other=True)
        td = nxt
    _flush(agent, staged, masks)
    return {"learn_items": float(items.mean()), "frames": frames}


_HIDDEN = (keys.INSTANCE, keys.REWARD)  # never replayed / not part of a state


def _transition(td: TensorDictBase, nxt: TensorDictBase) -> TensorDictBase:
    """The replayed transition: the state ``td`` (with action, behaviour, ``is_init``) and
    ``"next"``, minus the hidden instance (the keys ``env.step`` + ``step_mdp`` give)."""
    root = {k: v for k, v in td.items() if k not in _HIDDEN}
    root[keys.NEXT] = nxt.exclude(keys.INSTANCE)
    return TensorDict._new_unsafe(root, batch_size=td.batch_size, device=td.device)


def _flush(agent: LifelongAgent, staged: list, masks: list) -> None:
    """Write the staged transitions that are kept to the replay buffer (one ``extend``)."""
    if not staged:
        return
    keep = torch.cat(masks)
    if bool(keep.any()):
        agent.buffer.extend(torch.cat(staged)[keep])
    staged.clear()
    masks.clear()


def test_phase(policy: SideBySide, env: WargusEnv, k: int) -> dict[str, np.ndarray]:
    """The nominal test episodes of every method, side by side, learning off (paper §3.5.1).

    Returns per method ``items`` (mean per test episode), ``interruptions`` (per episode) and,
    over the hierarchy's live steps, the count of steps each subtask held control. ``env``: the
    test env (:func:`make_test_env`), at its next trial. The fast loop (:func:`test_trials` with
    the live heads); the same episodes as :func:`test_phase_torchrl` (tested equal).
    """
    return test_trials(policy, env, k, None)[0]


@torch.inference_mode()
def test_trials(
    policy: SideBySide,
    env: WargusEnv,
    k: int,
    snapshots: Sequence[Sequence[torch.Tensor]] | None,
    calibrations: Sequence[RobustnessCalibration | None] | None = None,
) -> list[dict[str, np.ndarray]]:
    """The test phases of ``G`` trials side by side: trial ``g`` with frozen heads
    ``snapshots[g]`` (:meth:`HeadValues.snapshot`; ``None``: one trial, the live heads) on rows
    ``(g, method, episode)`` of ``env`` (:func:`make_test_env` with ``trials=G``).

    Steps ``env``'s dynamics directly (:meth:`WargusEnv.step_all`) with
    :meth:`SideBySide.decide_batch`, carries ``running_option`` (-1 at the start) itself, and stops
    when every episode is done. Test episodes read nothing learnt later and draw nothing from the
    global stream, so testing a trial later, beside others, gives the episodes it gave right after
    its learning phase (tested equal). Returns one :func:`test_phase` result per trial.
    """
    params = None
    G = 1
    if snapshots is not None:
        params = [torch.stack(p) for p in zip(*snapshots)]
        G = len(snapshots)
    M = len(METHODS)
    n = env.num_envs
    if n != G * M * k:
        raise ValueError(f"the test env has {n} sub-environments, expected {G} x {M} x {k}")
    dev = env.device
    td = env.reset_all()
    running = torch.full((n,), -1, dtype=torch.int64, device=dev)
    alive = torch.ones(n, dtype=torch.bool, device=dev)
    ret = torch.zeros(n, device=dev)
    inter = torch.zeros(n, dtype=torch.int64, device=dev)
    lost = torch.zeros(n, dtype=torch.int64, device=dev)
    h = METHODS.index("hierarchy")
    thresholds = policy.threshold_rows(calibrations) if calibrations is not None else None
    options, alives = [], []
    for _ in range(env.horizon):
        lost += (
            td.get(ITEM_LOST).reshape(n) & alive
        ).long()  # the step that led here lost the item
        out = policy.decide_batch(td, running, params, thresholds)
        inter += (out[keys.INTERRUPTED] & alive).long()
        options.append(out[keys.OPTION])
        alives.append(alive)
        td = env.step_all(out[keys.ACTION])
        running = out["next_running"]
        ret += torch.where(alive, td.get(keys.REWARD).reshape(n), 0.0)
        alive = alive & ~td.get(keys.DONE).reshape(n)
        if not bool(alive.any()):
            break
    option = torch.stack(options, -1).view(G, M, k, -1)[:, h]  # (G, K, T)
    live = torch.stack(alives, -1).view(G, M, k, -1)[:, h]  # (G, K, T)
    ret, inter, lost = ret.view(G, M * k), inter.view(G, M * k), lost.view(G, M * k)
    return [
        _test_summary(policy, ret[g], inter[g], option[g], live[g], k, lost[g]) for g in range(G)
    ]


def _test_summary(
    policy: SideBySide,
    ret: torch.Tensor,  # (M K,) items per test episode
    inter: torch.Tensor,  # (M K,) interruptions per test episode
    option: torch.Tensor,  # (K, T) the hierarchy's option per step
    alive: torch.Tensor,  # (K, T) its live steps
    k: int,
    lost: torch.Tensor,  # (M K,) item_lost events per test episode
) -> dict[str, np.ndarray]:
    num_options = len(policy.controllers[METHODS.index("hierarchy")].heads.option_names)
    control = torch.stack([((option == o) & alive).sum() for o in range(num_options)])
    return {
        "items": ret.reshape(len(METHODS), k).mean(-1).cpu().numpy(),  # (M,)
        "interruptions": inter.reshape(len(METHODS), k).double().mean(-1).cpu().numpy(),  # (M,)
        "control_steps": control.cpu().numpy(),  # (O,)
        "item_lost": lost.reshape(len(METHODS), k).double().mean(-1).cpu().numpy(),  # (M,)
    }


# ---- the TorchRL loops: the reference the fast loops are tested against ---------------------


def learning_phase_torchrl(agent: LifelongAgent, env: TransformedEnv) -> dict[str, float]:
    """:func:`learning_phase` through TorchRL's ``EnvBase.step`` (``env``: the learning env with
    an ``InitTracker``), ``step_mdp`` and one ``extend`` per step: the reference implementation."""
    t = agent.cfg.train
    n = env.batch_size[0]
    td = env.reset()  # every sub-env starts a new episode with a fresh training instance
    alive = torch.ones(n, dtype=torch.bool, device=env.device)
    items = torch.zeros(n, device=env.device)
    frames = 0
    drop = (keys.INSTANCE, (keys.NEXT, keys.INSTANCE))
    for _ in range(env.base_env.horizon):
        agent.behaviour.set_epsilon(epsilon_at(agent.frames, t))
        td = agent.behaviour(td)
        td = env.step(td)
        keep = alive
        if t.first_visit:
            keep = keep & agent.first_visit(td.unsqueeze(1)).squeeze(1)
        if bool(keep.any()):
            agent.buffer.extend(td.exclude(*drop)[keep])
        n_alive = int(alive.sum())
        agent.frames += n_alive
        agent.pending += n_alive
        frames += n_alive
        items += torch.where(alive, td.get((keys.NEXT, keys.REWARD)).reshape(n), 0.0)
        learn_due(agent, t)
        alive = alive & ~td.get((keys.NEXT, keys.DONE)).reshape(n)
        if not bool(alive.any()):
            break
        td = step_mdp(td, keep_other=True)
    return {"learn_items": float(items.mean()), "frames": frames}


def test_phase_torchrl(policy: SideBySide, env: TransformedEnv, k: int) -> dict[str, np.ndarray]:
    """:func:`test_phase` through :func:`run_episodes` (``env``: the test env with the
    controllers' primer): the reference implementation."""
    out = run_episodes(env, policy, trace_keys=(keys.OPTION, ITEM_LOST))
    h = METHODS.index("hierarchy")
    option = out["trace", keys.OPTION][h * k : (h + 1) * k]  # (K, T)
    alive = out["trace", "alive"][h * k : (h + 1) * k]  # (K, T)
    lost = (out["trace", ITEM_LOST] & out["trace", "alive"]).sum(-1)  # (M K,)
    return _test_summary(policy, out["return"], out["interruptions"], option, alive, k, lost)


# --------------------------------------------------------------------------------------------
# one repetition


def run_repetition(
    cfg: Config,
    rep: int,
    out_dir: str | os.PathLike,
    on_trial: Callable[[int, int], None] | None = None,
    test_group: int = TEST_GROUP,
) -> dict[str, Any]:
    """Repetition ``rep`` of the lifelong protocol (module docstring); saves ``rep{rep}/final.pt``.

    The test phases of ``test_group`` consecutive trials run side by side after their learning
    phases, each with a frozen copy of the heads taken at the end of its trial
    (:func:`test_trials`): the same episodes as testing each trial at once, in a batch that
    amortises the per-step work (``test_group = 1`` tests every trial at once).

    Runs inside :func:`torch.random.fork_rng` seeded with :func:`repetition_seed`, so its global
    torch stream (network init, behaviour draws) is its own and leaves the caller's untouched.

    Returns:
        ``items``, ``interruptions`` and ``item_lost`` ``(T, M)``, ``control_steps`` ``(T, O)``,
        ``learn_items``,
        ``frames``, ``updates`` ``(T,)``, ``option_names``, ``seconds``.
    """
    x = cfg.experiment
    seed = repetition_seed(cfg, rep)
    rep_cfg = dataclasses.replace(cfg, seed=seed)
    k = x.test_episodes_per_trial
    start = time.perf_counter()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        learn_env = make_env(rep_cfg, num_envs=x.learning_episodes_per_trial, seed=seed)
        learn_env.validate_actions = False  # the behaviour's actions are in range by construction
        agent = make_agent(rep_cfg, learn_env, seed)
        controllers = make_test_controllers(agent)
        policy = SideBySide(controllers, k)
        group = test_group if policy.batchable else 1
        rows: dict[str, list] = {
            k_: []
            for k_ in (
                "items",
                "interruptions",
                "control_steps",
                "item_lost",
                "learn_items",
                "frames",
            )
        }
        updates: list[int] = []
        snapshots: list[list[torch.Tensor]] = []  # frozen heads of trials not tested yet
        calibrations: list[RobustnessCalibration | None] = []  # and their hierarchy thresholds
        hier = controllers[METHODS.index("hierarchy")]

        def test_pending() -> None:
            env = make_test_env(cfg, k, seed, first_trial=len(rows["items"]), trials=len(snapshots))
            if group == 1 and calibrations[0] is not None:
                hier.calibration = calibrations[0]
            tested_all = test_trials(policy, env, k, snapshots if group > 1 else None, calibrations)
            for tested in tested_all:
                for key, v in tested.items():
                    rows[key].append(v)
            snapshots.clear()
            calibrations.clear()

        for trial in range(x.trials):
            learned = learning_phase(agent, learn_env)
            for key, v in learned.items():
                rows[key].append(v)
            updates.append(agent.updates)
            snapshots.append(policy.head_values.snapshot() if group > 1 else [])
            calibrations.append(trial_calibration(agent))
            if len(snapshots) >= group:
                test_pending()
            if on_trial is not None:
                on_trial(rep, trial)
        if snapshots:
            test_pending()
        rows["updates"] = updates
        rep_dir = Path(out_dir) / f"rep{rep}"
        save_checkpoint(
            rep_dir / "final.pt",
            make_bundle(
                rep_cfg,
                models={"heads": agent.heads, "targets": agent.learner.loss.target_heads},
                optimizers={"adam": agent.learner.optimizer},
                counters={"frames": agent.frames, "updates": agent.updates, "trials": x.trials},
                rng=rng_state({"replay": agent.replay_generator}),
            ),
        )
    result = {key: np.asarray(v) for key, v in rows.items()}
    result["option_names"] = list(agent.heads.option_names)
    result["option_depths"] = hierarchy_depths(agent.subtasks.hierarchy, agent.heads.option_names)
    result["seconds"] = time.perf_counter() - start
    return result


def hierarchy_depths(hierarchy: Any, option_names: Sequence[str]) -> list[int]:
    """Depth of each option in the composition tree (0: the root; -1: outside the tree)."""
    depth, stack = {hierarchy.root: 0}, [hierarchy.root]
    while stack:
        o = stack.pop()
        for c in hierarchy.children.get(o, ()):
            depth[c] = depth[o] + 1
            stack.append(c)
    return [depth.get(o, -1) for o in option_names]


def _worker(cfg: Config, rep: int, out_dir: str, threads: int, queue: Any) -> None:
    """Process entry: one repetition, progress and result through ``queue``."""
    torch.set_num_threads(threads)
    try:
        result = run_repetition(cfg, rep, out_dir, lambda r, t: queue.put(("trial", r, None)))
        queue.put(("done", rep, result))
    except BaseException as e:  # report, so the parent does not wait forever
        queue.put(("error", rep, f"{type(e).__name__}: {e}"))


def run_repetitions(
    cfg: Config, out_dir: str | os.PathLike, workers: int = 1, progress: bool = True
) -> list[dict[str, Any]]:
    """Every repetition, sequentially (``workers = 1``) or in ``workers`` spawned processes."""
    reps = cfg.experiment.runs
    bar = tqdm(
        total=reps * cfg.experiment.trials, disable=not progress, desc=EXPERIMENT, unit="trial"
    )
    results: dict[int, dict[str, Any]] = {}
    if workers <= 1:
        for rep in range(reps):
            results[rep] = run_repetition(cfg, rep, out_dir, lambda r, t: bar.update(1))
    else:
        ctx = mp.get_context("spawn")
        queue = ctx.Queue()
        pending = list(range(reps))
        running: dict[int, Any] = {}
        threads = max(1, torch.get_num_threads() // workers)
        try:
            while pending or running:
                while pending and len(running) < workers:
                    rep = pending.pop(0)
                    running[rep] = ctx.Process(
                        target=_worker, args=(cfg, rep, str(out_dir), threads, queue), daemon=True
                    )
                    running[rep].start()
                kind, rep, payload = queue.get()
                if kind == "trial":
                    bar.update(1)
                elif kind == "error":
                    raise RuntimeError(f"repetition {rep} failed: {payload}")
                else:
                    results[rep] = payload
                    running.pop(rep).join()
        finally:  # an error or Ctrl-C here stops the other repetitions too
            for p in running.values():
                p.terminate()
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
) -> dict[str, Any]:
    """Run the lifelong protocol (module docstring), write the results folder, print the table.

    ``workers`` processes run the repetitions; ``plots=False`` skips ``fig4.png`` (``taskvar plot
    DIR`` draws it later from the folder); ``overwrite`` replaces results already in ``out_dir``
    (without it such a folder is refused).
    """
    if cfg.family != "wargus":
        raise ValueError(f"wargus-fig4 needs a Wargus config (family='wargus'), got {cfg.family!r}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    out = Path(out_dir)
    refuse_existing_results(out, overwrite, "taskvar experiment wargus-fig4")
    out.mkdir(parents=True, exist_ok=True)
    save_config_yaml(cfg, out / "config.yaml")

    start = time.perf_counter()
    results = run_repetitions(cfg, out, workers=workers, progress=progress)
    wall = time.perf_counter() - start

    items = np.stack([r["items"] for r in results])  # (R, T, M)
    inter = np.stack([r["interruptions"] for r in results])  # (R, T, M)
    control = np.stack([r["control_steps"] for r in results])  # (R, T, O)
    lost = np.stack([r["item_lost"] for r in results])  # (R, T, M)
    write_csv(out / "per_trial.csv", _csv_rows(items, inter), CSV_FIELDS)
    metrics = summarise(
        items, inter, control, results[0]["option_names"], results[0]["option_depths"], lost
    )
    metrics["protocol"] = {
        "repetitions": cfg.experiment.runs,
        "trials": cfg.experiment.trials,
        "learning_episodes_per_trial": cfg.experiment.learning_episodes_per_trial,
        "test_episodes_per_trial": cfg.experiment.test_episodes_per_trial,
        "seeds": [repetition_seed(cfg, r) for r in range(cfg.experiment.runs)],
        "tau": cfg.train.robustness_tau,
        "threshold": cfg.train.robustness_threshold,
        "keep_share": cfg.train.robustness_keep_share,
        "grid": cfg.env.wargus.size,
        "horizon": cfg.env.wargus.horizon,
        "workers": workers,
    }
    metrics["timing"] = {
        "wall_seconds": wall,
        "seconds_per_trial": wall / max(cfg.experiment.runs * cfg.experiment.trials, 1),
        "repetition_seconds": [r["seconds"] for r in results],
        "frames_per_repetition": [int(r["frames"].sum()) for r in results],
        "updates_per_repetition": [int(r["updates"][-1]) for r in results],
    }
    learn = np.stack([r["learn_items"] for r in results])  # (R, T)
    metrics["learning_items"] = {
        "curve_mean": learn.mean(0).tolist(),
        "curve_per_rep": learn.tolist(),
    }
    write_json(out / "metrics.json", metrics)
    if plots:  # else ``taskvar plot DIR`` draws them from the folder
        plot_results(out)
    print(format_table(metrics))
    return metrics


def _csv_rows(items: np.ndarray, inter: np.ndarray) -> list[dict[str, Any]]:
    R, T, M = items.shape
    return [
        {
            "rep": r,
            "trial": t + 1,
            "method": METHODS[m],
            "items": float(items[r, t, m]),
            "interruptions": float(inter[r, t, m]),
        }
        for r in range(R)
        for t in range(T)
        for m in range(M)
    ]


# --------------------------------------------------------------------------------------------
# statistics


def smoothing_window(trials: int) -> int:
    """Moving-average window: ``max(1, trials // 20)`` (25 for the paper's 500 trials)."""
    return max(1, int(trials) // 20)


def moving_average(x: np.ndarray, window: int) -> np.ndarray:
    """Trailing moving average along the last axis (the first values average what exists)."""
    x = np.asarray(x, dtype=float)
    c = np.cumsum(x, axis=-1)
    out = c.copy()
    out[..., window:] = c[..., window:] - c[..., :-window]
    n = np.minimum(np.arange(1, x.shape[-1] + 1), window)
    return out / n


def final_count(trials: int) -> int:
    """Number of last trials whose mean is the "final" performance: 10%, at least one."""
    return max(1, int(math.ceil(FINAL_FRACTION * trials)))


def trials_to_fraction_of_max(curve: np.ndarray, fraction: float = 0.9) -> int:
    """First trial (1-based) at which the smoothed ``curve`` reaches ``fraction`` of its own
    maximum (the paper's Figure 4 bars: "90% to their maximum performance")."""
    smooth = moving_average(np.asarray(curve, dtype=float), smoothing_window(np.size(curve)))
    return int(np.nonzero(smooth >= fraction * smooth.max())[0][0]) + 1


def mean_over_trials(items: np.ndarray, first: int | None = None) -> dict[str, float]:
    """Mean items per test episode over trials ``1..first`` (all: ``None``) of ``items`` ``(R,
    T)``: the mean, the standard deviation across repetitions and a 95% CI half-width
    (normal approximation over repetitions)."""
    per_rep = np.asarray(items, dtype=float)[:, :first].mean(1)  # (R,)
    R = per_rep.size
    std = float(per_rep.std(ddof=1)) if R > 1 else float("nan")
    return {
        "mean": float(per_rep.mean()),
        "std": std,
        "ci95": 1.959964 * std / math.sqrt(R) if R > 1 else float("nan"),
        "trials": int(np.asarray(items)[:, :first].shape[1]),
    }


def trials_to_fraction(curve: np.ndarray, fraction: float = 0.9) -> tuple[int, bool]:
    """First trial (1-based) at which the smoothed ``curve`` reaches ``fraction`` of its final
    value (mean of the last 10% of the raw curve); ``(len(curve), False)`` if it never does."""
    curve = np.asarray(curve, dtype=float)
    final = curve[-final_count(curve.size) :].mean()
    smooth = moving_average(curve, smoothing_window(curve.size))
    hit = np.nonzero(smooth >= fraction * final)[0]
    return (int(hit[0]) + 1, True) if hit.size else (int(curve.size), False)


def summarise(
    items: np.ndarray,  # (R, T, M) mean items per test episode
    inter: np.ndarray,  # (R, T, M) interruptions per test episode
    control: np.ndarray,  # (R, T, O) hierarchy steps per controlling subtask
    option_names: Sequence[str],
    option_depths: Sequence[int],
    item_lost: np.ndarray | None = None,  # (R, T, M) item_lost events per test episode
) -> dict[str, Any]:
    """``metrics.json``'s content (definitions in the module docstring)."""
    R, T, M = items.shape
    nf = final_count(T)
    w = smoothing_window(T)
    methods = {}
    for m, name in enumerate(METHODS):
        mean, std = items[:, :, m].mean(0), items[:, :, m].std(0)
        t90, reached = trials_to_fraction(mean)
        per_rep = [trials_to_fraction(items[r, :, m])[0] for r in range(R)]
        methods[name] = {
            "final_score": float(mean[-nf:].mean()),
            "final_score_std": float(items[:, -nf:, m].mean(1).std()),
            "trials_to_90pct": t90,
            "reached_90pct": reached,
            "trials_to_90pct_per_rep": per_rep,
            "trials_to_90pct_std": float(np.std(per_rep)),
            "trials_to_90pct_of_max": trials_to_fraction_of_max(mean),
            "mean_over_trials": mean_over_trials(items[:, :, m]),
            "mean_first_250_trials": mean_over_trials(items[:, :, m], 250),
            "interruptions_per_episode": float(inter[:, :, m].mean()),
            "curve_mean": mean.tolist(),
            "curve_std": std.tolist(),
            "curve_smoothed": moving_average(mean, w).tolist(),
            "curve_per_rep": items[:, :, m].tolist(),
        }
        if item_lost is not None:
            methods[name]["item_lost_per_episode"] = float(item_lost[:, :, m].mean())

    def fractions(c: np.ndarray) -> dict[str, Any]:
        total = max(float(c.sum()), 1.0)
        per_option = {o: float(c[..., i].sum()) / total for i, o in enumerate(option_names)}
        per_level = {
            f"level_{d}": sum(v for v, dd in zip(per_option.values(), option_depths) if dd == d)
            for d in sorted(set(option_depths))
        }
        return {"per_subtask": per_option, "per_level": per_level, "steps": int(c.sum())}

    return {
        "experiment": EXPERIMENT,
        "methods": methods,
        "smoothing_window": w,
        "final_trials": nf,
        "definitions": {
            "score": "items collected per nominal test episode",
            "final_score": f"mean over repetitions of the last {nf} trials (10%)",
            "trials_to_90pct": f"first trial where the trailing {w}-trial moving average of the "
            "repetition-mean curve reaches 90% of final_score",
            "trials_to_90pct_of_max": f"first trial where the trailing {w}-trial moving average "
            "of the repetition-mean curve reaches 90% of its own maximum (the paper's bars)",
            "mean_over_trials": "mean items per test episode over all trials (std and 95% CI "
            "across repetitions); mean_first_250_trials: the same over trials 1-250",
            "hierarchy_trace": "fraction of the hierarchy's test steps each subtask (level 0: root "
            "TG+FE, level 1: components TG, FE) held control",
        },
        "hierarchy_trace": {
            "all_trials": fractions(control),
            "last_10pct": fractions(control[:, -nf:]),
        },
    }


# --------------------------------------------------------------------------------------------
# files, table, plot


def format_table(metrics: dict[str, Any]) -> str:
    """Final score and trials-to-90% per method, the hierarchy's control split, the wall time."""
    p, tm = metrics.get("protocol", {}), metrics.get("timing", {})
    lines = [
        f"Wargus Figure 4: {p.get('repetitions')} repetitions x {p.get('trials')} trials "
        f"({p.get('learning_episodes_per_trial')} learning + {p.get('test_episodes_per_trial')} "
        f"nominal test episodes), grid {p.get('grid')}, horizon {p.get('horizon')}, "
        + (
            f"tau calibrated (root keeps {p.get('keep_share'):.0%} of no-conflict states)"
            if p.get("threshold") == "calibrated"
            else f"tau {p.get('tau')}"
        ),
        f"{'method':<14}{'final items':>12}{'+-std':>8}{'mean (all)':>12}{'90% final':>11}"
        f"{'90% max':>9}{'interr./ep':>12}",
    ]
    for name, m in metrics["methods"].items():
        t90 = f"{m['trials_to_90pct']}{'' if m['reached_90pct'] else '*'}"
        mean_all = m.get("mean_over_trials", {}).get("mean", float("nan"))
        lines.append(
            f"{name:<14}{m['final_score']:>12.3f}{m['final_score_std']:>8.3f}{mean_all:>12.3f}"
            f"{t90:>11}{m.get('trials_to_90pct_of_max', '-'):>9}"
            f"{m['interruptions_per_episode']:>12.2f}"
        )
    h = metrics["hierarchy_trace"]["all_trials"]["per_subtask"]
    lines.append("hierarchy control: " + ", ".join(f"{o} {v:.1%}" for o, v in h.items()))
    if "wall_seconds" in tm:
        lines.append(
            f"wall time {tm['wall_seconds']:.1f} s ({tm['seconds_per_trial']:.2f} s per trial); "
            "paper: hierarchy ~100 trials to 90%, averaging > 350"
        )
    return "\n".join(lines)


STYLES = {
    "hierarchy": dict(color="tab:blue", ls="-"),
    "averaging": dict(color="tab:green", ls="--"),
    "options": dict(color="tab:orange", ls=":"),
    "interruption": dict(color="tab:red", ls="-."),
}


def is_results_folder(out_dir: str | os.PathLike) -> bool:
    """Whether ``out_dir`` holds a ``metrics.json`` written by :func:`wargus_fig4`."""
    path = Path(out_dir) / "metrics.json"
    try:
        return json.loads(path.read_text()).get("experiment") == EXPERIMENT
    except (OSError, ValueError, AttributeError):
        return False


def plot_results(out_dir: str | os.PathLike) -> list[Path]:
    """(Re)draw ``fig4.png`` from ``metrics.json``: smoothed mean items per test episode per trial
    with +-std bands over repetitions, and the trials-to-90% bars (paper Figure 4 layout)."""

    out = Path(out_dir)
    metrics = json.loads((out / "metrics.json").read_text())
    plt = _pyplot()
    fig, (ax, bx) = plt.subplots(
        2, 1, figsize=(8, 6), gridspec_kw={"height_ratios": [3, 1]}, sharex=True
    )
    w = metrics["smoothing_window"]
    for name, m in metrics["methods"].items():
        mean = np.asarray(m["curve_smoothed"], dtype=float)
        std = moving_average(np.asarray(m["curve_std"], dtype=float), w)
        x = np.arange(1, mean.size + 1)
        ax.plot(x, mean, lw=1.6, label=name, **STYLES.get(name, {}))
        ax.fill_between(
            x, mean - std, mean + std, alpha=0.15, color=STYLES.get(name, {}).get("color")
        )
    ax.set_ylabel("items per test episode")
    ax.set_title(
        f"Wargus lifelong protocol: mean of {metrics['protocol']['repetitions']} repetitions "
        f"(moving average of {w} trials, bands: std)"
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    names = list(metrics["methods"])
    t90 = [metrics["methods"][n]["trials_to_90pct"] for n in names]
    err = [metrics["methods"][n]["trials_to_90pct_std"] for n in names]
    bx.barh(names, t90, xerr=err, color=[STYLES.get(n, {}).get("color") for n in names], alpha=0.7)
    bx.set_xlabel("trial")
    bx.set_title(
        "trials to 90% of final performance (error bars: std over repetitions)", fontsize=9
    )
    bx.grid(alpha=0.3, axis="x")
    path = save_figure(fig, out / "fig4.png")
    plt.close(fig)
    return [path]


__all__ = [
    "METHODS",
    "HeadValues",
    "LifelongAgent",
    "SideBySide",
    "default_config_path",
    "learning_phase",
    "learning_phase_torchrl",
    "make_agent",
    "moving_average",
    "plot_results",
    "repetition_seed",
    "run_repetition",
    "run_repetitions",
    "summarise",
    "test_phase",
    "test_phase_torchrl",
    "trials_to_fraction",
    "wargus_fig4",
]
