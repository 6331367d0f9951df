"""Trained heads against the exact windy oracle
(docs/oracle.md#which-reference-the-learnt-heads-should-reach).

:func:`compare_with_oracle` measures, against :class:`~taskvar_torch.oracle.WindyOracle` for the
same layout and training distribution, on the visited cells (neither wall nor goal):

* ``averaging_return``, ``option_returns`` and their ``oracle_*`` and ``replay_*`` references: exact
  expected returns of the greedy policies, the mean-MDP optimum (§3.1-3.2) and the replay fixed
  point (:meth:`~taskvar_torch.oracle.WindyOracle.replay_policy`);
* ``mu_bar_agreement``: share of cells (option values apart by ``mu_margin``) where mu_bar agrees;
* ``max_value_error`` (Definition 1), and ``max_value_error_learnt_options`` against the max for the
  learnt option policies and mu_bar;
* ``interruption_agreement``, ``firing_pairs``: Algorithm 1 line 6's condition, learnt vs exact;
* ``interruptions_per_episode``: Algorithm 1's exact expected interruptions on the learnt heads and
  on the oracle's tables.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDict

from taskvar_torch import keys
from taskvar_torch.heads.bundle import Heads


@torch.no_grad()
def head_tables(heads: Heads, observations: torch.Tensor) -> dict[str, torch.Tensor]:
    """Every head's output on ``observations`` (S, D), as float64 tables keyed by head name."""

    td = TensorDict({keys.OBSERVATION: observations}, batch_size=observations.shape[:1])
    td = heads(td)
    out = {}
    for name, key in (
        ("averaging", keys.ACTION_VALUE),
        ("options", keys.OPTION_ACTION_VALUE),
        ("switching", keys.OPTION_VALUE),
        ("max_value", keys.MAX_VALUE),
    ):
        if heads.has(name):
            out[name] = td.get(key).to(torch.float64).cpu()
    return out


def compare_with_oracle(
    heads: Heads, oracle: Any, obs_encoding: str = "onehot", mu_margin: float = 0.5
) -> dict[str, Any]:
    """The acceptance figures of the windy heads against ``oracle`` (a ``WindyOracle``)."""
    obs = oracle.observation_td(obs_encoding).get(keys.OBSERVATION).to(torch.float32)
    device = next(heads.parameters()).device
    tab = head_tables(heads, obs.to(device))  # (S, ...) float64 on CPU
    layout = oracle.layout
    visited = torch.tensor([layout.char(c) not in "#G" for c in range(oracle.S)])  # (S,)

    res: dict[str, Any] = {}
    avg_policy = tab["averaging"].argmax(-1)  # (S,)
    res["averaging_return"] = float(oracle.expected_return(avg_policy))
    res["oracle_averaging_return"] = float(oracle.expected_return(oracle.averaging_policy()))

    option_policies = tab["options"].argmax(-1).T  # (O, S)
    oracle_policies = oracle.option_policies()  # (O, S)
    res["option_returns"] = [float(oracle.expected_return(p)) for p in option_policies]
    res["oracle_option_returns"] = [float(oracle.expected_return(p)) for p in oracle_policies]
    res["replay_averaging_return"] = float(oracle.expected_return(oracle.replay_policy()))
    res["replay_option_returns"] = [
        float(oracle.expected_return(oracle.replay_policy(o))) for o in oracle.option_names
    ]

    q_mu, q_mu_oracle = tab["switching"], oracle.switching_q().cpu()  # (S, O)
    gap = (q_mu_oracle.max(-1).values - q_mu_oracle.min(-1).values) > mu_margin  # (S,)
    decided = visited & gap
    agree = q_mu.argmax(-1) == q_mu_oracle.argmax(-1)
    res["mu_bar_cells"] = int(decided.sum())
    res["mu_bar_agreement"] = float(agree[decided].double().mean()) if decided.any() else 1.0

    q_hat, q_hat_oracle = tab["max_value"], oracle.max_value().cpu()  # (S, O)
    res["max_value_error"] = float((q_hat - q_hat_oracle)[visited].abs().max())
    res["max_value_error_per_option"] = (
        (q_hat - q_hat_oracle)[visited].abs().max(0).values.tolist()  # (O,)
    )
    # the same max over the oracle's instance set, for the *learnt* option policies and mu_bar
    p, d = oracle.instance_set()
    P, R = oracle.transition(p, d)
    mu = heads.mu_bar(q_mu)  # (S, O)
    q_hat_learnt = oracle.option_values(P, R, mu, policies=option_policies).max(0).values
    res["max_value_error_learnt_options"] = float((q_hat - q_hat_learnt)[visited].abs().max())
    v = (heads.mu_bar(q_mu) * q_mu).sum(-1)  # (S,) V^{mu_bar}
    fire = q_hat < v.unsqueeze(-1)  # (S, O)
    fire_oracle = q_hat_oracle < oracle.v_mu_bar().cpu().unsqueeze(-1)
    res["interruption_agreement"] = float((fire == fire_oracle)[visited].double().mean())
    res["interruption_pairs"] = int(visited.sum()) * q_hat.shape[-1]
    res["firing_pairs"] = int(fire[visited].sum())
    res["oracle_firing_pairs"] = int(fire_oracle[visited].sum())
    pt, d, w = oracle.quadrature()
    for name, h in (
        ("interruptions_per_episode", heads),
        ("oracle_interruptions_per_episode", None),
    ):
        fires = oracle.controller_fire_count(
            "interruption",
            pt,
            d,
            start="uniform",
            heads=h,
            subtasks=oracle.subtasks,
            obs_encoding=obs_encoding,
        )  # (K,)
        res[name] = float((w * fires).sum())
    return res
