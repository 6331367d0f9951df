"""The training loop of the heads and of every baseline, and the learning step every loop shares
(paper §3.1-3.4; docs/design.md#training-loops).

:func:`collect_and_learn` is the one loop over a TorchRL collector, driving a :class:`Run` whose
:class:`Learner` is the varying part. Every loop explores at :func:`epsilon_at` and steps through
:func:`update_phase` at :func:`lr_at` once :func:`learning_started`; :func:`non_finite` is the
divergence check before a model is written.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any, Protocol

import torch
from tensordict import TensorDictBase

from taskvar_torch.config import TrainConfig
from taskvar_torch.training.allocator import keep_freed_memory


class TrainingDiverged(RuntimeError):
    """A loss or a weight became NaN or infinite; no checkpoint holding it is ever written, so the
    last checkpoint on disk is intact."""


class Learner(Protocol):
    """What a run asks of its learner: one gradient step on a replay sample, and the learning rate
    (``MultiHeadLearner``, ``BaselineLearner``).
    """

    def update(self, sample: TensorDictBase) -> Any:
        """One gradient step on ``sample``; returns its (detached) losses."""

    def set_lr(self, lr: float) -> None:
        """The Adam learning rate from the next update on."""


class Run(Protocol):
    """What :func:`collect_and_learn` asks of a run: its counters, and the two steps it takes on
    every collected batch."""

    counters: dict[str, int]  # "frames": per seed, "updates"

    def store(self, batch: TensorDictBase) -> int:
        """Replay a collected batch and count its frames; returns the frame count before it."""

    def learn(self) -> None:
        """The learning after it (:func:`learn_batch` on the run's learner), then the exploration
        rate for the frames played."""


def collect_and_learn(
    run: Run,
    collector: Iterable[TensorDictBase],
    pbar: Any,
    report: Callable[[int], dict[str, float] | None],
) -> dict[str, float]:
    """The training loop: every batch of ``collector`` stored, learnt from, counted on ``pbar`` and
    reported on (``report(frames before the batch)``); returns the last row reported (``{}``: none).
    """
    last = {}
    for batch in collector:
        frames_before = run.store(batch)
        run.learn()
        played = run.counters["frames"] - frames_before
        pbar.update(min(played, max(pbar.total - pbar.n, 0)))  # the bar ends at its total
        row = report(frames_before)
        if row is not None:
            last = row
    pbar.close()
    return last


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


def learning_started(frames: int, filled: int, t: TrainConfig) -> bool:
    """Whether gradient steps are taken: ``train.init_random_frames`` played and a sample's
    ``train.batch_size`` rows in replay (``filled``)."""
    return frames >= t.init_random_frames and filled >= t.batch_size


def update_phase(
    learner: Learner,
    sample: Callable[[], TensorDictBase],
    updates: int,
    lr: float | None = None,
) -> Any:
    """``updates`` gradient steps of ``learner`` on fresh ``sample()`` s at ``lr`` (``None``: as it
    is); returns the last step's losses (``None``: no step).
    """
    keep_freed_memory()
    if lr is not None:
        learner.set_lr(lr)
    losses = None
    for _ in range(updates):
        losses = learner.update(sample())
    return losses


def learn_batch(
    learner: Learner,
    sample: Callable[[], TensorDictBase],
    frames: int,
    filled: int,
    t: TrainConfig,
) -> Any:
    """The learning after one collected batch: ``train.updates_per_batch`` steps at :func:`lr_at`
    once :func:`learning_started`; returns the last losses or ``None``.
    """
    if not learning_started(frames, filled, t):
        return None
    return update_phase(learner, sample, t.updates_per_batch, lr_at(frames, t))


def non_finite(groups: dict[str, Iterable[torch.Tensor]]) -> list[str]:
    """Which of the named groups of tensors (weights, targets, optimiser state) hold a NaN or
    infinite value; one host sync for all of them."""
    names, flags = [], []
    for name, tensors in groups.items():
        finite = [torch.isfinite(t).all() for t in tensors if t.is_floating_point()]
        if finite:
            names.append(name)
            flags.append(torch.stack(finite).all())
    ok = torch.stack(flags).tolist() if flags else []
    return [n for n, good in zip(names, ok) if not good]


__all__ = [
    "Learner",
    "Run",
    "collect_and_learn",
    "TrainingDiverged",
    "epsilon_at",
    "learn_batch",
    "learning_started",
    "lr_at",
    "non_finite",
    "update_phase",
]
