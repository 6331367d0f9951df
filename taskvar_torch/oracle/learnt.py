"""Learnt heads and controllers measured exactly by the oracle (windy Figure 2, paper §3.3.1;
docs/windy-fig2.md, docs/oracle.md).

Per-episode exact returns of a learnt controller (:func:`exact_returns`), Theorem 1's values at
each interruption firing (:func:`firing_values`) and the learnt averaging head's exact return per
start cell beside the mean-MDP optimum (:func:`learnt_vs_oracle_by_start`). ``oracle`` is a
:class:`~taskvar_torch.oracle.windy.WindyOracle`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from taskvar_torch import keys
from taskvar_torch.config import Config
from taskvar_torch.controllers import Controller
from taskvar_torch.envs import windy
from taskvar_torch.oracle.chains import discounted_chain_values


def exact_episode_returns(
    oracle,
    ctrl: Controller,
    cfg: Config,
    instance: dict[str, np.ndarray],
    start: np.ndarray,
    chunk: int = 2000,
) -> np.ndarray:
    """Exact expected horizon-step return of ``ctrl`` (learnt heads) per (instance, start) episode.

    ``oracle`` is a family's exact oracle (``Family.oracle``, docs/families.md): its
    ``instance_keys`` name the ``("instance", key)`` fields its ``controller_return(ctrl, *fields,
    start=None, obs_encoding=...)`` takes, each an array of the episodes' values in ``instance``;
    ``start`` holds each episode's first ``cell``. Learnt heads are read in the oracle's
    ``obs_encoding`` where it has one, else the config's ``env.obs_encoding``.
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
        encoding = getattr(oracle, "obs_encoding", None) or cfg.env.obs_encoding
        V = oracle.controller_return(ctrl, *fields, start=None, obs_encoding=encoding)  # (B, S)
        idx = torch.as_tensor(start[sl], dtype=torch.int64).unsqueeze(-1)
        out.append(V.gather(1, idx.to(V.device)).squeeze(-1).cpu().numpy())
    return np.concatenate(out) if out else np.zeros(0)


def optimal_episode_returns(
    oracle, instance: dict[str, np.ndarray], start: np.ndarray, chunk: int = 500
) -> np.ndarray:
    """Exact expected horizon-step return of the per-instance optimal policy per (instance, start)
    episode: an agent that knows the instance (the ceiling regret is measured against,
    docs/evaluation.md; paper §3.3.1's returns).

    Mirrors :func:`exact_episode_returns`: ``oracle.optimal_return(*fields, start=None)`` gives
    ``(B, S)`` for the ``instance_keys`` fields. Distinct instances are solved once (a finite test
    set, a dry Taxi), in chunks of ``chunk`` instances.
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


def exact_returns(
    oracle,
    ctrl: Controller,
    cfg: Config,
    p: np.ndarray,
    direction: np.ndarray,
    start: np.ndarray,
    chunk: int = 2000,
) -> np.ndarray:
    """:func:`exact_episode_returns` of windy episodes (wind ``p`` and ``direction`` arrays)."""
    return exact_episode_returns(
        oracle, ctrl, cfg, {"p": p, "direction": direction}, start, chunk=chunk
    )


def firing_values(
    oracle,
    options_ctrl: Controller,
    obs_encoding: str,
    rolls: dict[str, np.ndarray],
    chunk: int = 1000,
) -> dict[str, np.ndarray]:
    """Theorem 1's values at every firing ``(s', o)`` of interruption, in its episode's instance m.

    ``rolls``: ``fire_episode``, ``fire_cell``, ``fire_option`` per firing (the option running when
    Algorithm 1 line 6 fired) and ``p``, ``direction`` per episode. Returns per firing:
    ``v_mu_bar``: the learnt ``V^{mu_bar}(s')`` (switching head, mu_bar of ``options_ctrl``'s
    heads); ``v_m``: ``V^{m,mu_bar}(s')`` and ``q_m``: ``Q^{m,mu_bar}(s', o)``, the exact discounted
    values (``oracle.gamma``) of the learnt options controller in m (:func:`discounted_chain_values`);
    ``q_hat``: the learnt ``Q_hat(s', o)`` (max-value head). Paper §3.3, Definition 1.
    """
    ep, cell, opt = rolls["fire_episode"], rolls["fire_cell"], rolls["fire_option"]
    chain = oracle.controller_chain(options_ctrl, obs_encoding=obs_encoding)
    tab = oracle.tabulate(options_ctrl.heads, obs_encoding)
    heads = options_ctrl.heads
    q_mu = tab[keys.OPTION_VALUE].double()  # (S, O)
    v_learnt = (heads.mu_bar(q_mu) * q_mu).sum(-1).numpy()  # (S,) V^{mu_bar}
    q_hat = tab[keys.MAX_VALUE].double().numpy()  # (S, O)
    episodes = np.unique(ep)
    v_m = np.zeros(ep.size)
    q_m = np.zeros(ep.size)
    for lo in range(0, episodes.size, chunk):
        eps = episodes[lo : lo + chunk]
        P, R = windy.transition_tensors(
            oracle.model,
            torch.as_tensor(rolls["p"][eps], dtype=torch.float64),
            torch.as_tensor(rolls["direction"][eps], dtype=torch.int64),
            dtype=torch.float64,
        )
        V = discounted_chain_values(P, R, chain, oracle.gamma).numpy()  # (b, S, Z)
        sel = np.isin(ep, eps)
        row = np.searchsorted(eps, ep[sel])
        v_m[sel] = V[row, cell[sel], 0]
        q_m[sel] = V[row, cell[sel], opt[sel] + 1]
    return {"v_mu_bar": v_learnt[cell], "v_m": v_m, "q_m": q_m, "q_hat": q_hat[cell, opt]}


def learnt_vs_oracle_by_start(heads: Any, oracle: Any) -> list[dict[str, Any]]:
    """Per start cell: exact expected return (training distribution) of the mean-MDP optimal
    averaging policy (paper §3.1) and of the learnt averaging head's greedy policy."""
    with torch.no_grad():
        q = heads(oracle.observation_td().to(oracle.device))[keys.ACTION_VALUE]  # (S, A)
    learnt = oracle.expected_return(q.argmax(-1), None, starts=None)  # (S,)
    optimum = oracle.expected_return(oracle.averaging_policy(), None, starts=None)  # (S,)
    width = oracle.layout.width
    return [
        {
            "start": list(divmod(c, width)),
            "oracle_optimum": float(optimum[c]),
            "learnt": float(learnt[c]),
        }
        for c in oracle.start_cells.tolist()
    ]
