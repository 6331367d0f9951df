"""``taskvar eval --explain``: what the table of :func:`~taskvar_torch.experiments.bundle_eval.
format_table` shows, in words derived from its numbers (which methods played alike, how each
stands against the best memoryless one, memory against ``blind``, and whether ``informed`` is a
ceiling: :func:`ceiling_gate`, docs/memory.md#the-ceiling-gate)."""

from __future__ import annotations

import textwrap
from collections.abc import Sequence
from typing import Any

from taskvar_torch.heads.recurrent import SEES_MORE


def _score(r: dict[str, Any], regret: bool) -> tuple[float, float]:
    """A method's regret (``regret``) or mean return, and its 95% CI half-width."""
    if regret:
        return r["regret_mean"], r["regret_ci95"]
    return r["mean_return"], r["mean_return_ci95"]


def _apart(a: tuple[float, float], b: tuple[float, float]) -> bool:
    """Whether two (value, 95% CI half-width) intervals do not overlap."""
    return abs(a[0] - b[0]) > a[1] + b[1]


def _versus(
    a: tuple[float, float], b: tuple[float, float], sign: float, words: Sequence[str]
) -> str:
    """``words[0]`` where ``a`` and ``b`` (value, CI half-width) overlap, else ``words[1]`` where
    ``a`` is better (``sign``: -1 when higher is better), ``words[2]`` where it is worse."""
    if not _apart(a, b):
        return words[0]
    return words[1] if sign * a[0] < sign * b[0] else words[2]


def _and(words: Sequence[str]) -> str:
    """``a``, ``a and b``, ``a, b and c``."""
    return words[0] if len(words) == 1 else f"{', '.join(words[:-1])} and {words[-1]}"


def _zero_width(ms: dict[str, Any], pair: Sequence[str], regret: bool) -> str:
    """A note where one of ``pair``'s 95% CIs is 0 wide (every episode scored the same, as when
    each ran to the step cap): the separation rests on the other's spread alone."""
    flat = [m for m in pair if _score(ms[m], regret)[1] == 0.0]
    if not flat:
        return ""
    m = flat[0]
    return (
        f" (the 95% CI of {m} is 0 wide: every one of its episodes scored the same, "
        f"{ms[m].get('mean_length', float('nan')):.0f} steps on average, as when each runs to "
        "the step cap; 'apart' rests on the other's spread alone)"
    )


def _wrap(text: str, indent: str = "  ") -> str:
    return textwrap.fill(text, 100, initial_indent=indent, subsequent_indent=indent + "  ")


def explain_table(metrics: dict[str, Any]) -> str:
    """What :func:`format_table`'s table shows, in words derived from its numbers (``taskvar eval
    --explain``); a statement is made only where the numbers support it.
    """
    points, episodes = metrics["points"], metrics["episodes"]
    rows = [r for p in points for r in p["methods"].values()]
    sampled = sorted(
        {m for p in points for m, r in p["methods"].items() if r.get("regret_sampled")}
    )
    parts = [
        f"mean return: the sampled mean over {episodes} paired episodes (every method played the "
        "same instances, starts and random draws), +- its 95% CI half-width; higher is better"
    ]
    if any("exact_mean_return" in r for r in rows):
        parts.append(
            "exact: the expected return of the learnt memoryless policy in each episode's instance "
            "and start, computed by the exact oracle (no sampling noise)"
        )
    if any("regret_mean" in r for r in rows):
        parts.append(
            "regret: the exact per-instance optimum (an agent that knows the hidden instance) minus "
            "the method's return, per episode: 0 is the ceiling, lower is better; from the exact "
            "value for the memoryless methods"
            + (f", from the sampled return for {', '.join(sampled)}" if sampled else "")
        )
    if any("control" in r for r in rows):
        parts.append(
            "interr./ep: how often interruption (Algorithm 1) cut a running option short, per "
            "episode; control: the share of steps each option acted"
        )
    lines = ["How to read the table:", *map(_wrap, parts)]
    alike: list[list[str]] = []
    if len(points) == 1:
        shows, alike = _explain_point(points[0]["methods"])
        lines += ["What it shows:", *map(_wrap, shows)]
    if metrics.get("figures"):
        overlap = [g for g in alike if len(g) > 1]
        lines.append(
            _wrap(
                f"Plots beside metrics.json: {', '.join(metrics['figures'])}"
                + "".join(f"; {', '.join(g)} draw on top of each other" for g in overlap),
                "",
            )
        )
    lines.append(
        _wrap(
            "Further: docs/evaluation.md (this table, named tests, --shift curves), docs/memory.md "
            "(memory and the ceiling), docs/results.md (many training seeds)",
            "",
        )
    )
    return "\n".join(lines)


_ALIKE = ("mean_return", "exact_mean_return", "regret_mean")


