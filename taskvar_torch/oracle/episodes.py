"""Exact returns per played episode, for any family's oracle (docs/evaluation.md, docs/oracle.md):
``taskvar eval``'s exact values (:func:`exact_episode_returns`) and regret
(:func:`optimal_episode_returns`).
"""

from __future__ import annotations

import numpy as np
import torch

from taskvar_torch.config import Config
from taskvar_torch.contract import family
from taskvar_torch.controllers import Controller
from taskvar_torch.oracle.protocol import ExactOracle


def exact_episode_returns(
    oracle: ExactOracle,
    ctrl: Controller,
    cfg: Config,
    instance: dict[str, np.ndarray],
    start: np.ndarray,
    chunk: int = 2000,
) -> np.ndarray:
    """Exact expected horizon-step return of ``ctrl`` (learnt heads) per (instance, start) episode.

    ``oracle``: a family's :class:`~taskvar_torch.oracle.protocol.ExactOracle`; ``instance`` holds
    the episodes' ``instance_keys`` fields, ``start`` their first ``cell``. Heads read the oracle's
    ``obs_encoding`` where it has one.
    """
    names = tuple(oracle.instance_keys)
    missing = [k for k in names if k not in instance]
    if missing:
        raise ValueError(f"exact returns need the episodes' instance fields {list(names)}")
    out = []
    for lo in range(0, len(start), chunk):
        sl = slice(lo, lo + chunk)
        fields = []
        for k in names:
            v = torch.as_tensor(np.asarray(instance[k])[sl])
            fields.append(v.to(torch.float64) if v.is_floating_point() else v.to(torch.int64))
        encoding = getattr(oracle, "obs_encoding", None) or family(cfg).observation(cfg)
        V = oracle.controller_return(ctrl, *fields, start=None, obs_encoding=encoding)  # (B, S)
        idx = torch.as_tensor(start[sl], dtype=torch.int64).unsqueeze(-1)
        out.append(V.gather(1, idx.to(V.device)).squeeze(-1).cpu().numpy())
    return np.concatenate(out) if out else np.zeros(0)


def optimal_episode_returns(
    oracle: ExactOracle, instance: dict[str, np.ndarray], start: np.ndarray, chunk: int = 500
) -> np.ndarray:
    """Exact expected horizon-step return of the per-instance optimum per (instance, start) episode
    (paper §3.3.1), distinct instances solved once, ``chunk`` at a time.
    """
    names = tuple(oracle.instance_keys)
    missing = [k for k in names if k not in instance]
    if missing:
        raise ValueError(f"optimal returns need the episodes' instance fields {list(names)}")
    cols = [np.asarray(instance[k]) for k in names]
    uniq, inv = np.unique(
        np.stack([c.astype(np.float64) for c in cols], 1), axis=0, return_inverse=True
    )
    inv = inv.reshape(-1)
    out = np.zeros(len(start))
    start = np.asarray(start, dtype=np.int64)
    for lo in range(0, len(uniq), chunk):
        fields = []
        for j, c in enumerate(cols):
            v = torch.as_tensor(uniq[lo : lo + chunk, j])
            fields.append(v if c.dtype.kind == "f" else v.to(torch.int64))
        V = oracle.optimal_return(*fields, start=None).cpu().numpy()  # (b, S)
        sel = (inv >= lo) & (inv < lo + chunk)
        out[sel] = V[inv[sel] - lo, start[sel]]
    return out


__all__ = ["exact_episode_returns", "optimal_episode_returns"]
