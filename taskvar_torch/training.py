"""Offline training of every head from one stream of experience (paper §3.1-3.4; docs/design.md).

The loop, top to bottom (:func:`train`)::

    env (batched family, instances redrawn at every reset) + InitTracker + RewardSum
      --Collector(BehaviourPolicy)--> raw transitions --ReplayBuffer(LazyTensorStorage)-->
      one shared sample --MultiHeadLearner--> every head (averaging, options, switching, max-value,
      robustness) --> CSV logs, periodic checkpoints, DIR/final.pt

The env and collector come from :mod:`taskvar_torch.collection` (re-exported here). With
``collector.num_workers = W > 1`` the collector is TorchRL's ``MultiSyncCollector``: W spawned
processes, each stepping its own slice of the N environments (:func:`make_worker_env`), their
batches concatenated in worker order into the same ``(N, T)`` batch; after every update phase the
learner's behaviour weights (epsilon included) reach the workers through TorchRL's
``SharedMemWeightSyncScheme`` (``collector.update_policy_weights_``). With ``collector.backend =
ray`` the W workers are Ray actors instead (TorchRL ``Collector(backend="ray")``, weights through
its ``RayWeightSyncScheme``), on a local Ray or a cluster (``collector.ray_address``): the same
slices, the same ``(N, T)`` batch.

Exact resume: a checkpoint holds the heads, targets, optimiser, target-updater counter, step
counters, the replay buffer, the env's simulator state, the collector's carried tensordict and every
RNG state, so ``train(..., resume=ckpt)`` continues bit for bit on CPU (one collector process only:
the workers' env and RNG states are not saved, so resuming a multi-process run is refused).

The results folder (one run per folder, locked, never silently reused; logs cut back on resume;
SIGINT / SIGTERM stop at a resumable checkpoint) is :mod:`taskvar_torch.run_folder`, whose names
this module re-exports.

Examples:
    >>> cfg = load_config("configs/windy.yaml", ["train.total_frames=20000"])  # doctest: +SKIP
    >>> result = train(cfg, "/tmp/run")  # doctest: +SKIP
    >>> heads, cfg = load_heads("/tmp/run/final.pt")  # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import importlib.util
import os
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.collectors import BaseCollector, Collector
from torchrl.data import ReplayBuffer
from torchrl.envs import TransformedEnv
from torchrl.record.loggers import Logger, get_logger

from taskvar_torch import keys
from taskvar_torch.checkpoint import (
    EVAL_HEADS,
    RUNTIME_KEYS,
    CheckpointError,
    config_differences,
    load_checkpoint,
    make_bundle,
    require_entries,
    require_finite_heads,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from taskvar_torch.checkpoint_checks import (
    check_counter,
    check_counters,
    check_like,
    check_optimizer_state,
    check_rng_state,
    load_state_dicts,
)
from taskvar_torch.collection import (
    collects_in_workers,
    make_collector,
    make_training_env,
)
from taskvar_torch.config import (
    Config,
    TrainConfig,
    apply_overrides,
    config_from_dict,
    save_config_yaml,
)
from taskvar_torch.config.memory import check_memory
from taskvar_torch.config.memory import estimate as estimate_memory
from taskvar_torch.factory import (
    HEADS_NAME,
    build_heads,
    check_device,
    make_learner,
    make_subtasks,
    write_heads,
)
from taskvar_torch.heads.behaviour import BEHAVIOUR, BehaviourPolicy
from taskvar_torch.heads.bundle import Heads
from taskvar_torch.heads.first_visit import FirstVisitFilter
from taskvar_torch.heads.informed import INFORMED
from taskvar_torch.heads.learner import MultiHeadLearner
from taskvar_torch.heads.nstep import nstep_returns
from taskvar_torch.heads.recurrent import baseline_path, save_informed_head
from taskvar_torch.heads.seeds import split_seed, stack_seeds
from taskvar_torch.progress import progress_bar
from taskvar_torch.replay import (
    EPISODE_REWARD,
    check_replay_state,
    load_replay_state,
    make_replay_buffer,
    raw_transitions,
    replay_state,
)
from taskvar_torch.run_folder import (
    RunFolder,
    _interrupted,
    _last_checkpoint_note,
    _restore_logs,
    _StopSignals,
    check_out_path,
    check_output_folder,
)

HEADS_SNAPSHOTS = "heads"
"""Folder of a run's ``train.heads_every`` snapshots (``heads_<frames>.pt``)."""


class TrainingDiverged(RuntimeError):
    """A loss or a weight became NaN or infinite; no checkpoint holding it is ever written, so the
    last checkpoint on disk is intact."""


# --------------------------------------------------------------------------------------------
# replay and exploration


def epsilon_at(frames: int, t: TrainConfig) -> float:
    """Exploration rate after ``frames`` steps: 1 during ``init_random_frames``, then linear decay."""
    if frames < t.init_random_frames:
        return 1.0
    if t.eps_decay_frames <= 0:
        return t.eps_end
    frac = min(frames / t.eps_decay_frames, 1.0)
    return t.eps_start + frac * (t.eps_end - t.eps_start)


def lr_at(frames: int, t: TrainConfig) -> float:
    """Adam learning rate after ``frames`` steps: ``lr``, then (with ``lr_end``) linear decay from
    ``lr_decay_start_frames`` to ``lr_end`` at ``total_frames``."""
    if t.lr_end is None or frames <= t.lr_decay_start_frames:
        return t.lr
    span = t.total_frames - t.lr_decay_start_frames
    frac = 1.0 if span <= 0 else min((frames - t.lr_decay_start_frames) / span, 1.0)
    return t.lr + frac * (t.lr_end - t.lr)


