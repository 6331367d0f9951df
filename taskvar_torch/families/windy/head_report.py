"""Every learnt windy head against its exact optimum at any grid size (docs/scale.md,
docs/oracle.md#which-reference-the-learnt-heads-should-reach).

:func:`head_report` measures with a
:class:`~taskvar_torch.families.windy.sparse_oracle.SparseWindyOracle` the averaging head (§3.1),
each exit option, mu_bar and the options and interruption controllers (§3.2, Algorithm 1), and
the interruption condition's agreement with the exact one; ``rel_gap = (V* - V) / |V*|``,
``within_2pct`` is ``rel_gap <= 0.02``.
"""

from __future__ import annotations

from typing import Any

import torch

from taskvar_torch.families.windy.env import observation_table
from taskvar_torch.families.windy.sparse_oracle import SparseWindyOracle
from taskvar_torch.heads.bundle import Heads
from taskvar_torch.heads.networks import head_network
from taskvar_torch.oracle.mdp import greedy

TOLERANCE = 0.02
"""A head is learnt when its objective is within 2% of the exact optimum."""


@torch.no_grad()
def tabulate_heads(heads: Heads, observations: torch.Tensor) -> dict[str, torch.Tensor]:
    """Each head's output at every cell: ``averaging (S, A)``, ``options (O, S, A)``,
    ``switching (S, O)``, ``max_value (S, O)`` (those the bundle has), float64 on the CPU."""
    out = {}
    for name in ("averaging", "options", "switching", "max_value"):
        if heads.has(name):
            q = head_network(heads.heads[name])(observations).double().cpu()
            out[name] = q.permute(1, 0, 2).contiguous() if name == "options" else q
    return out


def _rel_gap(v: torch.Tensor, v_star: torch.Tensor) -> float:
    return float((v_star - v) / v_star.abs().clamp_min(1e-12))


def head_report(
    heads: Heads,
    oracle: SparseWindyOracle,
    obs_encoding: str,
    patch_radius: int = 2,
    with_max_value: bool = True,
) -> dict[str, Any]:
    """Every head of a trained windy bundle measured against ``oracle`` (module docstring);
    ``with_max_value=False`` skips the slowest exact solve.
    """
    table = observation_table(oracle.layout, obs_encoding, patch_radius)
    tensor = next(iter([*heads.parameters(), *heads.buffers()]), None)  # tables: buffers only
    device = oracle.device if tensor is None else tensor.device
    tab = tabulate_heads(heads, torch.as_tensor(table, device=device))
    starts = oracle.start_cells.cpu()
    open_cells = torch.tensor([oracle.layout.char(c) != "#" for c in range(oracle.S)])
    report: dict[str, Any] = {}

    pi = greedy(tab["averaging"]).to(oracle.device)
    v, v_star = (
        oracle.averaging_objective(pi)[starts].mean().cpu(),
        oracle.averaging_objective()[starts].mean().cpu(),
    )
    ret, ret_star = (
        float(oracle.expected_return(pi)),
        float(oracle.expected_return(oracle.averaging_policy())),
    )
    report["averaging"] = {
        "objective": float(v),
        "optimum": float(v_star),
        "rel_gap": _rel_gap(v, v_star),
        "expected_return": ret,
        "optimal_return": ret_star,
    }
    report["averaging"]["within_2pct"] = report["averaging"]["rel_gap"] <= TOLERANCE
    if "options" not in tab:
        return report

    pols = greedy(tab["options"]).to(oracle.device)  # (O, S)
    obj = oracle.option_objective(pols)[:, starts].mean(-1).cpu()
    opt = oracle.option_objective()[:, starts].mean(-1).cpu()
    report["options"] = {
        name: {
            "objective": float(obj[o]),
            "optimum": float(opt[o]),
            "rel_gap": _rel_gap(obj[o], opt[o]),
            "within_2pct": _rel_gap(obj[o], opt[o]) <= TOLERANCE,
        }
        for o, name in enumerate(oracle.option_names)
    }

    q_mu_exact = oracle.switching_q().cpu()  # (S, O) of the exact option policies
    pick = tab["switching"].argmax(-1)  # (S,) learnt mu_bar
    best = q_mu_exact.max(-1).values
    chosen = q_mu_exact.gather(-1, pick.unsqueeze(-1)).squeeze(-1)
    ok = chosen >= best - oracle.tie_atol
    report["mu_bar"] = {
        "start_agreement": float(ok[starts].double().mean()),
        "mean_value_lost": float((best - chosen)[starts].mean()),
        "learnt_choices": {
            name: int((pick[starts] == o).sum()) for o, name in enumerate(oracle.option_names)
        },
        "exact_choices": {
            name: int((oracle.mu_bar().cpu()[starts] == o).sum())
            for o, name in enumerate(oracle.option_names)
        },
    }

    # the options controller: mu_bar's pick at the start cell, then that option's policy
    exact_pols, exact_q_mu = oracle.option_policies(), oracle.switching_q()
    learnt_q_mu = tab["switching"].to(oracle.device)
    report["options_controller"] = {
        "expected_return": float(oracle.controller_returns(pols, learnt_q_mu)["expected_return"]),
        "oracle_options_return": float(
            oracle.controller_returns(exact_pols, exact_q_mu)["expected_return"]
        ),
        "averaging_optimal_return": ret_star,
    }

    if with_max_value and "max_value" in tab:
        exact = oracle.interruption_condition(oracle.max_value(), oracle.switching_q()).cpu()
        learnt = oracle.interruption_condition(
            tab["max_value"].to(oracle.device), tab["switching"].to(oracle.device)
        ).cpu()
        cells = open_cells & ~oracle.is_goal.cpu()
        report["interruption_condition"] = {
            "agreement": float((exact == learnt)[cells].double().mean()),
            "exact_pairs": int(exact[cells].sum()),
            "learnt_pairs": int(learnt[cells].sum()),
            "pairs": int(cells.sum()) * len(oracle.option_names),
        }
        learnt_ctrl = oracle.controller_returns(pols, learnt_q_mu, tab["max_value"])
        exact_ctrl = oracle.controller_returns(exact_pols, exact_q_mu, oracle.max_value())
        report["interruption_controller"] = {
            "expected_return": float(learnt_ctrl["expected_return"]),
            "interruptions_per_episode": float(learnt_ctrl["interruptions_per_episode"]),
            "oracle_interruption_return": float(exact_ctrl["expected_return"]),
            "oracle_interruptions_per_episode": float(exact_ctrl["interruptions_per_episode"]),
            "oracle_options_return": report["options_controller"]["oracle_options_return"],
        }
    return report
