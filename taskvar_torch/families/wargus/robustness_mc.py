"""The robustness critics against Monte Carlo returns of their own option (paper §3.4.3, Wargus;
docs/hierarchy-critics.md).

Each critic ``R_o`` is the Q-function of o's robustness reward under o's greedy policy, cut at
o's termination (``taskvar_torch/heads/robustness.py``). :func:`robustness_monte_carlo` plays
fixed instances, runs o wherever it can start until ``beta_o`` or the episode's end, and compares
``R(o, s_t, a_t)`` with the discounted return-to-go of the run (:func:`option_returns`). A run the
horizon censors is completed by the critic's own tail (``truncation="bootstrap"``) or dropped
(``"exclude"``). ``agree``: the share of steps where ``R > tau[o]`` is decided alike by critic and
return, ``tau`` the hierarchy's (:func:`hierarchy_thresholds`); ``agree_ranked``: the same with
the return's threshold at the critic's share of steps above it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import torch

from taskvar_torch import keys
from taskvar_torch.config.schema import Config
from taskvar_torch.contract import family
from taskvar_torch.factory import calibrate, make_subtasks, training_states
from taskvar_torch.families.wargus import dynamics as wargus
from taskvar_torch.families.wargus.env import WargusEnv
from taskvar_torch.families.wargus.family import section
from taskvar_torch.heads.bundle import Heads, with_root_row
from taskvar_torch.subtasks.base import Subtasks

TRUNCATIONS = (
    "bootstrap",
    "exclude",
)  # censored returns at the horizon: the critic's tail, or drop


def fixed_instances_env(cfg: Config, seeds: Sequence[int]) -> WargusEnv:
    """One sub-env per Wargus instance seed in ``seeds`` (``cfg.env.wargus``'s layout)."""
    return WargusEnv(
        len(seeds),
        config=dataclasses.asdict(section(cfg)),
        instances=wargus.WargusInstances(seeds=tuple(seeds)),
        seed=0,
        validate_actions=False,
    )


def option_returns(
    rewards: torch.Tensor,  # (T, N) robustness reward of step t (s_t -> s_{t+1})
    active: torch.Tensor,  # (T, N) bool: the option runs at step t
    ends: torch.Tensor,  # (T, N) bool: its run ends after step t (beta_o(s_{t+1}) or episode end)
    bootstrap: torch.Tensor,  # (T, N) bool: the run is censored after step t (truncation)
    next_values: torch.Tensor,  # (T, N) R_o(s_{t+1}, pi^o(s_{t+1})), read where bootstrap
    gamma: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Discounted return-to-go ``G_t`` of each step within its own run and the weight ``W_t`` of its
    bootstrap tail (``gamma^k`` if censored, else 0), ``(T, N)`` each, 0 on inactive steps.
    """
    g = torch.zeros_like(rewards[0])
    w = torch.zeros_like(rewards[0])
    out_g, out_w = torch.zeros_like(rewards), torch.zeros_like(rewards)
    zero = torch.zeros_like(g)
    for t in range(rewards.shape[0] - 1, -1, -1):
        cont = active[t] & ~ends[t]
        boot = active[t] & bootstrap[t]
        tail_g = torch.where(cont, g, torch.where(boot, next_values[t], zero))
        tail_w = torch.where(cont, w, torch.where(boot, torch.ones_like(w), zero))
        g = torch.where(active[t], rewards[t] + gamma * tail_g, zero)
        w = torch.where(active[t], gamma * tail_w, zero)
        out_g[t], out_w[t] = g, w
    return out_g, out_w


@torch.no_grad()
def hierarchy_thresholds(cfg: Config, heads: Heads, subtasks: Subtasks) -> torch.Tensor:
    """``(O,)`` the hierarchy controller's tau per option: calibrated on training states
    (``train.robustness_threshold = "calibrated"``, as ``make_method_controller`` does) or the
    fixed ``train.robustness_tau``."""
    t = cfg.train
    if t.robustness_threshold == "calibrated":
        return calibrate(cfg, heads, subtasks, training_states(cfg, heads)).tau.cpu()
    return torch.full((len(heads.option_names),), float(t.robustness_tau))


def _stats(pred: torch.Tensor, mc: torch.Tensor, tau: float) -> dict[str, float]:
    n = pred.numel()
    if n == 0:
        return {"n": 0}
    corr = float("nan")
    if n > 1 and float(pred.std()) > 0 and float(mc.std()) > 0:
        corr = float(torch.corrcoef(torch.stack((pred, mc)))[0, 1])
    above = pred > tau
    mc_tau = torch.quantile(mc, 1.0 - above.float().mean())  # MC's tau keeping the same share
    return {
        "n": n,
        "predicted": float(pred.mean()),
        "mc": float(mc.mean()),
        "mae": float((pred - mc).abs().mean()),
        "bias": float((pred - mc).mean()),
        "corr": corr,
        "tau": tau,
        "critic_above": float((pred > tau).float().mean()),
        "mc_above": float((mc > tau).float().mean()),
        "agree": float((above == (mc > tau)).float().mean()),
        "agree_ranked": float((above == (mc > mc_tau)).float().mean()),
    }


@torch.no_grad()
def robustness_monte_carlo(
    heads: Heads,
    cfg: Config,
    seeds: Sequence[int],
    subtasks: Subtasks | None = None,
    tau: torch.Tensor | Sequence[float] | None = None,
    truncation: str = "bootstrap",
) -> dict[str, dict[str, float]]:
    """Each option's robustness critic against Monte Carlo returns of its own runs (module
    docstring).

    Args: heads, cfg: a Wargus bundle's heads and config (``load_heads``). seeds: instance seeds,
        one episode each; use training-distribution seeds, never nominal ones. subtasks: default
        ``make_subtasks(cfg, env)``. tau: ``(O,)`` thresholds; default :func:`hierarchy_thresholds`.
        truncation: ``"bootstrap"`` or ``"exclude"``.

    Returns:
        ``{option: {n, runs, censored, tail_weight, predicted, mc, mae, bias, corr, tau,
        critic_above, mc_above, agree, agree_ranked}}`` (``bias``: mean(predicted - MC), ``corr``:
        Pearson's r, ``*_above``: share above tau).
    """
    t = cfg.train
    if family(cfg).env_class is not WargusEnv:  # it plays fixed WargusEnv instances
        raise ValueError(
            f"robustness_monte_carlo plays Wargus instances, got family {cfg.family!r}"
        )
    if t.robustness_target != "option":
        raise ValueError(
            f"train.robustness_target={t.robustness_target!r}: only 'option' critics evaluate "
            "their option's own policy, which this Monte Carlo check plays"
        )
    if t.robustness_until not in ("termination", "episode"):
        raise ValueError(f"unknown train.robustness_until {t.robustness_until!r}")
    if truncation not in TRUNCATIONS:
        raise ValueError(f"truncation must be one of {list(TRUNCATIONS)}, got {truncation!r}")
    for head in ("options", "robustness"):
        if not heads.has(head):
            raise ValueError(f"robustness_monte_carlo needs the {head!r} head")
    until_termination = t.robustness_until == "termination"
    names = list(heads.option_names)
    n = len(seeds)
    env = fixed_instances_env(cfg, seeds)
    subtasks = make_subtasks(cfg, env) if subtasks is None else subtasks
    taus = hierarchy_thresholds(cfg, heads, subtasks) if tau is None else torch.as_tensor(tau)
    tree = subtasks.hierarchy
    avg_root = (
        names.index(tree.root)
        if t.hierarchy_root_policy == "averaging" and tree is not None and heads.has("averaging")
        else None
    )
    gamma = float(t.robustness_gamma)
    rows = torch.arange(n)
    out: dict[str, dict[str, float]] = {}
    for o, name in enumerate(names):
        env = fixed_instances_env(cfg, seeds)  # the same instances for every option
        td = env.reset()
        alive = torch.ones(n, dtype=torch.bool)
        running = torch.zeros(n, dtype=torch.bool)
        runs = torch.zeros((), dtype=torch.int64)
        pred, rew, act, end, boot, v_own = [], [], [], [], [], []
        for step in range(env.horizon + 1):
            td = heads(td)
            q = td.get(keys.OPTION_ACTION_VALUE)  # (n, O, A)
            if avg_root is not None:
                q = with_root_row(q, td.get(keys.ACTION_VALUE), avg_root)
            own = q[:, o].argmax(-1)  # pi^o(s_t)
            rob = td.get(keys.ROBUSTNESS)[:, o]  # (n, A)
            v_own.append(rob[rows, own])  # R_o(s_t, pi^o(s_t)): bootstrap of step t - 1
            if step == env.horizon or not bool(alive.any()):
                break
            start = alive & ~running & subtasks.startable(td)[:, o]
            runs += start.sum()
            running = running | start
            q_avg = td.get(keys.ACTION_VALUE, None)  # between o's runs: the averaging policy
            between = q_avg.argmax(-1) if q_avg is not None else own
            action = torch.where(running, own, between)
            pred.append(rob[rows, action])
            td.set(keys.ACTION, action)
            td = env.step(td)
            nxt = td.get(keys.NEXT)
            done = nxt.get(keys.DONE).reshape(n)
            truncated = done & ~nxt.get(keys.TERMINATED).reshape(n)
            stop = subtasks.termination(nxt)[:, o] if until_termination else torch.zeros_like(done)
            rew.append(subtasks.robustness_reward(td)[:, o].to(torch.float32))
            act.append(running.clone())
            end.append(running & (done | stop))
            boot.append(running & truncated & ~stop)
            running = running & ~(done | stop)
            alive = alive & ~done
            td = nxt.clone()
        if not pred:
            out[name] = {"n": 0, "runs": 0}
            continue
        active = torch.stack(act)
        g, w = option_returns(
            torch.stack(rew),
            active,
            torch.stack(end),
            torch.stack(boot),
            torch.stack(v_own[1 : len(pred) + 1]),
            gamma,
        )
        keep = active & (w == 0) if truncation == "exclude" else active
        stats = _stats(torch.stack(pred)[keep], g[keep], float(taus[o]))
        stats["runs"] = int(runs)
        stats["censored"] = float((w[active] > 0).float().mean()) if bool(active.any()) else 0.0
        stats["tail_weight"] = float(w[keep].mean()) if bool(keep.any()) else 0.0
        out[name] = stats
    return out


def format_report(report: dict[str, dict[str, float]]) -> list[str]:
    """One line per option of :func:`robustness_monte_carlo`'s report."""
    lines = []
    for name, s in report.items():
        if not s.get("n"):
            lines.append(f"{name:>6}: no step (the option never ran)")
            continue
        lines.append(
            f"{name:>6}: n={s['n']} runs={s['runs']} critic {s['predicted']:.2f} vs MC "
            f"{s['mc']:.2f} (bias {s['bias']:+.2f}, MAE {s['mae']:.2f}, corr {s['corr']:.2f}); "
            f"R>tau={s['tau']:.2f}: critic {s['critic_above']:.0%}, MC {s['mc_above']:.0%}, "
            f"agree {s['agree']:.0%} (ranked {s['agree_ranked']:.0%}); censored "
            f"{s['censored']:.0%} (tail weight {s['tail_weight']:.2f})"
        )
    return lines