# --------------------------------------------------------------------------------------------
# checkpoint pieces that checkpoint.py's conventional keys do not cover


def _check_runtime_only(bundle: dict[str, Any], cfg: Config, path: Any) -> None:
    """Overrides on a resumed run may change only runtime keys (e.g. ``train.total_frames``)."""
    diffs = config_differences(bundle["config"], cfg)
    if diffs:
        key, saved, wanted = diffs[0]
        raise CheckpointError(
            f"cannot resume {str(path)!r} with {key}={wanted!r}: it was trained with {saved!r}; "
            f"only {list(RUNTIME_KEYS)} may change on resume"
        )


def _collector_carrier(collector: Collector) -> TensorDictBase:
    # TorchRL's Collector keeps the current step's tensordict (observations, carried policy state
    # such as the behaviour mode, RewardSum's returns) in ``_carrier``; its state_dict does not
    # include it, so exact resume saves and restores it here.
    return collector._carrier


# --------------------------------------------------------------------------------------------
# faults: non-finite weights


def _non_finite(learner: MultiHeadLearner) -> list[str]:
    """Which of heads, target heads and optimiser state hold a NaN or infinite value (one sync)."""
    groups = {
        "heads": list(learner.heads.state_dict().values()),
        "targets": list(learner.loss.target_heads.state_dict().values()),
        "optimizer": [
            v
            for st in learner.optimizer.state.values()
            for v in st.values()
            if isinstance(v, torch.Tensor)
        ],
    }
    if learner.eval_heads is not learner.heads:  # train.eval_ema_tau
        groups[EVAL_HEADS] = list(learner.eval_heads.state_dict().values())
    names, flags = [], []
    for name, tensors in groups.items():
        finite = [torch.isfinite(t).all() for t in tensors if t.is_floating_point()]
        if finite:
            names.append(name)
            flags.append(torch.stack(finite).all())
    ok = torch.stack(flags).tolist() if flags else []
    return [n for n, good in zip(names, ok) if not good]


def _non_finite_seeds(learner: MultiHeadLearner, seeds: int) -> list[int]:
    """Which runs of a ``train.seeds`` batch hold a NaN or infinite weight, target or optimiser
    value (every such tensor is seed-major along its first dimension: heads/seeds.py)."""
    tensors = [
        *learner.heads.state_dict().values(),
        *learner.loss.target_heads.state_dict().values(),
        *(v for st in learner.optimizer.state.values() for v in st.values()),
    ]
    flags = [
        torch.isfinite(t.reshape(seeds, -1)).all(1)
        for t in tensors
        if isinstance(t, torch.Tensor) and t.is_floating_point() and t.dim() > 0
    ]
    ok = torch.stack(flags).all(0).tolist()  # (S,), one sync
    return [k for k, good in enumerate(ok) if not good]


def _require_finite(
    learner: MultiHeadLearner, frames: int, last: Path | None, cfg: Config | None = None
) -> None:
    """:class:`TrainingDiverged` when a weight or optimiser value is not finite: such a model is
    never written (a ``train.seeds`` batch: the message names the seeds that diverged)."""
    bad = _non_finite(learner)
    if bad:
        which = ""
        if cfg is not None and cfg.train.seeds > 1:
            seeds = [cfg.seed + k for k in _non_finite_seeds(learner, cfg.train.seeds)]
            which = f" of seed{'s' if len(seeds) > 1 else ''} {', '.join(map(str, seeds))}"
        raise TrainingDiverged(
            f"non-finite values in the {' and '.join(bad)}{which} at frame {frames}: training "
            f"diverged (lower train.lr?); nothing written, {_last_checkpoint_note(last)}"
        )


# --------------------------------------------------------------------------------------------
# the training loop


