"""The learning step every training loop shares (paper §3.1-3.4; docs/design.md, "Training loops").

Four loops learn: the heads' (:func:`~taskvar_torch.training.train`), the baselines'
(:func:`~taskvar_torch.train_recurrent.train_baseline`) and the Figure 4 protocol's learning phases
(``families/wargus/fig4_trial.py`` ``learning_phases``, ``fig4_recurrent.py`` ``learning_phase``).
Each plays epsilon-greedily at :func:`epsilon_at`, writes its replay, then takes its gradient
steps through :func:`update_phase`, on a :class:`Learner` (the heads' ``MultiHeadLearner`` or the
baselines' ``BaselineLearner``: the one varying part), learning rate :func:`lr_at`, once
:func:`learning_started`. :func:`learn_batch` is the step after each collected batch of the two
collector loops; :func:`non_finite` the divergence check before a model is written.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any, Protocol

import torch
from tensordict import TensorDictBase

from taskvar_torch.allocator import keep_freed_memory
from taskvar_torch.config import TrainConfig


class TrainingDiverged(RuntimeError):
    """A loss or a weight became NaN or infinite; no checkpoint holding it is ever written, so the
    last checkpoint on disk is intact."""


class Learner(Protocol):
    """What a loop asks of a learner: one gradient step on a replay sample, and the learning rate.

    :class:`~taskvar_torch.heads.learner.MultiHeadLearner` (every head from one shared sample) and
    :class:`~taskvar_torch.train_recurrent.BaselineLearner` (a baseline's ``DQNLoss``) are two."""

    def update(self, sample: TensorDictBase) -> Any:
        """One gradient step on ``sample``; returns its (detached) losses."""

    def set_lr(self, lr: float) -> None:
        """The Adam learning rate from the next update on."""


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
    """``updates`` gradient steps of ``learner``, each on a fresh ``sample()``, at learning rate
    ``lr`` (``None``: as it is); returns the last step's losses (``None`` for no step). The first
    call of a process keeps glibc from returning freed memory to the OS between the steps
    (:func:`~taskvar_torch.allocator.keep_freed_memory`)."""
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
    """The learning after one collected batch, ``frames`` played and ``filled`` rows in replay:
    ``train.updates_per_batch`` steps at :func:`lr_at` once :func:`learning_started`; returns the
    last step's losses, ``None`` where no step was taken."""
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
    "TrainingDiverged",
    "epsilon_at",
    "learn_batch",
    "learning_started",
    "lr_at",
    "non_finite",
    "update_phase",
]
