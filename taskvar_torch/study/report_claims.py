"""The paper's claims scored on the groups ``taskvar report`` reads (docs/claims.md; guide
docs/report.md): Figure 2 (§3.3.1, :func:`_fig2`), Figure 4's ordering and speed (§3.5.3,
:func:`_fig4`) and §3.2's premise (:func:`_eval`), on the sealed held-out instances only and on
groups of >= ``MIN_SEEDS`` seeds only, aggregated with ``rliable`` and judged by :data:`RULES`.
:func:`build_report` computes every group's claims, Results row, profile panel and summary.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from taskvar_torch.contract import FAMILIES
from taskvar_torch.experiments.curves import trials_to_fraction_of_max
from taskvar_torch.study import aggregate
from taskvar_torch.study import report_results as at_a_glance
from taskvar_torch.study.report_folders import (
    MIN_SEEDS,
    NOT_FINITE,
    Group,
    ReportError,
    Result,
    check_commits,
    collect,
    exploratory_note,
)

NO_WORSE = 0.75
"""Figure 2: the least fraction no worse that reads as the paper's "almost 80%"."""
SPEED_RATIO = 2.0
"""Figure 4: the least averaging / hierarchy ratio of trials to 90% of maximum that reads as the
paper's ~100 vs > 350 (3.5x)."""
FIG4_MIN_REPETITIONS = 10
"""Repetitions one Figure 4 realisation needs for a verdict on its own (5 flipped between two
realisations: docs/report.md)."""
NOT_ROBUST = "not robust"
"""The verdict of a Figure 4 claim whose independent realisations disagree."""
FIG4_ROBUST = (
    f"each realisation (results folder) needs >= {FIG4_MIN_REPETITIONS} repetitions to stand "
    "alone; where two realisations' verdicts differ, each is not robust"
)
RULES = {
    "fig2": f"reproduced: the CI of the held-out fraction no worse lies at or above "
    f"{NO_WORSE:.0%} and interruption is better in some episodes (CI above 0); partly: at or above "
    f"{NO_WORSE:.0%} without being better anywhere (a tie, not a gain), or a CI across "
    f"{NO_WORSE:.0%}; not: the CI below {NO_WORSE:.0%}",
    "fig4_order": "reproduced: each of hierarchy - interruption, interruption - options, options - "
    "averaging has a paired CI above 0; partly: hierarchy - averaging above 0 but not the whole "
    "chain; not: otherwise; " + FIG4_ROBUST,
    "fig4_speed": "reproduced: averaging - hierarchy in trials to 90% of maximum has a paired CI "
    f"above 0 and the means' ratio is at least {SPEED_RATIO:g}; partly: the CI above 0 with a "
    "smaller ratio; not: otherwise; " + FIG4_ROBUST,
    "premise": "reproduced: averaging's range minus the options controller's range over the shift "
    "curve has a paired CI above 0 and the options controller is not worse than averaging over the "
    "curve (paired mean difference CI reaching 0 or above; a policy that fails everywhere is "
    "unaffected, not robust); partly: the smaller range without that, or a range CI across 0; "
    "not: a range CI at or below 0",
}
"""How each verdict is decided (printed on the claims page). Every CI is the mean's 95%
stratified-bootstrap CI over training seeds."""
CLAIMS = {
    "fig2": (
        "Figure 2: offline interruption no worse than the averaging policy (§3.3.1)",
        "no worse in almost 80% of episodes",
    ),
    "fig4_order": (
        "Figure 4: hierarchy > interruption > options > averaging, first half (§3.5.3)",
        "the hierarchy leads, then interruption, options, averaging",
    ),
    "fig4_speed": (
        "Figure 4: trials to 90% of maximum, hierarchy vs averaging (§3.5.3)",
        "~100 vs > 350 of 500 trials",
    ),
    "premise": (
        "§3.2: a capability is less affected by variability than the full task",
        "argued (shown through Figure 4's head start)",
    ),
}
"""Claim id -> (title, the paper's figure)."""
PAPER_METHODS = ("averaging", "options", "interruption", "hierarchy")