def train(
    cfg: Config | None,
    out_dir: str | os.PathLike,
    resume: str | os.PathLike | None = None,
    overrides: Sequence[str] = (),
    progress: bool = True,
    overwrite: bool = False,
    keep_replay: bool = True,
) -> dict[str, Any]:
    """Train every head of ``cfg``'s family; write logs, checkpoints and ``out_dir/final.pt``.

    Args:
        cfg: the run's config; with ``resume`` it may be ``None`` (the checkpoint's config is used)
            or must equal the checkpoint's up to runtime keys such as ``train.total_frames``.
        out_dir: results folder (created). A folder already holding a run is refused unless
            ``resume`` is a checkpoint inside it (the run continues; its logs are cut back to the
            checkpoint's frame) or ``overwrite`` is set; a second run on the same folder is refused.
        resume: a checkpoint written by this function to continue from, exactly.
        overrides: ``key.sub=value`` applied to the checkpoint's config when ``cfg`` is ``None``.
        progress: show a progress bar (plain lines when stderr is not a terminal).
        overwrite: remove the run already in ``out_dir`` (config, checkpoints, logs) first.
        keep_replay: ``False``: ``final.pt`` holds no replay buffer (up to ~1.3 GB at the scaled
            configs' 1M rows; the bundle still evaluates, :func:`load_heads`, but cannot be
            resumed); periodic checkpoints always hold it.

    Returns:
        ``{"final": path, "frames": int, "updates": int, "seconds": float, "last_log": dict}``.

    Raises:
        ValueError: an unusable ``out_dir`` or device, or a run already there; nothing is written.
        CheckpointError: an unreadable, foreign or non-finite ``resume`` checkpoint.
        TrainingDiverged: a loss (checked once per logging interval) or a weight (checked before
            every checkpoint write) became NaN or infinite; the last checkpoint written is intact.
        TrainingInterrupted: SIGINT or SIGTERM; the run stopped after its current batch and wrote
            a checkpoint (a second signal aborts at once: ``KeyboardInterrupt``).
    """
    out = check_out_path(out_dir)  # not '': it would be the current folder
    check_output_folder(out)  # inputs first: a refused run writes nothing
    bundle = None
    if resume is not None:
        bundle = load_checkpoint(resume, expected_config=cfg)
        member = bundle.get("batch_member")
        if isinstance(member, dict):
            raise CheckpointError(
                f"{str(resume)!r} is seed index {member.get('seed_index')} of a "
                f"{member.get('seeds')}-seed batch: it evaluates, it does not resume alone; "
                f"resume the batch from {str(Path(resume).resolve().parent.parent)!r}'s "
                "checkpoint_*.pt or final.pt"
            )
        require_finite_heads(bundle, resume)
        if cfg is None:
            cfg = apply_overrides(
                config_from_dict(bundle["config"], f"checkpoint {resume}"), overrides
            )
            _check_runtime_only(bundle, cfg, resume)
    if cfg is None:
        raise ValueError("train needs a config (or a checkpoint to resume)")
    check_device(cfg.device)
    check_memory(estimate_memory(cfg))  # before anything is allocated or written
    check_logger(cfg.train.logger)
    workers = cfg.collector.num_workers
    remote = collects_in_workers(cfg)
    if bundle is not None and "replay" not in bundle:
        raise CheckpointError(
            f"cannot resume {str(resume)!r}: it holds no replay buffer (written with "
            "keep_replay=False); it can be evaluated, not continued"
        )
    if bundle is not None:
        require_entries(bundle, resume)  # a damaged or edited bundle: one line, not a KeyError
    if bundle is not None and remote:
        raise CheckpointError(
            f"cannot resume {str(resume)!r}: exact resume needs collector.num_workers=1 and "
            f"collector.backend=process, got {workers} and {cfg.collector.backend!r} (the "
            "workers' env and RNG states are not checkpointed)"
        )
    if resume is not None and overwrite and Path(resume).resolve().parent == out.resolve():
        raise ValueError(
            f"--overwrite would delete {str(resume)!r}, the checkpoint being resumed; drop "
            "--overwrite to continue the run in its folder"
        )
    folder = RunFolder(out, resume, overwrite).acquire()
    started = False

    def on_start() -> None:
        nonlocal started
        started = True

    try:
        return _train_loop(cfg, out, bundle, resume, progress, on_start, keep_replay)
    except BaseException:
        if not started:
            folder.abandon()  # a run that never started leaves nothing behind
        raise
    finally:
        folder.release()


def _train_loop(
    cfg: Config,
    out: Path,
    bundle: dict[str, Any] | None,
    resume: str | os.PathLike | None,
    progress: bool,
    on_start: Any,
    keep_replay: bool = True,
) -> dict[str, Any]:
    """:func:`train` once its inputs are checked and ``out`` is held: build the run (or restore it
    from ``bundle``), then, batch by batch until ``train.total_frames``, store the transitions
    (:meth:`_Run.store`), learn (:meth:`_Run.learn`), log and checkpoint (:meth:`_Run.report`)."""
    t = cfg.train
    save_config_yaml(cfg, out / "config.yaml")
    run = _build_run(cfg, out, bundle, resume)
    threads = torch.get_num_threads()
    with warnings.catch_warnings():  # TorchRL's note that the last batch may pass total_frames
        warnings.filterwarnings("ignore", message=r"total_frames \(\d+\) is not exactly divisible")
        run.collector = make_collector(
            cfg,
            run.env,
            run.behaviour,
            max(t.total_frames - run.counters["frames"], 0) * t.seeds,
            seeds=t.seeds,
        )
    pbar = loggers = None
    try:  # shut the worker processes down on any exit
        if bundle is not None:  # after the collector's own reset and policy probe
            _restore_collection(run, bundle, resume)
        loggers = RunLoggers(t.logger, out)
        pbar = progress_bar(
            total=t.total_frames,
            initial=run.counters["frames"],
            disable=not progress,
            desc="train",
            unit="frame",
        )
        start_time, last_log = time.perf_counter(), {}
        on_start()
        with _StopSignals() as stop:
            try:
                for batch in run.collector:
                    frames_before = run.store(batch)
                    run.learn()
                    per_seed = batch.numel() // t.seeds
                    pbar.update(min(per_seed, max(pbar.total - pbar.n, 0)))  # ends at total
                    row = run.report(frames_before, stop, loggers, pbar, start_time)
                    if row is not None:
                        last_log = row
                pbar.close()
                final = out / "final.pt"  # a first signal from here on: the run ends normally
                run.save(final, replay=keep_replay)
                if t.seeds == 1:
                    write_heads(out / HEADS_NAME, run.learner.eval_heads, cfg, run.counters)
                    write_informed(out, run.learner.eval_heads, cfg, run.counters)
                else:  # the batch's final.pt resumes; each seed<k>/ evaluates
                    seed_finals = run.write_seed_bundles()
            except KeyboardInterrupt:
                raise KeyboardInterrupt(
                    f"aborted by a second signal; nothing written, "
                    f"{_last_checkpoint_note(run.last_checkpoint)}"
                ) from None
    finally:
        if pbar is not None:
            pbar.close()  # before any message: the bar's last line does not run into it
        if loggers is not None:
            loggers.close()  # TensorBoard, W&B and MLflow write their last rows here
        run.collector.shutdown()
        torch.set_num_threads(threads)  # MultiSyncCollector.shutdown adds num_workers threads
    result = {
        "final": final,
        "frames": run.counters["frames"],
        "updates": run.counters["updates"],
        "seconds": time.perf_counter() - start_time,
        "last_log": last_log,
    }
    if t.seeds > 1:
        result["seeds"] = seed_finals
    return result