def _explain_point(ms: dict[str, Any]) -> tuple[list[str], list[list[str]]]:
    """:func:`explain_table`'s statements on one test point's methods ``ms``, and the groups of
    memoryless methods that played alike (the same mean return, exact value and regret)."""
    regret = all("regret_mean" in r for r in ms.values())
    what = "regret" if regret else "mean return"
    sign = 1.0 if regret else -1.0  # the best is the smallest regret, the largest return
    memoryless = [m for m in ms if m not in SEES_MORE]
    alike: list[list[str]] = []
    for m in memoryless:
        for g in alike:
            if all(ms[g[0]].get(k) == ms[m].get(k) for k in _ALIKE):
                g.append(m)
                break
        else:
            alike.append([m])
    shows = []
    for g in (g for g in alike if len(g) > 1):
        v, ci = _score(ms[g[0]], regret)
        why = []
        if {"options", "interruption"} <= set(g):
            if ms["interruption"].get("interruptions_per_episode") == 0:
                why.append("interruption never fired, so it ran as the options controller")
        if {"options", "averaging"} <= set(g):
            ran = [o for o, share in ms["options"].get("control", {}).items() if share == 1.0]
            if ran:
                why.append(f"the options controller ran {ran[0]} on every step")
        same = ["mean return"]  # only what was measured (a family with no oracle has no exact)
        same += ["exact value"] if "exact_mean_return" in ms[g[0]] else []
        same += ["regret"] if regret else []
        shows.append(
            f"{', '.join(g)}: the same {_and(same)} ({v:.3f} +-{ci:.3f}): "
            "on these episodes they acted alike" + (f" ({'; '.join(why)})" if why else "")
        )
    first = [g[0] for g in alike]
    best = min(first, key=lambda m: sign * _score(ms[m], regret)[0]) if first else None
    for m in first:
        if m == best:
            continue
        a, b = _score(ms[m], regret), _score(ms[best], regret)
        shows.append(
            f"{m} ({what} {a[0]:.3f} +-{a[1]:.3f}) "
            + ("is behind" if _apart(a, b) else "ties with")
            + f" {best} ({b[0]:.3f} +-{b[1]:.3f})"
            + (", 95% CIs apart" if _apart(a, b) else " within their 95% CIs")
            + (_zero_width(ms, (m, best), regret) if _apart(a, b) else "")
        )
    if "recurrent" in ms and best is not None:
        a, b = _score(ms["recurrent"], regret), _score(ms[best], regret)
        verdict = _versus(
            a,
            b,
            sign,
            (
                "ties with the best memoryless method within their 95% CIs",
                "is better than every memoryless method, 95% CIs apart",
                "is worse than the best memoryless method, 95% CIs apart",
            ),
        )
        shows.append(
            f"recurrent (memory: it acts on the episode so far; {what} {a[0]:.3f} +-{a[1]:.3f}) "
            f"{verdict} (best: {best}, {b[0]:.3f} +-{b[1]:.3f}); where and why memory pays: "
            "docs/memory.md"
        )
    fired = ms.get("interruption", {}).get("interruptions_per_episode")
    if fired == 0 and not any({"options", "interruption"} <= set(g) for g in alike):
        shows.append(
            "interruption never fired on these episodes (0 interruptions per episode): it ran "
            "as the options controller would have, so where they differ it is the random draws"
        )
    elif fired:
        shows.append(f"interruption cut a running option short {fired:.2f} times per episode")
    if "recurrent" in ms and "blind" in ms:
        a, b = _score(ms["recurrent"], regret), _score(ms["blind"], regret)
        verdict = _versus(
            a,
            b,
            sign,
            (
                "ties with blind within their 95% CIs: no gain from memory shown here",
                "is ahead of blind, 95% CIs apart: memory, not its own stream, pays here",
                "is behind blind, 95% CIs apart",
            ),
        )
        shows.append(
            f"recurrent {verdict} (blind: the same trainer on its own stream, no memory and no "
            f"instance; {what} {b[0]:.3f} +-{b[1]:.3f})"
        )
    if "informed" in ms:
        v, ci = _score(ms["informed"], regret)
        if not regret:
            where = f"mean return {v:.3f} +-{ci:.3f}"
        elif abs(v) <= ci:
            where = f"at the exact optimum (regret {v:.3f} +-{ci:.3f}: the CI contains 0)"
        else:
            where = f"regret {v:.3f} +-{ci:.3f}: short of the exact optimum"
        ok, why = ceiling_gate({m: _score(r, regret) for m, r in ms.items()}, lower=regret)
        role = "a ceiling here" if ok else f"no ceiling here: {why}"
        shows.append(f"informed (it sees the hidden instance; {role}): {where}")
    return shows, alike


def ceiling_gate(scores: dict[str, tuple[float, float]], lower: bool = False) -> tuple[bool, str]:
    """Whether ``informed`` is a ceiling on these scores (docs/memory.md#the-ceiling-gate): at
    least as good as every memoryless method (every method but :data:`SEES_MORE`) within their
    95% CIs, ``scores`` each method's ``(value, CI half-width)``, ``lower``: lower is better
    (regret). Returns ``(ok, why)``, ``why`` naming the method it is behind."""
    if "informed" not in scores:
        return False, "no informed result"
    sign = 1.0 if lower else -1.0
    inf = scores["informed"]
    for m, s in scores.items():
        if m in SEES_MORE:
            continue
        if _apart(inf, s) and sign * inf[0] > sign * s[0]:
            return False, (
                f"it is behind {m} ({inf[0]:.3f} +-{inf[1]:.3f} against {s[0]:.3f} +-{s[1]:.3f}, "
                "95% CIs apart), so its features or budget do not let it use the instance"
            )
    return True, ""


__all__ = ["ceiling_gate", "explain_table"]