@dataclass
class Claim:
    """One claim's row: the paper's figure, ours, the verdict and why, and detail lines."""

    key: str
    group: str
    ours: str
    verdict: str
    reason: str
    details: list[str] = field(default_factory=list)


# --------------------------------------------------------------------------------------------
# statistics per group


def _num(x: Any) -> float:
    return float("nan") if x is None else float(x)


def _score(r: Result, *path: str | int) -> float:
    """The number at ``path`` in ``r``'s ``metrics.json``; a ``null`` there (the library writes a
    non-finite number as ``null``) or a non-number is a one-line :class:`ReportError` naming the
    file and the key."""
    x: Any = r.metrics
    for k in path:
        x = x[k]
    key = "".join(f"[{k}]" if isinstance(k, int) else f".{k}" for k in path).lstrip(".")
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
        raise ReportError(f"{r.path / 'metrics.json'}: {key} is {x!r}, {NOT_FINITE}")
    return float(x)


def _curves(r: Result, m: str) -> np.ndarray:
    """Repetition ``r``'s held-out ``curve_per_rep`` of method ``m`` ``(R, T)``, every value
    finite (a ``null`` or ``NaN`` is one line naming the file and the entry)."""
    c = r.metrics["heldout"]["methods"][m]["curve_per_rep"]
    a = np.asarray(c, dtype=float)  # a null reads as NaN
    if not np.isfinite(a).all():
        bad = np.argwhere(~np.isfinite(a))[0]
        value = a[tuple(bad)]
        where = "".join(f"[{i}]" for i in bad.tolist())
        shown = None if np.isnan(value) else float(value)  # written as null, or NaN by hand
        raise ReportError(
            f"{r.path / 'metrics.json'}: heldout.methods.{m}.curve_per_rep{where} is {shown!r}, "
            f"{NOT_FINITE}"
        )
    return a


def _ci(e: dict[str, Any], fmt: str = ".3f", which: str = "mean") -> str:
    lo, hi = e[f"{which}_ci95"]
    return f"{e[which]:{fmt}} [{lo:{fmt}}, {hi:{fmt}}]"


def _both(e: dict[str, Any], fmt: str = ".3f") -> str:
    return f"IQM {_ci(e, fmt, 'iqm')}, mean {_ci(e, fmt)}"


def _held(r: Result) -> dict[str, Any]:
    h = r.metrics.get("heldout")
    if not h:
        raise ReportError(
            f"{r.path}: {r.kind} results without held-out scores (run before the held-out split, "
            "issue 33); rerun the experiment"
        )
    return h


def _fig2(g: Group, reps: int) -> tuple[Claim, str, dict[str, Any]]:
    for r in g.results:
        _held(r)
    keys = {
        "no worse": "fraction_no_worse",
        "better": "fraction_better",
        "null no worse": "fraction_no_worse_null",
        "interruption - averaging": "mean_difference",
    }
    per_seed = {k: [_score(r, "heldout", key) for r in g.results] for k, key in keys.items()}
    est = aggregate.interval_estimates(per_seed, reps)
    returns = {
        m: [_score(r, "heldout", "mean_return", m, "mean") for r in g.results]
        for m in ("averaging", "options", "interruption")
    }
    poi = aggregate.probability_of_improvement(returns, "averaging", reps)
    nw, better, null = est["no worse"], est["better"], est["null no worse"]
    lo, hi = nw["mean_ci95"]
    acts = better["mean_ci95"][0] > 0
    pct = lambda e: _ci(e, ".1%")  # noqa: E731
    if lo >= NO_WORSE and acts:
        verdict, why = "reproduced", f"no worse in {pct(nw)}, better in {pct(better)}"
    elif hi < NO_WORSE:
        verdict, why = "not", f"no worse in only {pct(nw)}"
    elif lo >= NO_WORSE:
        verdict = "partly"
        why = (
            f"no worse in {pct(nw)} but better in {pct(better)}: interruption ties the "
            "averaging policy rather than improving on it"
        )
    else:
        verdict, why = "partly", f"no worse in {pct(nw)}: the CI crosses {NO_WORSE:.0%}"
    if nw["mean"] <= null["mean"]:
        why += f"; the null (averaging against itself, other gusts) is already {pct(null)}"
    ours = f"no worse in {pct(nw)} of held-out episodes ({len(g.seeds)} seeds)"
    details = [
        f"fraction no worse (paired, sampled): {_both(nw, '.3f')}",
        f"fraction better: {_both(better, '.3f')}; null fraction no worse: {_both(null, '.3f')}",
        "interruption - averaging per episode, paired: " + _both(est["interruption - averaging"]),
        "P(improvement over averaging): "
        + ", ".join(f"{m} {v['probability']:.2f} {_pair(v['ci95'])}" for m, v in poi.items()),
    ]
    claim = Claim("fig2", g.label, ours, verdict, why, details)
    headline = (
        f"interruption no worse than averaging in {pct(nw)} of held-out episodes, better in "
        f"{pct(better)} (null {pct(null)}); interruption - averaging "
        f"{_ci(est['interruption - averaging'], '+.3f')} per episode"
    )
    return claim, headline, returns