@dataclasses.dataclass
class _Run:
    """One training run between batches: what :func:`_build_run` builds from the config (or a
    checkpoint), and the steps :func:`_train_loop` takes on every collected batch."""

    cfg: Config
    out: Path
    env: TransformedEnv
    learner: MultiHeadLearner
    behaviour: BehaviourPolicy
    buffers: list[ReplayBuffer]  # one per seed (train.seeds), sampled with its own generator
    first_visit: FirstVisitFilter
    replay_generators: list[torch.Generator]
    counters: dict[str, int]  # frames: per seed (every seed steps the same number)
    stats: dict[str, torch.Tensor]  # device-side episode statistics since the last log row
    collector: BaseCollector | None = None
    last_checkpoint: Path | None = None  # the newest periodic checkpoint in ``out``

    @property
    def seeds(self) -> int:
        """How many independent runs this one is (``train.seeds``)."""
        return len(self.buffers)

    def store(self, batch: TensorDictBase) -> int:
        """Replay ``batch``'s raw transitions (first visits only with ``train.first_visit``) and
        add its finished episodes to the statistics; returns the frame count before it."""
        t = self.cfg.train
        if self.cfg.collector.backend == "ray":
            # (W, n, T) from W actors -> (N, T): worker w's rows [w n, (w+1) n)
            batch = batch.reshape(-1, batch.shape[-1])
        if collects_in_workers(self.cfg):
            batch = batch.exclude("collector")  # MultiSyncCollector's trajectory ids
        counters, stats = self.counters, self.stats
        S = self.seeds
        frames_before = counters["frames"]
        counters["frames"] += batch.numel() // S  # per seed
        counters["batches"] += 1
        if t.n_step > 1:  # multi-step windows, within this batch (heads/nstep.py)
            batch = nstep_returns(
                batch.copy(), self.learner.loss.subtasks, t.gamma, t.n_step, BEHAVIOUR
            )  # a shallow copy: the collector's own batch is left as it was
        keep = self.first_visit(batch) if t.first_visit else None  # (N, T): first visits
        n = batch.shape[0] // S  # seed s owns sub-envs [s n, (s + 1) n) (set_seed_blocks)
        for s, buffer in enumerate(self.buffers):
            rows = batch if S == 1 else batch[s * n : (s + 1) * n]
            raw = replay_rows(self.cfg, rows)
            if keep is not None:  # one sample per (s, a) per episode
                raw = raw[(keep if S == 1 else keep[s * n : (s + 1) * n]).reshape(-1)]
            stored = raw.batch_size[0]  # (TensorDict.numel() of an empty batch is 1, not 0)
            if stored:  # else every transition a repeat (a greedy loop): nothing new to store
                buffer.extend(raw)
            counters["stored"] += stored
        done = batch.get((keys.NEXT, keys.DONE)).squeeze(-1)  # (N, T)
        ret = batch.get((keys.NEXT, EPISODE_REWARD)).squeeze(-1)  # (N, T)
        by_options = done & (batch.get(BEHAVIOUR) >= 0)
        stats["return_sum"] += (ret * done).sum()
        stats["episodes"] += done.sum()
        stats["return_sum_options"] += (ret * by_options).sum()
        stats["episodes_options"] += by_options.sum()
        if S > 1:  # each seed's own training return (its sub-envs' rows)
            stats["seed_return_sum"] += (ret * done).reshape(S, -1).sum(1)
            stats["seed_episodes"] += done.reshape(S, -1).sum(1)
        return frames_before

    def sample(self) -> TensorDictBase:
        """One replay sample for the learner: each seed's buffer sampled with its own generator,
        concatenated seed-major (``S`` groups of ``train.batch_size`` rows)."""
        if self.seeds == 1:
            return self.buffers[0].sample()
        return torch.cat([b.sample() for b in self.buffers])

    def learn(self) -> None:
        """Every head from one shared sample per update, ``train.updates_per_batch`` updates once
        past ``train.init_random_frames``; then the exploration rate for the frames played, and
        the new weights and epsilon to the collector workers before their next batch."""
        t = self.cfg.train
        filled = min(len(b) for b in self.buffers)
        if self.counters["frames"] >= t.init_random_frames and filled >= t.batch_size:
            self.learner.set_lr(lr_at(self.counters["frames"], t))
            for _ in range(t.updates_per_batch):
                self.learner.update(self.sample())
                self.counters["updates"] += 1
        self.behaviour.set_epsilon(epsilon_at(self.counters["frames"], t))
        if collects_in_workers(self.cfg):
            self.collector.update_policy_weights_(self.behaviour)

    def report(
        self,
        frames_before: int,
        stop: _StopSignals,
        logger: RunLoggers,
        pbar: Any,
        start_time: float,
    ) -> dict[str, float] | None:
        """After a batch: the log row (one host sync) when ``train.log_every`` frames were crossed
        or at the end, then a periodic checkpoint when ``train.checkpoint_every`` frames were
        crossed or a signal asks to stop (:class:`TrainingInterrupted`). Returns the row, if any."""
        t = self.cfg.train
        frames = self.counters["frames"]
        log_now = _crossed(frames_before, frames, t.log_every)
        checkpoint_now = _crossed(frames_before, frames, t.checkpoint_every)
        is_last = frames >= t.total_frames
        stop_now = stop.signum is not None and not is_last
        row = None
        if log_now or checkpoint_now or is_last:
            row = _log_row(
                self.learner,
                self.stats,
                self.behaviour,
                self.counters,
                logger,
                start_time,
                self.last_checkpoint,
                self.cfg.seed,
            )
            pbar.set_postfix({k: f"{v:.3g}" for k, v in row.items() if k.startswith("loss")})
        if _crossed(frames_before, frames, t.heads_every) and not is_last:  # learning curves
            seconds = time.perf_counter() - start_time
            for folder, heads, cfg in self.runs(self.learner.eval_heads):
                write_heads(
                    folder / HEADS_SNAPSHOTS / f"heads_{frames:09d}.pt",
                    heads,
                    cfg,
                    {**self.counters, "seconds": seconds},
                )
        if (checkpoint_now or stop_now) and not is_last:
            path = self.out / f"checkpoint_{frames:09d}.pt"
            self.save(path)
            if self.last_checkpoint is not None and self.last_checkpoint != path:
                self.last_checkpoint.unlink(missing_ok=True)  # keep the newest periodic one
            self.last_checkpoint = path
        if stop_now:
            remote = collects_in_workers(self.cfg)
            raise _interrupted(stop.signum, self.last_checkpoint, self.out, self.counters, remote)
        return row

    def save(self, path: Path, replay: bool = True) -> None:
        """Write the whole run state (:meth:`bundle`) to ``path`` (``replay=False``: without the
        replay buffer); a non-finite model is never written."""
        _require_finite(self.learner, self.counters["frames"], self.last_checkpoint, self.cfg)
        save_checkpoint(path, self.bundle(replay))

    def runs(self, heads: Heads) -> list[tuple[Path, Heads, Config]]:
        """``(folder, heads, config)`` of each run: ``out`` itself for one seed, else
        ``out/seed<k>`` with seed ``k``'s heads cut out of ``heads`` (heads/seeds.py) and its
        single-seed config (``seed + k``, ``train.seeds = 1``)."""
        if self.seeds == 1:
            return [(self.out, heads, self.cfg)]
        spec = self.learner.heads.spec
        out = []
        for k in range(self.seeds):
            cfg_k = seed_config(self.cfg, k)
            one = split_seed(heads, k, build_heads(cfg_k, spec))
            one.spec = spec
            out.append((self.out / f"seed{k}", one.eval(), cfg_k))
        return out

    def write_seed_bundles(self) -> list[Path]:
        """Each seed's ``seed<k>/`` in today's single-seed layout: ``config.yaml``, ``final.pt``
        (its online and, with ``train.eval_ema_tau``, evaluation heads; marked as a member of
        this batch: it evaluates, it does not resume alone) and ``heads.pt``."""
        learner = self.learner
        online = self.runs(learner.heads)
        evals = self.runs(learner.eval_heads) if learner.eval_heads is not learner.heads else None
        finals = []
        for k, (folder, heads, cfg_k) in enumerate(online):
            folder.mkdir(parents=True, exist_ok=True)
            save_config_yaml(cfg_k, folder / "config.yaml")
            models = {"heads": heads}
            if evals is not None:
                models[EVAL_HEADS] = evals[k][1]
            bundle = make_bundle(
                cfg_k,
                models=models,
                counters=dict(self.counters),
                rng={},
                heads_spec=learner.heads.spec.to_dict(),
                batch_member={"seed_index": k, "seeds": self.seeds},
            )
            finals.append(save_checkpoint(folder / "final.pt", bundle))
            write_heads(folder / HEADS_NAME, models.get(EVAL_HEADS, heads), cfg_k, self.counters)
            write_informed(folder, models.get(EVAL_HEADS, heads), cfg_k, self.counters)
        return finals

    def bundle(self, replay: bool = True) -> dict[str, Any]:
        """The checkpoint of the run: every head, target and optimiser, the learner's counters,
        replay, first-visit filter, statistics and RNG, and (one collector process) the env's
        simulator state and the collector's carried tensordict."""
        learner = self.learner
        single = not collects_in_workers(self.cfg)  # else the env states live in the workers
        return make_bundle(
            self.cfg,
            models=_models(learner),
            optimizers={"adam": learner.optimizer},
            counters=dict(self.counters),
            rng=rng_state(_replay_rngs(self.replay_generators)),
            replay=_replay_states(self.buffers) if replay else None,
            learner={
                k: v for k, v in learner.state_dict().items() if k not in ("targets", "optimizer")
            },
            env=self.env.base_env.state_dict() if single else None,
            carrier=_collector_carrier(self.collector).to_dict() if single else None,
            first_visit=self.first_visit.state_dict(),
            stats={k: v.clone() for k, v in self.stats.items()},
            heads_spec=learner.heads.spec.to_dict(),
        )


