"""One training run of the heads between collected batches (paper §3.1-3.4; docs/design.md).

:class:`TrainingRun` holds what :func:`~taskvar_torch.training.run_setup.build_run` builds and takes
the per-batch steps: :meth:`~TrainingRun.store`, :meth:`~TrainingRun.learn`,
:meth:`~TrainingRun.report`; :meth:`~TrainingRun.bundle` is its whole checkpoint.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.collectors import BaseCollector, Collector
from torchrl.data import ReplayBuffer
from torchrl.envs import TransformedEnv

from taskvar_torch import keys
from taskvar_torch.checkpoint import (
    EVAL_HEADS,
    make_bundle,
    rng_state,
    save_checkpoint,
)
from taskvar_torch.config import Config, save_config_yaml
from taskvar_torch.factory import HEADS_NAME, build_heads, write_heads
from taskvar_torch.heads.behaviour import BEHAVIOUR, BehaviourPolicy
from taskvar_torch.heads.bundle import Heads
from taskvar_torch.heads.first_visit import FirstVisitFilter
from taskvar_torch.heads.learner import MultiHeadLearner
from taskvar_torch.heads.nstep import nstep_returns
from taskvar_torch.heads.seeds import split_seed
from taskvar_torch.run_folder import StopSignals, _interrupted, last_checkpoint_note
from taskvar_torch.training.collection import collects_in_workers
from taskvar_torch.training.learning import TrainingDiverged, epsilon_at, learn_batch, non_finite
from taskvar_torch.training.replay import EPISODE_REWARD, raw_transitions, replay_state, sample_many
from taskvar_torch.training.run_logs import RunLoggers

HEADS_SNAPSHOTS = "heads"
"""Folder of a run's ``train.heads_every`` snapshots (``heads_<frames>.pt``)."""


def collector_carrier(collector: Collector) -> TensorDictBase:
    # TorchRL's Collector keeps the current step's tensordict (observations, carried policy state
    # such as the behaviour mode, RewardSum's returns) in ``_carrier``; its state_dict does not
    # include it, so exact resume saves and restores it here.
    return collector._carrier


def _non_finite(learner: MultiHeadLearner) -> list[str]:
    """Which of heads, target heads and optimiser state hold a NaN or infinite value (one sync:
    :func:`~taskvar_torch.training.learning.non_finite`)."""
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
    return non_finite(groups)


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
            f"diverged (lower train.lr?); nothing written, {last_checkpoint_note(last)}"
        )