def _pair(ci: Sequence[float]) -> str:
    return f"[{ci[0]:.2f}, {ci[1]:.2f}]"


def _fig4(g: Group, reps: int) -> tuple[list[Claim], str, dict[str, Any]]:
    held = [_held(r) for r in g.results]
    extra = [  # experiment.baselines' curves, beside the paper's methods in every folder
        m
        for m in held[0]["methods"]
        if m not in PAPER_METHODS and all(m in h["methods"] for h in held)
    ]
    curves = {
        m: np.concatenate([_curves(r, m) for r in g.results]) for m in (*PAPER_METHODS, *extra)
    }  # (R, T) items per held-out test episode; experiment.baselines' curves in the evidence
    T = curves["averaging"].shape[1]
    half = max(T // 2, 1)
    first = {m: c[:, :half].mean(1) for m, c in curves.items()}
    links = [("hierarchy", "interruption"), ("interruption", "options"), ("options", "averaging")]
    diffs = aggregate.paired_differences(first, [*links, ("hierarchy", "averaging")], reps)
    level = aggregate.interval_estimates(first, reps)
    poi = aggregate.probability_of_improvement(first, "averaging", reps)

    def status(e: dict[str, Any]) -> str:
        lo, hi = e["mean_ci95"]
        if lo > 0:
            return "ahead"
        if hi < 0:
            return "behind"
        return "tied" if lo == hi == 0 else "level"

    sts = [status(diffs[f"{a} - {b}"]) for a, b in links]
    overall = diffs["hierarchy - averaging"]
    if all(s == "ahead" for s in sts):
        verdict = "reproduced"
    elif status(overall) == "ahead":
        verdict = "partly"
    else:
        verdict = "not"
    why = "; ".join(f"{a} vs {b}: {s}" for (a, b), s in zip(links, sts))
    order = Claim(
        "fig4_order",
        g.label,
        f"hierarchy - averaging {_ci(overall, '+.3f')} items per held-out episode, trials 1-{half} "
        f"({len(g.seeds)} seeds)",
        verdict,
        why,
        [
            f"items per held-out episode, trials 1-{half}: "
            + "; ".join(f"{m} {_both(level[m])}" for m in curves),
            "paired differences: " + "; ".join(f"{k} {_ci(v, '+.3f')}" for k, v in diffs.items()),
            "P(improvement over averaging): "
            + ", ".join(f"{m} {v['probability']:.2f} {_pair(v['ci95'])}" for m, v in poi.items()),
        ],
    )
    t90 = {
        m: np.array([trials_to_fraction_of_max(c) for c in curves[m]], dtype=float)
        for m in ("hierarchy", "averaging")
    }
    speed = aggregate.interval_estimates(t90, reps)
    gap = aggregate.paired_differences(t90, [("averaging", "hierarchy")], reps)[
        "averaging - hierarchy"
    ]
    ratio = speed["averaging"]["mean"] / max(speed["hierarchy"]["mean"], 1e-9)
    if gap["mean_ci95"][0] > 0 and ratio >= SPEED_RATIO:
        sv = "reproduced"
    elif gap["mean_ci95"][0] > 0:
        sv = "partly"
    else:
        sv = "not"
    speed_claim = Claim(
        "fig4_speed",
        g.label,
        f"hierarchy {_ci(speed['hierarchy'], '.0f')} vs averaging "
        f"{_ci(speed['averaging'], '.0f')} of {T} trials ({len(g.seeds)} seeds)",
        sv,
        f"averaging - hierarchy {_ci(gap, '+.0f')} trials, paired; ratio {ratio:.1f}"
        + ("" if T == 500 else f" (the paper's protocol has 500 trials, these {T})"),
        [
            f"trials to 90% of maximum (each repetition's held-out curve): {_both(speed['hierarchy'], '.0f')} (hierarchy), {_both(speed['averaging'], '.0f')} (averaging)"
        ],
    )
    headline = (
        f"items per held-out episode, trials 1-{half}: "
        + ", ".join(f"{m} {_ci(level[m], '.2f')}" for m in PAPER_METHODS)
        + f"; 90% of maximum in {speed['hierarchy']['mean']:.0f} vs "
        f"{speed['averaging']['mean']:.0f} trials (hierarchy vs averaging)"
    )
    profile = {m: c[:, :half] for m, c in curves.items()}
    return [order, speed_claim], headline, profile


def _eval(g: Group, reps: int) -> tuple[Claim | None, str, dict[str, Any]]:
    methods = list(g.config["eval"]["methods"] or [])
    points = [r.metrics["points"] for r in g.results]
    scores = {
        m: np.array(
            [
                [_score(r, "points", i, "methods", m, "mean_return") for i in range(len(pts))]
                for r, pts in zip(g.results, points)
            ]
        )
        for m in methods
    }  # (seeds, points)
    est = aggregate.interval_estimates(scores, reps)
    test = g.config["eval"]["test"]
    where = "held-out" if g.sealed else f"--test {test}"  # a family's own test, where not sealed
    headline = f"IQM mean return ({where}, {scores[methods[0]].shape[1]} point(s)): " + ", ".join(
        f"{m} {_ci(est[m], '.3f', 'iqm')}" for m in methods
    )
    claim = None
    if g.sealed and scores[methods[0]].shape[1] >= 2 and {"averaging", "options"} <= set(methods):
        spread = {m: scores[m].max(1) - scores[m].min(1) for m in ("averaging", "options")}
        d = aggregate.paired_differences(spread, [("averaging", "options")], reps)[
            "averaging - options"
        ]
        lo, hi = d["mean_ci95"]
        level = {m: scores[m].mean(1) for m in ("averaging", "options")}
        worse = aggregate.paired_differences(level, [("options", "averaging")], reps)[
            "options - averaging"
        ]
        fails = worse["mean_ci95"][1] < 0  # options clearly worse over the whole curve
        verdict = "not" if hi <= 0 else ("reproduced" if lo > 0 and not fails else "partly")
        rng = aggregate.interval_estimates(spread, reps)
        claim = Claim(
            "premise",
            g.label,
            f"range of mean return over the curve: options {_ci(rng['options'])} vs averaging "
            f"{_ci(rng['averaging'])} ({len(g.seeds)} seeds)",
            verdict,
            f"averaging - options range {_ci(d, '+.3f')}, paired"
            + (
                f"; but options are worse over the curve ({_ci(worse, '+.3f')} per episode): "
                "unaffected because they fail everywhere"
                if fails and lo > 0
                else ""
            )
            + "; the options controller composes the capabilities, so this tests them composed",
            [f"mean return per point and seed: {headline}"],
        )
    return claim, headline, scores


def _scale_seeds(metrics: dict[str, Any]) -> list[dict[str, dict[str, float]]]:
    """One ``{cell: {method: score}}`` per training seed of a scale folder (``per_seed`` where the
    experiment ran ``seeds > 1``, else the cell's own methods); the score is the gap closed on
    windy cells, the mean return elsewhere."""
    n = max(len(c.get("per_seed") or [None]) for c in metrics.get("cells", [])) or 1
    out: list[dict[str, dict[str, float]]] = [{} for _ in range(n)]
    for c in metrics.get("cells", []):
        runs = [ps["methods"] for ps in c["per_seed"]] if c.get("per_seed") else [c["methods"]]
        for k, methods in enumerate(runs):
            for m, v in (methods or {}).items():
                if v:
                    score = (
                        v.get("gap_closed") if c.get("family") == "windy" else v.get("mean_return")
                    )
                    out[k].setdefault(f"{c['case']}-n{c['num_envs']}", {})[m] = _num(score)
    return out


def _scale(g: Group, reps: int) -> str:
    seeds = [row for r in g.results for row in _scale_seeds(r.metrics)]
    windy = sorted({cell for row in seeds for cell in row if cell.startswith("windy")})
    methods = [m for m in PAPER_METHODS if all(m in row.get(c, {}) for row in seeds for c in windy)]
    parts = []
    for m in methods if windy else []:
        mat = np.array([[row[c][m] for c in windy] for row in seeds])  # (seeds, cells)
        e = aggregate.interval_estimates({m: mat}, reps)[m]
        parts.append(f"{m} {_ci(e, '.2f', 'iqm')}")
    return "gap to the exact optimum closed, windy cells (IQM over seeds x cells): " + (
        ", ".join(parts) or "no windy cells"
    )


# --------------------------------------------------------------------------------------------
# the report


@dataclass
class Report:
    """What ``taskvar report`` writes: the claims, the Results rows, the profile panels and the
    per-group summaries behind the compact tables and the regret figure
    (:mod:`~taskvar_torch.study.report_results`)."""

    groups: list[Group]
    claims: list[Claim]
    rows: list[tuple[str, str, int, str]]  # (label, headline, seeds, config digest)
    profiles: list[tuple[str, dict[str, Any], str]]  # (title, scores, x label)
    reps: int
    summaries: list[dict[str, Any]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    """One-line notes for stdout (where the Results went when a page had no markers)."""

    @property
    def scored(self) -> list[Claim]:
        """The claims given a verdict (an exploratory group's are ``not measured``)."""
        return [c for c in self.claims if c.verdict != NOT_MEASURED]


NOT_MEASURED = "not measured"
"""The verdict of a claim with no results, or only an exploratory group's (< ``MIN_SEEDS``)."""


def _exploratory(claims: list[Claim], g: Group) -> list[Claim]:
    """An exploratory group's claims: its figures kept, the verdict ``not measured`` and why."""
    why = f"{exploratory_note(len(g.seeds))} (a claim needs >= {MIN_SEEDS} training seeds)"
    return [Claim(c.key, c.group, c.ours, NOT_MEASURED, why, c.details) for c in claims]


def fig4_robustness(claims: list[Claim], groups: Sequence[Group]) -> list[Claim]:
    """Figure 4's verdicts held to :data:`FIG4_ROBUST`: where two or more realisations of one
    protocol (groups of one ``protocol``: the same grid and trials) give a claim different
    verdicts, each is :data:`NOT_ROBUST`; a lone realisation of fewer than
    :data:`FIG4_MIN_REPETITIONS` repetitions keeps its verdict, with the shortfall said."""
    fig4 = {g.label: g for g in groups if g.kind == "wargus-fig4"}
    out = []
    for c in claims:
        g = fig4.get(c.group)
        if g is None or c.verdict == NOT_MEASURED:
            out.append(c)
            continue
        twins = [
            o
            for o in claims
            if o.key == c.key
            and o.verdict != NOT_MEASURED
            and o.group in fig4
            and fig4[o.group].protocol == g.protocol
        ]
        if len({o.verdict for o in twins}) > 1:
            said = "; ".join(f"{o.verdict} ({o.group})" for o in twins)
            c = dataclasses.replace(
                c, verdict=NOT_ROBUST, reason=f"{c.reason}; realisations disagree: {said}"
            )
        elif len(twins) == 1 and len(g.seeds) < FIG4_MIN_REPETITIONS:
            c = dataclasses.replace(
                c,
                reason=f"{c.reason}; one realisation of {len(g.seeds)} repetitions "
                f"(< {FIG4_MIN_REPETITIONS}): not yet shown robust",
            )
        out.append(c)
    return out


def build_report(
    dirs: Sequence[str], reps: int = aggregate.REPS, mixed_commits: bool = False
) -> Report:
    """Read and check every ``DIR`` (:func:`collect`; results of different commits refused
    unless ``mixed_commits``, :func:`~taskvar_torch.study.report_folders.check_commits`), then
    compute every group's figures (docs/report.md)."""
    groups = collect(dirs)
    check_commits([(r.commit, str(r.path)) for g in groups for r in g.results], mixed_commits)
    claims: list[Claim] = []
    rows: list[tuple[str, str, int, str]] = []
    profiles: list[tuple[str, dict[str, Any], str]] = []
    summaries: list[dict[str, Any]] = []
    for g in groups:
        if g.kind == "windy-fig2":
            claim, headline, returns = _fig2(g, reps)
            claims.append(claim)
            profiles.append((g.label, returns, "mean held-out return per seed"))
            summaries.append(_fig2_summary(g, returns, reps))
        elif g.kind == "wargus-fig4":
            fig4_claims, headline, curves = _fig4(g, reps)
            claims += fig4_claims
            profiles.append((g.label, curves, "held-out items per episode, first half"))
            summaries.append(_fig4_summary(g, curves, reps))
        elif g.kind == "eval":
            claim, headline, scores = _eval(g, reps)
            if claim is not None:
                claims.append(claim)
            profiles.append((g.label, scores, "mean return per seed and point"))
            summaries.append(_eval_summary(g, scores, reps))
        else:  # the scale experiment's gap closed: its row of the table of every result only
            headline = _scale(g, reps)
        if g.exploratory:  # tabled and labelled, no verdict
            mine = [c for c in claims if c.group == g.label]
            claims = [c for c in claims if c.group != g.label] + _exploratory(mine, g)
            headline = f"{exploratory_note(len(g.seeds))}; {headline}"
        rows.append((g.label, headline, len(g.seeds), g.digest))
    return Report(groups, fig4_robustness(claims, groups), rows, profiles, reps, summaries)


# --------------------------------------------------------------------------------------------
# the compact tables' and the regret figure's data, per group (study/report_results.py)


def _group_info(g: Group, family: Any, row: str, budget: str, score: str) -> dict[str, Any]:
    return {
        "label": g.label,
        "digest": g.digest,
        "kind": g.kind,
        "family": str(family),
        "row": row,
        "budget": budget,
        "seeds": len(g.seeds),
        "score": score,
        "commit": g.commit if len({r.commit for r in g.results}) == 1 else None,
    }


def failed_below(family: str) -> float | None:
    """The failure rule of ``family`` (``Family.failed_below``, docs/report.md#failed-seeds);
    ``None`` for a family without one or not installed here (its rows keep their cells)."""
    fam = FAMILIES.get(family)
    return None if fam is None else fam.failed_below


def _frames(train: Any) -> str:
    frames = train.get("total_frames") if isinstance(train, dict) else None
    return "-" if frames is None else at_a_glance.frames_text(frames)


def _with_ceiling(per_seed: dict[str, np.ndarray]) -> tuple[str, Any, set[str]] | None:
    """The regret to the ``informed`` head where it was evaluated and its mean is at least every
    memoryless method's (a ceiling in this row, ``report_results.is_ceiling_row``), from sampled
    returns; ``None`` elsewhere: no regret is taken against what is no ceiling."""
    if at_a_glance.CEILING not in per_seed:
        return None
    means = {m: {"mean": float(np.mean(v))} for m, v in per_seed.items()}
    if not at_a_glance.is_ceiling_row(means):
        return None
    reference, arrays = at_a_glance.regret_to_ceiling(per_seed)
    return reference, arrays, set(arrays)


def _fig2_summary(g: Group, returns: dict[str, Any], reps: int) -> dict[str, Any]:
    per_seed = {m: np.asarray(v, dtype=np.float64) for m, v in returns.items()}
    row = "Figure 2 protocol, " + g.label.removeprefix("windy-fig2, ")
    info = _group_info(
        g,
        g.config.get("family") or g.kind,
        row,
        _frames(g.config.get("train")),
        "mean return per held-out episode",
    )
    return at_a_glance.summarise(
        info, per_seed, _with_ceiling(per_seed), reps, failed_below(info["family"])
    )


def _fig4_summary(g: Group, curves: dict[str, Any], reps: int) -> dict[str, Any]:
    per_seed = {m: np.asarray(c, dtype=np.float64).mean(1) for m, c in curves.items()}
    half = np.asarray(next(iter(curves.values()))).shape[1]
    row = f"Figure 4 {g.label.removeprefix('wargus-fig4, ')}: trials 1-{half}"
    trials = g.config.get("experiment", {}).get("trials")
    info = _group_info(
        g,
        g.config.get("family") or g.kind,
        row,
        f"{trials} trials",
        "Figure 4: items per held-out episode over the first half of the trials",
    )
    return at_a_glance.summarise(
        info, per_seed, _with_ceiling(per_seed), reps, failed_below(info["family"])
    )


def _eval_budget(g: Group) -> str:
    """The heads' training frames, and a baseline's own where it trained on another budget:
    ``300k frames (recurrent 1.2M)``."""
    budget = _frames(g.config.get("bundle", {}).get("train"))
    own: dict[str, str] = {}
    for r in g.results:
        for m, frames in (r.metrics.get("baseline_frames") or {}).items():
            text = at_a_glance.frames_text(frames) if frames else budget
            if text != budget:
                own[m] = text.removesuffix(" frames")
    if own:
        budget += " (" + ", ".join(f"{m} {t}" for m, t in sorted(own.items())) + ")"
    return budget


def _eval_summary(g: Group, scores: dict[str, np.ndarray], reps: int) -> dict[str, Any]:
    family = g.config["eval"]["family"]
    per_seed = {m: s.mean(1) for m, s in scores.items()}  # the points' mean, per seed
    n = next(iter(scores.values())).shape[1]
    info = _group_info(
        g,
        family,
        at_a_glance.row_name(g.label, family),
        _eval_budget(g),
        "mean return per episode" + (f" (mean over a curve's {n} points)" if n > 1 else ""),
    )
    points = [r.metrics["points"] for r in g.results]
    rows = [p["methods"][m] for pts in points for p in pts for m in scores]
    regret = None
    if all("regret_mean" in r for r in rows):  # the exact per-instance optimum, every point
        arrays = {
            m: np.array(
                [
                    np.mean(
                        [
                            _score(r, "points", i, "methods", m, "regret_mean")
                            for i in range(len(pts))
                        ]
                    )
                    for r, pts in zip(g.results, points)
                ]
            )
            for m in scores
        }
        sampled = {
            m
            for m in scores
            if any(p["methods"][m].get("regret_sampled") for pts in points for p in pts)
        }
        regret = (at_a_glance.EXACT, arrays, sampled)
    else:
        regret = _with_ceiling(per_seed)
    return at_a_glance.summarise(info, per_seed, regret, reps, failed_below(family))


__all__ = [
    "CLAIMS",
    "FIG4_MIN_REPETITIONS",
    "NO_WORSE",
    "NOT_MEASURED",
    "NOT_ROBUST",
    "PAPER_METHODS",
    "RULES",
    "SPEED_RATIO",
    "Claim",
    "Report",
    "build_report",
    "fig4_robustness",
]