def replay_rows(cfg: Config, batch: TensorDictBase) -> TensorDictBase:
    """The raw transitions a run of ``cfg`` replays from a collector batch ``(N, T)``: the hidden
    instance kept for the ``instance`` max-value estimator and the informed head, its ``next``
    copy for the informed head (it reads the features at ``s'``)."""
    informed = cfg.heads.informed
    instance = cfg.train.max_value_estimator == "instance" or informed
    return raw_transitions(batch, keep_instance=instance, keep_next_instance=informed)


def write_informed(folder: Path, heads: Heads, cfg: Config, counters: dict[str, int]) -> None:
    """``folder/informed.pt``, the informed baseline's bundle, from the bundle's informed head
    (its evaluation weights), where the run trained one (``heads.informed``)."""
    if heads.has(INFORMED):
        spec = heads.spec
        save_informed_head(
            baseline_path(folder / "final.pt", INFORMED),
            heads.heads[INFORMED],
            spec.obs_dim,
            spec.num_actions,
            cfg,
            counters=dict(counters),
            averaging=heads.heads["averaging"] if heads.has("averaging") else None,
        )


def seed_config(cfg: Config, k: int) -> Config:
    """Seed ``k`` of a ``train.seeds`` batch as a single-seed config: ``seed + k``, one seed."""
    return dataclasses.replace(
        cfg, seed=cfg.seed + k, train=dataclasses.replace(cfg.train, seeds=1)
    )


