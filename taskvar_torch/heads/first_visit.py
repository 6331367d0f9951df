"""Instance-balanced replay: keep each (observation, action) once per episode (paper §3.1).

The averaging values are those of the mean MDP, which mixes instances by the prior at every (s, a);
replaying every transition weights instances by how often they revisit (s, a) (a windy gust pushing
the agent back yields ~100 samples in one episode). :class:`FirstVisitFilter` keeps each pair's
first visit per episode, hashed into ``buckets`` flags per environment (a collision drops a
transition, which only thins the data).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torch import nn

from taskvar_torch import keys, rng


class FirstVisitFilter(nn.Module):
    """Per-environment first-visit flags over hashed (observation, action) pairs, ``num_envs x
    buckets`` bools.
    """

    def __init__(
        self,
        num_envs: int,
        obs_dim: int,
        buckets: int = 1 << 14,
        device: torch.device | str | None = None,
    ):
        super().__init__()
        self.buckets = int(buckets)
        gen = torch.Generator().manual_seed(12345)
        coef = torch.randint(1, 1 << 30, (obs_dim + 1,), generator=gen, dtype=torch.int64) * 2 + 1
        salt = torch.randint(0, 1 << 31, (obs_dim + 1,), generator=gen, dtype=torch.int64)
        self.register_buffer("coef", coef.to(device), persistent=False)  # (D + 1,) odd
        self.register_buffer("salt", salt.to(device), persistent=False)  # (D + 1,)
        self.register_buffer(
            "seen", torch.zeros(num_envs, self.buckets, dtype=torch.bool, device=device)
        )

    def _hash(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``(N,)`` bucket of each (observation (N, D), action (N,)) pair."""
        bits = obs.contiguous().view(torch.int32).to(torch.int64) & rng.MASK32  # (N, D)
        x = torch.cat([bits, action.reshape(-1, 1).to(torch.int64)], -1)  # (N, D + 1)
        y = rng.hash32((x + self.salt) & rng.MASK32)  # (N, D + 1) mixed per element and position
        h = (y * self.coef).sum(-1) & rng.MASK32  # (N,)
        return rng.hash32(h) % self.buckets

    @torch.no_grad()
    def forward(self, batch: TensorDictBase) -> torch.Tensor:
        """``(N, T)`` bool mask of first visits in a collector batch ``(N, T)`` (updates the flags;
        ``is_init`` starts new episodes). :meth:`visit_steps` of the batch's steps at once."""
        obs = batch.get(keys.OBSERVATION)  # (N, T, D)
        action = batch.get(keys.ACTION)  # (N, T)
        is_init = batch.get("is_init").reshape(action.shape)  # (N, T) new episode at step t
        keep = self.visit_steps(obs.transpose(0, 1), action.t(), is_init.t())  # (T, N)
        return keep.t()

    @torch.no_grad()
    def visit(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``(N,)`` first-visit mask of one step (observation ``(N, D)``, action ``(N,)``); updates
        the flags.
        """
        rows = torch.arange(obs.shape[0], device=obs.device)
        h = self._hash(obs, action)  # (N,)
        keep = ~self.seen[rows, h]
        self.seen[rows, h] = True
        return keep

    @torch.no_grad()
    def visit_steps(
        self, obs: torch.Tensor, action: torch.Tensor, is_init: torch.Tensor | None = None
    ) -> torch.Tensor:
        """:meth:`visit` of ``T`` consecutive steps at once: ``(T, N)`` mask of observations ``(T,
        N, D)`` and actions ``(T, N)``; ``is_init (T, N)`` clears an environment's flags where its
        episode starts. Equal to ``T`` calls of :meth:`visit` (tested), by one hash and a sort.
        """
        T, N = action.shape
        h = self._hash(obs.reshape(T * N, -1), action.reshape(-1)).view(T, N)  # (T, N)
        rows = torch.arange(N, device=obs.device).expand(T, N)
        new = ~self.seen[rows, h]  # (T, N) not flagged before these steps
        seg = rows  # (T, N) the (environment, episode) segment of each step
        if is_init is not None:
            ep = is_init.to(torch.int64).cumsum(0)  # (T, N) 0: the episode running before
            new |= ep > 0  # an episode started here has no flags yet
            seg = rows * (T + 1) + ep
        key = (seg * self.buckets + h).reshape(-1)  # step-major: earlier steps first
        order = torch.sort(key, stable=True).indices  # equal keys stay in step order
        sorted_key = key[order]
        first = torch.ones_like(sorted_key, dtype=torch.bool)
        first[1:] = sorted_key[1:] != sorted_key[:-1]  # the earliest step of each key
        earliest = torch.empty_like(first).scatter_(0, order, first).view(T, N)
        if is_init is None:
            self.seen[rows, h] = True
        else:  # the flags left are those of each environment's last episode
            started = (ep[-1] > 0).nonzero().squeeze(-1)  # environments with a new episode
            self.seen.index_fill_(0, started, False)  # their rows only (a mask would sweep all)
            last = ep == ep[-1:]  # (T, N) steps of the episode running at the end
            self.seen[rows[last], h[last]] = True
        return new & earliest

    def clear(self) -> None:
        """Forget every visit (every environment starts a new episode)."""
        self.seen.zero_()
