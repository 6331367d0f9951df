"""Windy Figure 2 statistics: the content of ``metrics.json`` (paper §3.3.1;
docs/windy-fig2.md#outputs): :func:`summarise` (one distribution), :func:`run_summary` (one run)
and :func:`theorem1_check` (Theorem 1's premise at every firing).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from taskvar_torch.config import METHODS as ALL_METHODS
from taskvar_torch.config import Config
from taskvar_torch.controllers import Controller
from taskvar_torch.experiments.evaluation import mean_ci95, paired_summary
from taskvar_torch.families.windy import firing_values
from taskvar_torch.families.windy.config import section
from taskvar_torch.families.windy.family import windy_layout

METHODS = tuple(m for m in ALL_METHODS if m != "hierarchy")
"""Methods of Figure 2, every method but hierarchy (the windy family has no composition
hierarchy): the flat baseline, options without interruption, Algorithm 1."""
EXACT_ATOL = 1e-9
"""Exact differences within this of 0 count as ties ("no worse", not "better")."""


def _short(summary: dict[str, float]) -> dict[str, float]:
    return {
        k: summary[k]
        for k in (
            "fraction_no_worse",
            "fraction_better",
            "fraction_worse",
            "mean_difference",
            "mean_difference_ci95",
        )
    }


def _exact_summary(diff: np.ndarray) -> dict[str, float]:
    """``paired_summary`` of exact expected-return differences, ties within ``EXACT_ATOL``."""
    d = np.where(np.abs(diff) <= EXACT_ATOL, 0.0, diff)
    return paired_summary(torch.as_tensor(d))


def run_summary(
    run: int, seed: int, cols: dict[str, np.ndarray], returns: dict[str, dict[str, np.ndarray]]
) -> dict[str, Any]:
    """One run's entry of ``per_run``: the paired interruption - averaging summary, the null's
    fraction no worse, each method's mean return (``returns[m]["return"]``), interruptions."""
    diff = torch.as_tensor(cols["return_interruption"] - cols["return_averaging"])
    return {
        "run": run,
        "seed": seed,
        **_short(paired_summary(diff)),
        "fraction_no_worse_null": float(
            np.mean(cols["return_averaging"] >= cols["return_averaging_null"])
        ),
        "mean_return": {m: float(np.mean(returns[m]["return"], dtype=np.float64)) for m in METHODS},
        "interruptions_per_episode": float(np.mean(cols["interruptions"])),
    }


def summarise(
    data: dict[str, np.ndarray], fires: dict[str, np.ndarray], cfg: Config, runs: int, episodes: int
) -> dict[str, Any]:
    """Figure 2's numbers for one distribution from the pooled per-episode columns."""
    t = {k: torch.as_tensor(v, dtype=torch.float64) for k, v in data.items()}
    main = paired_summary(t["return_interruption"] - t["return_averaging"])
    null = paired_summary(t["return_averaging"] - t["return_averaging_null"])
    m: dict[str, Any] = {**main, "runs": runs, "episodes_per_run": episodes}
    m["fraction_no_worse_null"] = null["fraction_no_worse"]
    m["null"] = _short(null)
    m["options_vs_averaging"] = _short(paired_summary(t["return_options"] - t["return_averaging"]))
    m["interruption_vs_options"] = _short(
        paired_summary(t["return_interruption"] - t["return_options"])
    )
    m["mean_return"] = {}
    for name in (*METHODS, "averaging_null"):
        mean, ci = mean_ci95(t[f"return_{name}"])
        m["mean_return"][name] = {"mean": mean, "ci95": ci}
    if "exact_interruption" in data:
        ex = _exact_summary(data["exact_interruption"] - data["exact_averaging"])
        m["fraction_no_worse_exact"] = ex["fraction_no_worse"]
        m["exact"] = {
            **_short(ex),
            "options_vs_averaging": _short(
                _exact_summary(data["exact_options"] - data["exact_averaging"])
            ),
            "interruption_vs_options": _short(
                _exact_summary(data["exact_interruption"] - data["exact_options"])
            ),
            "mean_return": {n: float(data[f"exact_{n}"].mean()) for n in METHODS},
            "note": "exact expected returns of the learnt controllers in each episode's (instance, start)",
        }
    else:
        m["fraction_no_worse_exact"] = None
        m["exact"] = None
    k = data["interruptions"].astype(np.float64)
    S = windy_layout(section(cfg)).num_cells
    m["interruptions_per_episode"] = float(k.mean())
    m["episodes_with_interruption"] = float((k > 0).mean())
    m["interruption_cells"] = np.bincount(fires["fire_cell"], minlength=S).astype(int).tolist()
    opts = np.bincount(fires["fire_option"], minlength=2)
    m["interruptions_by_running_option"] = opts.astype(int).tolist()
    return m


def theorem1_check(
    oracle,
    options_ctrl: Controller,
    cfg: Config,
    rolls: dict[str, np.ndarray],
    exact_diff_vs_options: np.ndarray | None,
    diff_vs_averaging: np.ndarray,
    chunk: int = 1000,
) -> dict[str, Any]:
    """Theorem 1's premise ``V^{mu_bar}(s') <= V^{m,mu_bar}(s')`` at every firing ``(s', o)``, the
    proof's condition and the max-value assumption, and the outcome of the episodes where the
    premise held at every firing / failed at some (values from :func:`.learnt.firing_values`)."""
    ep = rolls["fire_episode"]
    if ep.size == 0:
        return {"firings": 0, "episodes_with_firing": 0}
    vals = firing_values(oracle, options_ctrl, section(cfg).obs_encoding, rolls, chunk)
    v_m, q_m = vals["v_m"], vals["q_m"]
    episodes = np.unique(ep)
    premise = vals["v_mu_bar"] <= v_m + 1e-9
    proof_condition = q_m <= v_m + 1e-9
    max_assumption = q_m <= vals["q_hat"] + 1e-9
    failed = np.zeros(rolls["return"].size, dtype=bool)
    np.logical_or.at(failed, ep, ~premise)
    fired = np.zeros_like(failed)
    fired[episodes] = True

    def outcome(mask: np.ndarray) -> dict[str, Any]:
        o: dict[str, Any] = {"episodes": int(mask.sum())}
        if mask.any():
            o["vs_averaging_sampled"] = _short(
                paired_summary(torch.as_tensor(diff_vs_averaging[mask]))
            )
            if exact_diff_vs_options is not None:
                o["vs_options_exact"] = _short(_exact_summary(exact_diff_vs_options[mask]))
        return o

    return {
        "firings": int(ep.size),
        "episodes_with_firing": int(episodes.size),
        "premise_held": int(premise.sum()),
        "premise_held_fraction": float(premise.mean()),
        "proof_condition_held": int(proof_condition.sum()),
        "proof_condition_held_fraction": float(proof_condition.mean()),
        "max_value_assumption_held_fraction": float(max_assumption.mean()),
        "outcome_premise_held_at_every_firing": outcome(fired & ~failed),
        "outcome_premise_failed_somewhere": outcome(fired & failed),
        "note": "values discounted with train.gamma; V^{m,mu_bar} = learnt options controller in m",
    }


__all__ = ["EXACT_ATOL", "METHODS", "run_summary", "summarise", "theorem1_check"]
