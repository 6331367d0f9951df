"""The replay of raw transitions the heads learn from (docs/design.md#training-the-heads).

One ``ReplayBuffer`` over ``LazyTensorStorage`` holds raw transitions, so every head's target comes
from the same sample (paper §3.2), sampled uniformly or per behaviour mode
(:class:`PerOptionSampler`); :func:`replay_state` / :func:`load_replay_state` restore it exactly.
"""

from __future__ import annotations

import warnings
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers import RandomSampler
from torchrl.data.replay_buffers.samplers import Sampler

from taskvar_torch import keys
from taskvar_torch.config import Config
from taskvar_torch.heads.behaviour import BEHAVIOUR

EPISODE_REWARD = "episode_reward"  # RewardSum's running return


class PerOptionSampler(Sampler):
    """Every sample in equal shares from each behaviour mode present in the buffer.

    A row's mode is its ``"behaviour"`` (-1 averaging, ``o`` option o); row ``i`` of a sample comes
    from mode ``i mod P``, uniformly within it, so an option mu_bar rarely picks still gets its
    share. Sampling depends on the stored rows and the generator only.
    """

    def __init__(self, mode_key: str = BEHAVIOUR):
        super().__init__()
        self.mode_key = mode_key
        self._groups: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None

    def extend(self, index: torch.Tensor) -> None:
        self._groups = None

    def add(self, index: int) -> None:
        self._groups = None

    def _empty(self) -> None:
        self._groups = None

    def _group_rows(self, storage: Any) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Storage indices sorted by mode, and each present mode's row count and first position."""
        n = len(storage)
        modes = storage.get(slice(0, n)).get(self.mode_key).reshape(n)
        if bool((modes < -1).any()):
            raise ValueError(
                f"replay rows have {self.mode_key!r} < -1; modes are -1 or option >= 0"
            )
        shifted = modes + 1  # 0 averaging, 1 + o option o
        counts = torch.bincount(shifted)
        order = torch.argsort(shifted.to(torch.int32), stable=True)
        present = counts.nonzero().squeeze(1)
        starts = torch.cumsum(counts, 0) - counts
        return order, counts[present], starts[present]

    def sample(self, storage: Any, batch_size: int) -> tuple[torch.Tensor, dict]:
        if len(storage) == 0:
            raise RuntimeError("Cannot sample from an empty storage.")
        if self._groups is None:
            self._groups = self._group_rows(storage)
        order, counts, starts = self._groups
        group = torch.arange(batch_size, device=order.device) % counts.numel()
        u = torch.rand(batch_size, generator=self._rng, dtype=torch.float64)
        offset = (u.to(order.device) * counts[group]).long().minimum(counts[group] - 1)
        return order[starts[group] + offset], {}

    def state_dict(self) -> dict[str, Any]:
        return {}  # a function of the stored rows

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self._groups = None

    def dumps(self, path: Any) -> None:  # nothing beyond the storage
        pass

    def loads(self, path: Any) -> None:
        self._groups = None


def make_replay_buffer(cfg: Config, generator: torch.Generator) -> ReplayBuffer:
    """Replay of raw transitions, sampled as ``train.replay_sampling`` says (uniform, or
    :class:`PerOptionSampler`); sampling draws from ``generator`` only."""
    t = cfg.train  # replay_sampling is one of REPLAY_SAMPLINGS (checked when the config is made)
    return ReplayBuffer(
        storage=LazyTensorStorage(t.buffer_size, device=cfg.device),
        sampler=RandomSampler() if t.replay_sampling == "uniform" else PerOptionSampler(),
        batch_size=t.batch_size,
        generator=generator,
    )


def sample_many(buffer: ReplayBuffer, n: int) -> list[TensorDictBase]:
    """``n`` replay samples of ``buffer.batch_size`` rows: the same rows and generator state as
    ``n`` calls of ``buffer.sample()`` (uniform: one draw and one gather).
    """
    B = int(buffer.batch_size)
    if n <= 1 or type(buffer.sampler) is not RandomSampler:
        return [buffer.sample() for _ in range(n)]
    with warnings.catch_warnings():  # "conflicting batch_sizes": n B rows, asked for on purpose
        warnings.simplefilter("ignore", UserWarning)
        rows = buffer.sample(n * B)
    return list(rows.reshape(n, B).unbind(0))


def raw_transitions(batch: TensorDictBase, keep_instance: bool = False) -> TensorDictBase:
    """Flatten a collector batch ``(N, T)`` to ``(N*T,)`` raw transitions, dropping RewardSum's
    returns, ``next``'s copy and the hidden instance (unless ``keep_instance``).
    """
    drop = [EPISODE_REWARD, (keys.NEXT, EPISODE_REWARD), (keys.NEXT, keys.INSTANCE)]
    if not keep_instance:
        drop.append(keys.INSTANCE)
    return batch.exclude(*drop).reshape(-1)


def replay_state(buffer: ReplayBuffer) -> dict[str, Any]:
    """The buffer's filled rows (a copy, in storage order) and writer cursor, as plain data."""
    n = len(buffer)
    data = {}
    if n:
        rows = buffer[:n]
        if n < buffer.storage.max_size:
            rows = rows.clone()
        data = rows.to_dict()
    return {"data": data, "size": n, "writer": buffer.writer.state_dict()}


def check_replay_state(
    state: Any, rows: TensorDictBase, capacity: int, where: str = "replay"
) -> None:
    """:class:`~taskvar_torch.checkpoint.CheckpointError` unless ``state`` is a :func:`replay_state`
    of a buffer of ``capacity`` rows laid out like ``rows``.
    """
    from taskvar_torch.checkpoint import CheckpointError
    from taskvar_torch.checkpoint.checks import check_counter, check_like

    check_like(state, {"data": None, "size": 0, "writer": None}, where)
    size = check_counter(state["size"], f"{where}['size']", high=capacity)
    data = state["data"]
    if size == 0:
        check_like(data, {}, f"{where}['data']")
    else:
        expected = {
            k: torch.empty((size, *v.shape[1:]), dtype=v.dtype) for k, v in rows.items(True, True)
        }
        flat = TensorDict(expected, batch_size=[size]).to_dict()
        check_like(data, flat, f"{where}['data']")
    writer = state["writer"]
    check_like(writer, {"_cursor": 0, "_write_count": 0}, f"{where}['writer']")
    cursor = check_counter(writer["_cursor"], f"{where}['writer']['_cursor']", high=capacity)
    count = check_counter(writer["_write_count"], f"{where}['writer']['_write_count']")
    full = count >= capacity  # a round-robin writer: cursor = count mod capacity
    if size != min(count, capacity) or cursor != (count % capacity if full else count):
        raise CheckpointError(
            f"{where} is inconsistent: size {size}, writer cursor {cursor} and count {count}"
        )


def load_replay_state(buffer: ReplayBuffer, state: dict[str, Any]) -> None:
    """Refill an empty buffer from :func:`replay_state`: same rows, same cursor."""
    n = int(state["size"])
    if n:
        buffer.extend(TensorDict(state["data"], batch_size=[n]))
    buffer.writer.load_state_dict(state["writer"])


__all__ = [
    "EPISODE_REWARD",
    "PerOptionSampler",
    "load_replay_state",
    "make_replay_buffer",
    "raw_transitions",
    "sample_many",
    "replay_state",
]
