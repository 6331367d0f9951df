"""The replay of raw transitions the heads learn from (docs/design.md, Training the heads).

One uniform ``ReplayBuffer`` over ``LazyTensorStorage`` holds raw transitions (observation, action,
reward, the subtasks' integer state keys, ``next``), so every head's target is computed from the
same sample (paper §3.2: intra-option learning from one stream of experience). Its sampling draws
from the trainer's own generator only, and :func:`replay_state` / :func:`load_replay_state` save
and restore it exactly for resume.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers import RandomSampler

from taskvar_torch import keys
from taskvar_torch.config import Config

EPISODE_REWARD = "episode_reward"  # RewardSum's running return


def make_replay_buffer(cfg: Config, generator: torch.Generator) -> ReplayBuffer:
    """Uniform replay of raw transitions; sampling draws from ``generator`` only."""
    t = cfg.train
    return ReplayBuffer(
        storage=LazyTensorStorage(t.buffer_size, device=cfg.device),
        sampler=RandomSampler(),
        batch_size=t.batch_size,
        generator=generator,
    )


def raw_transitions(batch: TensorDictBase, keep_instance: bool = False) -> TensorDictBase:
    """Flatten a collector batch ``(N, T)`` to ``(N*T,)`` raw transitions, minus what no head may read.

    Dropped: RewardSum's running returns, and the hidden instance (``("instance", ...)``) unless
    ``keep_instance`` (the ``instance`` max-value estimator's critic reads the episode's instance,
    offline only; ``next``'s copy is dropped either way: the instance is fixed along an episode).
    """
    drop = [(keys.NEXT, keys.INSTANCE), EPISODE_REWARD, (keys.NEXT, EPISODE_REWARD)]
    if not keep_instance:
        drop.append(keys.INSTANCE)
    return batch.exclude(*drop).reshape(-1)


def replay_state(buffer: ReplayBuffer) -> dict[str, Any]:
    """The buffer's filled rows (in storage order) and its writer's cursor, as plain data.

    Sampling draws from the trainer's own generator, whose state is saved with the other RNGs.
    The rows are a copy when the buffer is partly filled: ``buffer[:n]`` views a storage
    allocated at full capacity, and ``torch.save`` writes a view's whole storage.
    """
    n = len(buffer)
    data = {}
    if n:
        rows = buffer[:n]
        if n < buffer.storage.max_size:
            rows = rows.clone()
        data = rows.to_dict()
    return {"data": data, "size": n, "writer": buffer.writer.state_dict()}


def load_replay_state(buffer: ReplayBuffer, state: dict[str, Any]) -> None:
    """Refill an empty buffer from :func:`replay_state`: same rows, same cursor."""
    n = int(state["size"])
    if n:
        buffer.extend(TensorDict(state["data"], batch_size=[n]))
    buffer.writer.load_state_dict(state["writer"])


__all__ = [
    "EPISODE_REWARD",
    "load_replay_state",
    "make_replay_buffer",
    "raw_transitions",
    "replay_state",
]