def _replay_rngs(generators: list[torch.Generator]) -> dict[str, torch.Generator]:
    """The replay generators by checkpoint name: ``replay`` (seed 0, as a one-seed run names
    it), then ``replay1``, ``replay2``..."""
    return {("replay" if k == 0 else f"replay{k}"): g for k, g in enumerate(generators)}


def _replay_states(buffers: list[ReplayBuffer]) -> dict[str, Any]:
    """The replay entry of a checkpoint: one buffer's state, or ``{"seeds": [...]}``."""
    if len(buffers) == 1:
        return replay_state(buffers[0])
    return {"seeds": [replay_state(b) for b in buffers]}


def _models(learner: MultiHeadLearner) -> dict[str, torch.nn.Module]:
    """The networks of a training checkpoint: the online heads, their targets and, with
    ``train.eval_ema_tau``, the Polyak-averaged ``eval_heads`` evaluation reads
    (:func:`~taskvar_torch.factory.load_heads`)."""
    models = {"heads": learner.heads, "targets": learner.loss.target_heads}
    if learner.eval_heads is not learner.heads:
        models[EVAL_HEADS] = learner.eval_heads
    return models


def _build_run(
    cfg: Config,
    out: Path,
    bundle: dict[str, Any] | None,
    resume: str | os.PathLike | None = None,
) -> _Run:
    """Everything from the config, seeded (the networks' initialisation draws from the global
    torch stream, in this order), then overwritten with ``bundle``'s state (read from
    ``resume``) when resuming, once every entry is checked against what was built."""
    t = cfg.train
    S = t.seeds
    torch.manual_seed(cfg.seed)
    replay_generators = [
        torch.Generator(device="cpu").manual_seed(cfg.seed + k + 1) for k in range(S)
    ]
    workers = cfg.collector.num_workers
    env = make_training_env(cfg, num_envs=cfg.env.num_envs * S // workers)  # workers > 1: specs
    subtasks = make_subtasks(cfg, env.base_env)
    if S == 1:
        heads = build_heads(cfg, env, subtasks)
    else:  # seed k's networks initialised as its one-seed run's, then stacked (heads/seeds.py)
        if not hasattr(env.base_env, "set_seed_blocks"):
            raise ValueError(
                f"train.seeds={S} needs a family env with set_seed_blocks (envs/batched.py "
                f"BatchedFamilyEnv); {type(env.base_env).__name__} has none"
            )
        env.base_env.set_seed_blocks([cfg.seed + k for k in range(S)])
        runs = []
        for k in range(S):
            cfg_k = seed_config(cfg, k)
            torch.manual_seed(cfg_k.seed)
            one_env = make_training_env(cfg_k)
            runs.append(build_heads(cfg_k, one_env, make_subtasks(cfg_k, one_env.base_env)))
        heads = stack_seeds(runs)
        heads.spec = runs[0].spec
        torch.manual_seed(cfg.seed)  # exploration: one stream for the batch
    learner = make_learner(cfg, heads, subtasks)
    behaviour = BehaviourPolicy(
        heads,
        subtasks,
        env.action_spec,
        option_prob=t.option_behaviour_prob,
        root_policy=t.hierarchy_root_policy,
        option_coverage=t.option_coverage,
    )
    buffers = [make_replay_buffer(cfg, g) for g in replay_generators]
    obs_dim = env.observation_spec[keys.OBSERVATION].shape[-1]
    first_visit = FirstVisitFilter(cfg.env.num_envs * S, obs_dim, device=cfg.device)
    stats = {
        "return_sum": torch.zeros((), device=cfg.device),
        "episodes": torch.zeros((), device=cfg.device),
        "return_sum_options": torch.zeros((), device=cfg.device),
        "episodes_options": torch.zeros((), device=cfg.device),
    }
    if S > 1:
        stats["seed_return_sum"] = torch.zeros(S, device=cfg.device)
        stats["seed_episodes"] = torch.zeros(S, device=cfg.device)
    run = _Run(
        cfg=cfg,
        out=out,
        env=env,
        learner=learner,
        behaviour=behaviour,
        buffers=buffers,
        first_visit=first_visit,
        replay_generators=replay_generators,
        counters={"frames": 0, "updates": 0, "batches": 0, "stored": 0},
        stats=stats,
    )
    if bundle is not None:
        _check_resume_state(run, bundle, resume)  # every entry, before any is loaded
        load_state_dicts(bundle, models=_models(learner), optimizers={"adam": learner.optimizer})
        learner.load_state_dict(
            {
                **bundle["learner"],
                "targets": bundle["models"]["targets"],
                "optimizer": bundle["optimizers"]["adam"],
            }
        )
        replays = bundle["replay"]["seeds"] if S > 1 else [bundle["replay"]]
        for buffer, state in zip(buffers, replays):
            load_replay_state(buffer, state)
        first_visit.load_state_dict(bundle["first_visit"])
        run.counters.update(bundle["counters"])
        run.stats = {k: v.to(cfg.device) for k, v in bundle["stats"].items()}
    behaviour.set_epsilon(epsilon_at(run.counters["frames"], t))
    return run


def _check_resume_state(run: _Run, bundle: dict[str, Any], resume: str | os.PathLike) -> None:
    """:class:`CheckpointError` (one line naming the entry and both shapes or types) unless every
    entry a resume loads fits what the config built: the networks' tensors, the optimiser state
    (shapes included: the fused Adam does not check them), the learner's and run's counters
    (non-negative integers), the RNG states, the replay rows, the first-visit flags, the
    statistics, the collector's carrier (the env state: :func:`_restore_collection`)."""
    learner, t = run.learner, run.cfg.train
    live_learner = {
        k: v for k, v in learner.state_dict().items() if k not in ("targets", "optimizer")
    }
    live_learner["loss_sum"] = None  # None, or each loss's running sum (checked below)
    try:
        check_like(
            bundle["models"], {k: m.state_dict() for k, m in _models(learner).items()}, "models"
        )
        check_like(bundle["optimizers"], {"adam": None}, "optimizers")
        check_optimizer_state(bundle["optimizers"]["adam"], learner.optimizer, "optimizers['adam']")
        check_like(bundle["learner"], live_learner, "learner")
        for k in ("num_updates", "loss_count"):
            check_counter(bundle["learner"][k], f"learner[{k!r}]")
        params = sum(len(g["params"]) for g in learner.optimizer.param_groups)
        states = len(bundle["optimizers"]["adam"]["state"])
        want = params if bundle["learner"]["num_updates"] > 0 else 0  # every update steps all
        if states != want:
            raise CheckpointError(
                f"optimizers['adam']['state'] holds {states} parameters' state, expected {want} "
                f"after {bundle['learner']['num_updates']} updates"
            )
        loss_sum = bundle["learner"]["loss_sum"]
        if loss_sum is not None and not (
            isinstance(loss_sum, dict)
            and all(isinstance(v, torch.Tensor) and v.numel() == 1 for v in loss_sum.values())
        ):
            raise CheckpointError("learner['loss_sum'] is not a dict of scalar losses")
        check_counters(bundle["counters"], run.counters)
        check_rng_state(bundle["rng"], _replay_rngs(run.replay_generators))
        batch = _probe_batch(run)  # (N, 2), as the collector gives it
        stored = batch.copy()
        if t.n_step > 1:  # the n-step keys, as _Run.store adds them
            subtasks = learner.loss.subtasks
            stored = nstep_returns(stored, subtasks, t.gamma, t.n_step, BEHAVIOUR)
        rows = replay_rows(run.cfg, stored)
        if run.seeds == 1:
            check_replay_state(bundle["replay"], rows, t.buffer_size)
        else:
            check_like(bundle["replay"], {"seeds": [None] * run.seeds}, "replay")
            for k, state in enumerate(bundle["replay"]["seeds"]):
                check_replay_state(state, rows, t.buffer_size, f"replay['seeds'][{k}]")
        check_like(bundle["first_visit"], run.first_visit.state_dict(), "first_visit")
        check_like(bundle["stats"], run.stats, "stats")
        check_like(bundle["carrier"], batch[:, -1].exclude(keys.NEXT).to_dict(), "carrier")
    except CheckpointError as e:
        raise CheckpointError(
            f"checkpoint {str(resume)!r} does not fit the run its config builds: {e}"
        ) from None


def _probe_batch(run: _Run) -> TensorDictBase:
    """A collector batch ``(N, 2)`` as this run collects them: two steps of a fresh env of the
    run's size under its behaviour policy (draws from the global torch stream, which a resume
    restores afterwards)."""
    probe = make_training_env(run.cfg, num_envs=run.env.batch_size[0])
    return probe.rollout(2, policy=run.behaviour, break_when_any_done=False)


def _restore_collection(run: _Run, bundle: dict[str, Any], resume: str | os.PathLike) -> None:
    """The checkpoint's env simulator state, collector carrier and replay RNG (after the
    collector's own reset and policy probe), and the logs up to the checkpoint, without the rows a
    stopped run wrote after it; a periodic checkpoint of ``out`` is replaced by the next one."""
    carrier = _collector_carrier(run.collector)
    try:
        check_like(bundle["env"], run.env.base_env.state_dict(), "env")
        run.env.base_env.load_state_dict(bundle["env"])  # its values' ranges: one line
    except (CheckpointError, ValueError) as e:
        raise CheckpointError(
            f"checkpoint {str(resume)!r} does not fit the run its config builds: {e}"
        ) from None
    carrier.update(TensorDict(bundle["carrier"], batch_size=run.env.batch_size))
    set_rng_state(bundle["rng"], _replay_rngs(run.replay_generators))
    _restore_logs(Path(resume).parent, run.out, run.counters["frames"])
    if Path(resume).parent.resolve() == run.out.resolve() and Path(resume).name.startswith(
        "checkpoint_"
    ):
        run.last_checkpoint = Path(resume)


LOGGER_EXTRAS = ("tensorboard", "wandb", "mlflow")
"""``train.logger`` values beyond ``csv``: each needs the package (and pip extra) of its name."""


def check_logger(kind: str) -> None:
    """Raise a one-line ``ValueError`` naming the extra when ``train.logger``'s package is
    missing (checked before a run writes anything)."""
    if kind in LOGGER_EXTRAS and not _installed(kind):
        raise ValueError(
            f"train.logger={kind} needs the {kind} package: pip install 'taskvar-torch[{kind}]'"
        )


def _installed(package: str) -> bool:
    """Whether ``package`` can be imported (found, not imported)."""
    return importlib.util.find_spec(package) is not None


class RunLoggers:
    """Where a run's log rows go, every logger built by TorchRL's ``get_logger``: always the CSV
    files ``out/logs/scalars/<name>.csv`` (one ``frame,value`` row per log row; a resume cuts them
    back to its checkpoint), and with ``train.logger`` = tensorboard, wandb or mlflow the same
    scalars at the same frames to that logger too: TensorBoard event files in
    ``out/logs/tensorboard``, a W&B run saved under ``out/logs`` (``WANDB_PROJECT``,
    ``WANDB_MODE=offline`` as usual), an MLflow run in the file store ``out/logs/mlruns``."""

    def __init__(self, kind: str, out: Path) -> None:
        check_logger(kind)
        logs = out / "logs"
        self.loggers: list[Logger] = [get_logger("csv", str(out), "logs")]
        if kind == "tensorboard":
            self.loggers.append(get_logger("tensorboard", str(logs), "tensorboard"))
        elif kind == "wandb":
            self.loggers.append(get_logger("wandb", str(logs), out.resolve().name))
        elif kind == "mlflow":
            self.loggers.append(get_logger("mlflow", str(logs / "mlruns"), out.resolve().name))

    def log_scalar(self, name: str, value: float, step: int) -> None:
        """Log ``value`` of scalar ``name`` at frame ``step`` to every logger."""
        for logger in self.loggers:
            logger.log_scalar(name, value, step=step)

    def close(self) -> None:
        """Flush and close every logger (TensorBoard, W&B and MLflow write their last rows)."""
        for logger in self.loggers:
            logger.close()


def _crossed(before: int, after: int, every: int) -> bool:
    """Whether a multiple of ``every`` lies in ``(before, after]`` (``every = 0``: never)."""
    return every > 0 and after // every > before // every


def _log_row(
    learner: MultiHeadLearner,
    stats: dict[str, torch.Tensor],
    behaviour: BehaviourPolicy,
    counters: dict[str, int],
    logger: RunLoggers,
    start_time: float,
    last_checkpoint: Path | None = None,
    first_seed: int = 0,
) -> dict[str, float]:
    """Log one row (a value per scalar, to every logger); raise :class:`TrainingDiverged` on a
    non-finite loss."""
    seeds = learner.loss.seeds
    try:
        row = learner.pop_losses()
    except FloatingPointError as e:
        which = ""
        if seeds > 1:
            bad = [first_seed + k for k in _non_finite_seeds(learner, seeds)]
            if bad:
                which = f" (non-finite weights in seed{'s' if len(bad) > 1 else ''} "
                which += f"{', '.join(map(str, bad))})"
        raise TrainingDiverged(
            f"{e}{which}; stopped at frame {counters['frames']}, "
            f"{_last_checkpoint_note(last_checkpoint)}"
        ) from None
    if seeds > 1:  # the learner's losses add the seeds' own: log their mean
        row = {k: v / seeds for k, v in row.items()}
    per_seed = {k: stats[k].tolist() for k in ("seed_return_sum", "seed_episodes") if k in stats}
    s = {k: float(v) for k, v in stats.items() if k not in per_seed}  # host sync, once per row
    for v in stats.values():
        v.zero_()
    if s["episodes"] > 0:
        row["episode_return"] = s["return_sum"] / s["episodes"]
    if s["episodes_options"] > 0:
        row["episode_return_options"] = s["return_sum_options"] / s["episodes_options"]
    row["episodes"] = s["episodes"]
    if per_seed:  # train.seeds > 1: each seed's own training return
        for k, (r, n) in enumerate(zip(per_seed["seed_return_sum"], per_seed["seed_episodes"])):
            if n > 0:
                row[f"episode_return_seed{k}"] = r / n
    row["epsilon"] = behaviour.epsilon
    row["updates"] = float(counters["updates"])
    row["seconds"] = time.perf_counter() - start_time
    for k, v in row.items():
        logger.log_scalar(k, v, step=counters["frames"])
    return row


__all__ = [
    "LOGGER_EXTRAS",
    "RunLoggers",
    "TrainingDiverged",
    "check_logger",
    "epsilon_at",
    "lr_at",
    "train",
]