@dataclasses.dataclass
class TrainingRun:
    """One training run between batches: what :func:`~taskvar_torch.training.run_setup.build_run`
    builds, and the steps :func:`~taskvar_torch.training.train` takes on every collected batch.
    """

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
        return self.samples(1)[0]

    def samples(self, n: int) -> list[TensorDictBase]:
        """``n`` calls of :meth:`sample` at once (:func:`~taskvar_torch.training.replay.sample_many`: the
        same rows, one gather per buffer)."""
        if self.seeds == 1:
            return sample_many(self.buffers[0], n)
        return [torch.cat(parts) for parts in zip(*(sample_many(b, n) for b in self.buffers))]

    def learn(self) -> None:
        """``train.updates_per_batch`` updates from one shared sample each once learning started,
        then the exploration rate, and the new weights to the collector workers.
        """
        t = self.cfg.train
        filled = min(len(b) for b in self.buffers)
        phase: list[TensorDictBase] = []  # this phase's samples, drawn at its first update

        def sample() -> TensorDictBase:
            if not phase:
                phase.extend(reversed(self.samples(t.updates_per_batch)))
            return phase.pop()

        if learn_batch(self.learner, sample, self.counters["frames"], filled, t) is not None:
            self.counters["updates"] += t.updates_per_batch
        self.behaviour.set_epsilon(epsilon_at(self.counters["frames"], t))
        if collects_in_workers(self.cfg):
            self.collector.update_policy_weights_(self.behaviour)

    def report(
        self,
        frames_before: int,
        stop: StopSignals,
        logger: RunLoggers,
        pbar: Any,
        start_time: float,
    ) -> dict[str, float] | None:
        """After a batch: the log row every ``train.log_every`` frames (or at the end), then a
        checkpoint every ``train.checkpoint_every`` frames or on a stop signal; returns the row, if
        any.
        """
        t = self.cfg.train
        frames = self.counters["frames"]
        log_now = crossed(frames_before, frames, t.log_every)
        checkpoint_now = crossed(frames_before, frames, t.checkpoint_every)
        is_last = frames >= t.total_frames
        stop_now = stop.signum is not None and not is_last
        row = None
        if log_now or checkpoint_now or is_last:
            row = self.log_row(logger, start_time)
            pbar.set_postfix({k: f"{v:.3g}" for k, v in row.items() if k.startswith("loss")})
        if crossed(frames_before, frames, t.heads_every) and not is_last:  # learning curves
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

    def log_row(self, logger: RunLoggers, start_time: float) -> dict[str, float]:
        """Log one row to every logger; raise
        :class:`~taskvar_torch.training.learning.TrainingDiverged` on a non-finite loss.
        """
        learner, stats, counters = self.learner, self.stats, self.counters
        seeds = learner.loss.seeds
        try:
            row = learner.pop_losses()
        except FloatingPointError as e:
            which = ""
            if seeds > 1:
                bad = [self.cfg.seed + k for k in _non_finite_seeds(learner, seeds)]
                if bad:
                    which = f" (non-finite weights in seed{'s' if len(bad) > 1 else ''} "
                    which += f"{', '.join(map(str, bad))})"
            raise TrainingDiverged(
                f"{e}{which}; stopped at frame {counters['frames']}, "
                f"{last_checkpoint_note(self.last_checkpoint)}"
            ) from None
        if seeds > 1:  # the learner's losses add the seeds' own: log their mean
            row = {k: v / seeds for k, v in row.items()}
        per_seed = {
            k: stats[k].tolist() for k in ("seed_return_sum", "seed_episodes") if k in stats
        }
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
        row["epsilon"] = self.behaviour.epsilon
        row["updates"] = float(counters["updates"])
        row["seconds"] = time.perf_counter() - start_time
        for k, v in row.items():
            logger.log_scalar(k, v, step=counters["frames"])
        return row

    def save(self, path: Path, replay: bool = True) -> None:
        """Write the whole run state (:meth:`bundle`) to ``path`` (``replay=False``: without the
        replay buffer); a non-finite model is never written."""
        _require_finite(self.learner, self.counters["frames"], self.last_checkpoint, self.cfg)
        save_checkpoint(path, self.bundle(replay))

    def runs(self, heads: Heads) -> list[tuple[Path, Heads, Config]]:
        """``(folder, heads, config)`` of each run: ``out`` for one seed, else ``out/seed<k>`` with
        seed ``k``'s heads and single-seed config.
        """
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
        """Each seed's ``seed<k>/`` in the single-seed layout: ``config.yaml``, ``final.pt``
        (evaluates, does not resume alone) and ``heads.pt``.
        """
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
        return finals

    def bundle(self, replay: bool = True) -> dict[str, Any]:
        """The checkpoint of the run: everything it holds, with the env's state and the collector's
        carrier where there is one collector process.
        """
        learner = self.learner
        single = not collects_in_workers(self.cfg)  # else the env states live in the workers
        return make_bundle(
            self.cfg,
            models=run_models(learner),
            optimizers={"adam": learner.optimizer},
            counters=dict(self.counters),
            rng=rng_state(replay_rngs(self.replay_generators)),
            replay=_replay_states(self.buffers) if replay else None,
            learner={
                k: v for k, v in learner.state_dict().items() if k not in ("targets", "optimizer")
            },
            env=self.env.base_env.state_dict() if single else None,
            carrier=collector_carrier(self.collector).to_dict() if single else None,
            first_visit=self.first_visit.state_dict(),
            stats={k: v.clone() for k, v in self.stats.items()},
            heads_spec=learner.heads.spec.to_dict(),
        )


def replay_rows(cfg: Config, batch: TensorDictBase) -> TensorDictBase:
    """The raw transitions a run of ``cfg`` replays from a collector batch ``(N, T)``: the hidden
    instance kept for the ``instance`` max-value estimator."""
    instance = cfg.train.max_value_estimator == "instance"
    return raw_transitions(batch, keep_instance=instance)


def seed_config(cfg: Config, k: int) -> Config:
    """Seed ``k`` of a ``train.seeds`` batch as a single-seed config: ``seed + k``, one seed."""
    return dataclasses.replace(
        cfg, seed=cfg.seed + k, train=dataclasses.replace(cfg.train, seeds=1)
    )


def replay_rngs(generators: list[torch.Generator]) -> dict[str, torch.Generator]:
    """The replay generators by checkpoint name: ``replay`` (seed 0, as a one-seed run names
    it), then ``replay1``, ``replay2``..."""
    return {("replay" if k == 0 else f"replay{k}"): g for k, g in enumerate(generators)}


def _replay_states(buffers: list[ReplayBuffer]) -> dict[str, Any]:
    """The replay entry of a checkpoint: one buffer's state, or ``{"seeds": [...]}``."""
    if len(buffers) == 1:
        return replay_state(buffers[0])
    return {"seeds": [replay_state(b) for b in buffers]}


def run_models(learner: MultiHeadLearner) -> dict[str, torch.nn.Module]:
    """The networks of a training checkpoint: the online heads, their targets and, with
    ``train.eval_ema_tau``, the ``eval_heads``.
    """
    models = {"heads": learner.heads, "targets": learner.loss.target_heads}
    if learner.eval_heads is not learner.heads:
        models[EVAL_HEADS] = learner.eval_heads
    return models


def crossed(before: int, after: int, every: int) -> bool:
    """Whether a multiple of ``every`` lies in ``(before, after]`` (``every = 0``: never)."""
    return every > 0 and after // every > before // every


__all__ = [
    "HEADS_SNAPSHOTS",
    "TrainingRun",
    "collector_carrier",
    "replay_rngs",
    "replay_rows",
    "run_models",
    "seed_config",
]
