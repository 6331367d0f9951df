"""Learnt heads and controllers measured exactly by :class:`.oracle.WindyOracle` (paper §3.3.1;
docs/oracle.md): :func:`exact_returns`, :func:`firing_values`, :func:`learnt_vs_oracle_by_start`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from taskvar_torch import keys
from taskvar_torch.config import Config
from taskvar_torch.controllers import Controller
from taskvar_torch.families.windy import dynamics as windy
from taskvar_torch.oracle.chains import discounted_chain_values
from taskvar_torch.oracle.episodes import exact_episode_returns


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
    """Theorem 1's values at every interruption firing ``(s', o)`` in its episode's instance m
    (paper §3.3, Definition 1): ``v_mu_bar``, ``v_m = V^{m,mu_bar}(s')``,
    ``q_m = Q^{m,mu_bar}(s', o)`` and ``q_hat``; ``rolls`` holds the firings and the instances.
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
