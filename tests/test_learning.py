"""The learning step every training loop shares (``taskvar_torch/training/learning.py``): when it starts,
how many gradient steps it takes, on which samples and at which learning rate; the divergence
check; and both learners meeting the ``Learner`` protocol the loops call."""

from __future__ import annotations

import dataclasses
import math

import torch
from tensordict import TensorDict

from taskvar_torch.config import load_config
from taskvar_torch.training.baselines import BaselineLearner, build_for_training
from taskvar_torch.training.learning import (
    learn_batch,
    learning_started,
    lr_at,
    non_finite,
    update_phase,
)

CONFIG = "configs/windy.yaml"


class Recording:
    """A learner that records what the loop asks of it."""

    def __init__(self) -> None:
        self.samples: list[int] = []
        self.lrs: list[float] = []

    def update(self, sample):
        self.samples.append(int(sample["i"]))
        return {"loss": float(len(self.samples))}

    def set_lr(self, lr: float) -> None:
        self.lrs.append(lr)


def counter():
    """``sample()`` giving 0, 1, 2, ... (which draw each update got)."""
    n = iter(range(10**6))
    return lambda: TensorDict({"i": torch.tensor(next(n))}, [])


def test_learn_batch_starts_after_init_frames_and_a_full_batch():
    t = dataclasses.replace(
        load_config(CONFIG).train,
        init_random_frames=1000,
        batch_size=64,
        updates_per_batch=3,
        lr=1e-3,
        lr_end=1e-4,
        lr_decay_start_frames=0,
        total_frames=10_000,
    )
    assert not learning_started(999, 64, t) and not learning_started(1000, 63, t)
    assert learning_started(1000, 64, t)
    learner, sample = Recording(), counter()
    assert learn_batch(learner, sample, 999, 10**6, t) is None  # before init_random_frames
    assert learn_batch(learner, sample, 5000, 63, t) is None  # replay not yet a batch
    assert learner.samples == [] and learner.lrs == []  # nothing drawn, nothing set
    out = learn_batch(learner, sample, 5000, 64, t)
    assert learner.samples == [0, 1, 2]  # updates_per_batch steps, a fresh sample each
    assert out == {"loss": 3.0}  # the last step's losses
    assert learner.lrs == [lr_at(5000, t)] and math.isclose(learner.lrs[0], 5.5e-4)


def test_update_phase_keeps_the_rate_unless_given_one():
    learner, sample = Recording(), counter()
    assert update_phase(learner, sample, 0) is None and learner.samples == []
    update_phase(learner, sample, 2)
    assert learner.samples == [0, 1] and learner.lrs == []
    update_phase(learner, sample, 1, lr=0.5)
    assert learner.samples == [0, 1, 2] and learner.lrs == [0.5]


def test_non_finite_names_the_groups_holding_nan_or_inf():
    ok, nan, inf = torch.zeros(3), torch.tensor([0.0, float("nan")]), torch.tensor([float("inf")])
    groups = {
        "heads": [ok, ok],
        "targets": [ok, nan],
        "optimizer": [inf],
        "steps": [torch.ones(2, dtype=torch.long)],
    }
    assert non_finite(groups) == ["targets", "optimizer"]
    assert non_finite({"weights": iter([ok])}) == []  # any iterable, e.g. parameters()


def test_baseline_learner_steps_on_the_sample_it_is_given():
    """``BaselineLearner.update(sample)``: one step on exactly that sample, as the heads' learner
    (the loops draw it with ``sample()``)."""
    cfg = load_config(CONFIG, ["train.batch_size=8", "train.target_update=soft"])
    torch.manual_seed(0)
    net, _, env = build_for_training(cfg, "informed")
    learner = BaselineLearner(net, env.action_spec, cfg, recurrent=False)
    learner.store(env.rollout(4, break_when_any_done=False))
    sample = learner.sample()
    assert sample.batch_size == torch.Size([8])
    before = [p.detach().clone() for p in net.parameters()]
    loss = learner.update(sample)
    again = [p.detach().clone() for p in net.parameters()]
    assert loss.ndim == 0 and bool(loss.isfinite())
    assert any(not torch.equal(a, b) for a, b in zip(before, again))


def test_allocator_settings_are_set_once_and_can_be_left_alone(monkeypatch):
    import platform

    from taskvar_torch.training import allocator

    monkeypatch.setattr(allocator, "_result", None)
    monkeypatch.setenv("TASKVAR_MALLOC", "default")
    assert allocator.keep_freed_memory() is False  # glibc's settings left as they are
    monkeypatch.delenv("TASKVAR_MALLOC")
    if platform.system() == "Linux" and platform.libc_ver()[0] == "glibc":
        assert allocator.keep_freed_memory() is True and allocator._result
