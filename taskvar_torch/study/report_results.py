"""The Results at a glance (docs/results.md; docs/report.md#taskvar-report), written by
``taskvar report``: per family one compact table (mean over seeds with its 95% CI, the best in
bold, ``≈`` where not separated, :func:`marks`; ``(k/n seeds failed)``), one regret figure, and
the per-group summaries behind both (:func:`summarise`). Nothing branches on a family's name.
"""

from __future__ import annotations

import io
import re
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from taskvar_torch.config import METHODS
from taskvar_torch.heads.recurrent import BASELINES, SEES_MORE
from taskvar_torch.study import aggregate
from taskvar_torch.study.report_folders import MIN_SEEDS, exploratory_note

CEILING = "informed"
"""The baseline that sees the hidden instance: a ceiling where :func:`ceiling_gate` says so, shown
but never marked the winner."""
NO_CEILING = "no ceiling"
"""The informed cell's note in a row where it is not a ceiling (:func:`ceiling_gate`)."""


def is_ceiling_row(methods: Mapping[str, Mapping[str, Any]]) -> bool:
    """Whether ``informed``'s mean in one row is at least every memoryless method's (the row's
    half of the gate, docs/memory.md#the-ceiling-gate); a row without it is none."""
    if CEILING not in methods:
        return False
    top = [e["mean"] for m, e in methods.items() if m not in SEES_MORE]
    return not top or methods[CEILING]["mean"] >= max(top)


def _validation_label(label: str) -> str:
    """The label of the same bundles' validation row: its ``--test`` made ``train``, a
    ``--shift`` curve's too (the curve is over the same bundles)."""
    return re.sub(r"--test \S+", "--test train", re.sub(r" --shift \S+", "", label))


def ceiling_gate(s: Mapping[str, Any], summaries: Sequence[Mapping[str, Any]]) -> tuple[bool, str]:
    """Whether a row may call ``informed`` a ceiling (docs/memory.md#the-ceiling-gate): on the
    validation row of the same bundles (``--test train``: fresh instances of the training
    distribution, never a test seed) its 95% CI reaches up to every memoryless method's mean or
    beyond, and in this row its mean is at least every memoryless method's. Returns ``(ok,
    why)``; ``why`` says which half failed, or that the gate could not run (no validation row)."""
    ms = s["methods"]
    if CEILING not in ms:
        return False, ""
    want = _validation_label(str(s.get("label", "")))
    val = next((v for v in summaries if v.get("label") == want and CEILING in v["methods"]), None)
    if val is None:
        return False, "the gate did not run: no --test train row of these bundles"
    inf = val["methods"][CEILING]
    behind = [
        m for m, e in val["methods"].items() if m not in SEES_MORE and inf["ci95"][1] < e["mean"]
    ]
    if behind:
        return False, f"behind {behind[0]} on the validation row (--test train)"
    if not is_ceiling_row(ms):
        return False, "its mean is below a memoryless method's in this row"
    return True, ""


ORDER = (*METHODS, *BASELINES)
"""The columns' order: the paper's methods, then the baselines."""
COLORS = dict(zip(ORDER, ("#4c72b0", "#dd8452", "#55a868", "#8172b3", "#c44e52", "#7f7f7f")))
EXACT = "exact optimum"
"""A regret's reference where the results have the exact per-instance optimum."""
DETAILS_START = "<details><summary>Every result"
DETAILS_END = "</details>"


def _ordered(methods: Sequence[str]) -> list[str]:
    known = [m for m in ORDER if m in methods]
    return known + [m for m in methods if m not in ORDER]


def summarise(
    group: Mapping[str, Any],
    per_seed: Mapping[str, np.ndarray],
    regret: tuple[str, Mapping[str, np.ndarray], set[str]] | None,
    reps: int,
    failed_below: float | None = None,
) -> dict[str, Any]:
    """One group's summary: ``group`` (label, digest, kind, family, row, budget, seeds, score), each
    method's mean and 95% CI over ``per_seed`` scores, the :func:`marks`, ``regret`` summarised the
    same way and, with ``failed_below`` (docs/report.md#failed-seeds), each method's
    ``seeds_failed``."""
    scores = {m: np.asarray(per_seed[m], dtype=np.float64) for m in _ordered(list(per_seed))}
    est = aggregate.interval_estimates(scores, reps)
    out = dict(group)
    out["methods"] = {m: {"mean": est[m]["mean"], "ci95": est[m]["mean_ci95"]} for m in scores}
    if failed_below is not None:
        out["failed_below"] = float(failed_below)
        for m, v in scores.items():
            out["methods"][m]["seeds"] = int(v.size)
            out["methods"][m]["seeds_failed"] = int(np.sum(v < failed_below))
    out.update(marks(scores, est, reps))
    out["regret"] = None
    if regret is not None:
        reference, arrays, sampled = regret
        arrays = {m: np.asarray(arrays[m], dtype=np.float64) for m in _ordered(list(arrays))}
        r_est = aggregate.interval_estimates(arrays, reps)
        out["regret"] = {
            "reference": reference,
            "methods": {
                m: {
                    "mean": r_est[m]["mean"],
                    "ci95": r_est[m]["mean_ci95"],
                    "sampled": m in sampled,
                }
                for m in arrays
            },
        }
    return out


def marks(
    scores: Mapping[str, np.ndarray], est: Mapping[str, Mapping[str, Any]], reps: int
) -> dict[str, Any]:
    """The table's marks of one group (docs/report.md, the Results at a glance): ``best``, the
    method of the highest mean among those that do not see the hidden instance (bold), and
    ``not_separated``, every other such method whose 95% CI is not separated from the best's
    (``≈``): the CI of its paired difference to the best over training seeds reaches 0 where
    both have one score per seed of the group (the same seeds, each seed's methods on the same
    episodes: ``separation`` is ``"paired"``), else (unpaired scores) the two means' CIs overlap
    (``"overlap"``). ``est``: :func:`~taskvar_torch.study.aggregate.interval_estimates` of
    ``scores``. The ceiling (:data:`CEILING`) is never marked."""
    contenders = [m for m in scores if m != CEILING]
    if not contenders:
        return {"best": None, "not_separated": [], "separation": None}
    best = max(contenders, key=lambda m: est[m]["mean"])
    others = [m for m in contenders if m != best]
    paired = [m for m in others if np.shape(scores[m]) == np.shape(scores[best])]
    diffs = aggregate.paired_differences(scores, [(best, m) for m in paired], reps)
    tied = []
    for m in others:
        if m in paired:
            close = diffs[f"{best} - {m}"]["mean_ci95"][0] <= 0
        else:  # no pairing: the two means' CIs overlap
            close = est[m]["mean_ci95"][1] >= est[best]["mean_ci95"][0]
        if close:
            tied.append(m)
    how = "paired" if len(paired) == len(others) else "overlap"
    return {"best": best, "not_separated": tied, "separation": how}


def regret_to_ceiling(per_seed: Mapping[str, np.ndarray]) -> tuple[str, dict[str, np.ndarray]]:
    """Where the results have no exact optimum: each method's regret to the ``informed`` head,
    seed by seed (``informed`` minus the method), the ceiling itself left out."""
    ceiling = np.asarray(per_seed[CEILING], dtype=np.float64)
    return CEILING, {
        m: ceiling - np.asarray(v, dtype=np.float64) for m, v in per_seed.items() if m != CEILING
    }


def row_name(label: str, family: str) -> str:
    """A group's label, shortened for its family's table: the family prefix of an evaluation and
    the ``--test``/``--shift`` flags dropped (a shift curve named by its key and points)."""
    text = label.removeprefix(f"eval {family}").strip()

    def curve(m: re.Match[str]) -> str:
        return f", shift {m.group(1).split('.')[-1]} ({len(m.group(2).split(','))} points)"

    text = re.sub(r" --shift (\S+?)=(\S+)", curve, text)
    return text.replace("--test ", "")


def frames_text(frames: Any) -> str:
    """Training frames as a budget: ``50k frames``, ``5M frames``."""
    n = int(frames)
    for div, unit in ((1_000_000, "M"), (1_000, "k")):
        if n >= div and n % (div // 10) == 0:
            return f"{n / div:g}{unit} frames"
    return f"{n} frames"


TIE_MARK = "≈"
"""The mark of a method not separated from the best (:func:`marks`)."""
FAILED = "seeds failed"
"""A cell's note ``(k/n seeds failed)``: ``k`` of its ``n`` training seeds scored below the
family's ``failed_below`` (docs/report.md#failed-seeds)."""
LEGEND = (
    f"**Bold**: the best mean of the methods that do not see the hidden instance; {TIE_MARK}: not "
    "separated from it (the 95% CI of the paired difference over training seeds reaches 0; "
    "unpaired: the CIs overlap). "
    f"`{CEILING}` sees the instance and is never marked; it is a ceiling only where its cell does "
    f"not say '{NO_CEILING}' (docs/memory.md#the-ceiling-gate: on the validation row it is at least "
    "as good as every memoryless method within its CI, and in the row its mean is at least theirs)."
)
"""The line under each compact table."""
FAILED_LEGEND = (
    f"(k/n {FAILED}): k of the method's n training seeds scored below the line its family draws "
    "from its reward (named beside the family; docs/report.md#failed-seeds)."
)
"""The legend's line on failed seeds, where a table has a family with a failure rule."""


def _marked(s: Mapping[str, Any]) -> tuple[str | None, list[str]]:
    """A summary's best and not-separated methods (a summary kept by an older ``taskvar report``
    holds ``winners``: the best, then those not separated from it)."""
    if "best" in s:
        return s["best"], list(s.get("not_separated") or [])
    winners = list(s.get("winners") or [])
    return (winners[0] if winners else None), winners[1:]


def failed_text(e: Mapping[str, Any]) -> str:
    """`` (k/n seeds failed)`` where ``k`` of a method's ``n`` seeds failed in a row
    (:func:`summarise`), else nothing (none failed, or a summary without a failure rule)."""
    k = int(e.get("seeds_failed") or 0)
    return f" ({k}/{int(e['seeds'])} {FAILED})" if k else ""


def _cell(s: Mapping[str, Any], m: str, summaries: Sequence[Mapping[str, Any]] = ()) -> str:
    e = s["methods"].get(m)
    if e is None:
        return "-"
    text = f"{e['mean']:.2f} [{e['ci95'][0]:.2f}, {e['ci95'][1]:.2f}]"
    best, tied = _marked(s)
    if m == CEILING and not ceiling_gate(s, summaries)[0]:
        text = f"{text} ({NO_CEILING})"
    elif m == best:
        text = f"**{text}**"
    elif m in tied:
        text = f"{text} {TIE_MARK}"
    return text + failed_text(e)


def _by_family(summaries: Sequence[Mapping[str, Any]]) -> dict[str, list[Mapping[str, Any]]]:
    out: dict[str, list[Mapping[str, Any]]] = {}
    for s in summaries:
        out.setdefault(s["family"], []).append(s)
    return out


def _seeds(s: Mapping[str, Any]) -> str:
    """A row's training seeds, labelled exploratory below ``MIN_SEEDS`` (no claims)."""
    n = int(s["seeds"])
    return str(n) if n >= MIN_SEEDS else f"{n} ({exploratory_note(n)})"


def tables_markdown(summaries: Sequence[Mapping[str, Any]]) -> str:
    """Per family one table: a row per group, the methods as columns (``-``: not evaluated)."""
    parts = [
        "Each cell: the method's score, mean over training seeds [95% stratified-bootstrap CI] "
        "(rliable); each seed plays its own test episodes, all its methods the same ones. " + LEGEND
    ]
    if any(s.get("failed_below") is not None for s in summaries):
        parts[0] += f" {FAILED_LEGEND}"
    for family, rows in _by_family(summaries).items():
        methods = _ordered(sorted({m for s in rows for m in s["methods"]}))
        scores = list(dict.fromkeys(s["score"] for s in rows))
        rules = sorted({s["failed_below"] for s in rows if s.get("failed_below") is not None})
        scores += [f"a seed below {v:g} failed" for v in rules]
        head = list(methods)
        parts.append(
            "\n".join(
                [
                    f"**{family}**: {'; '.join(scores)}",
                    "",
                    "| results | budget, seeds | " + " | ".join(head) + " |",
                    "| --- | --- | " + " | ".join("---" for _ in head) + " |",
                    *(
                        f"| {s['row']} | {s['budget']}, {_seeds(s)} | "
                        + " | ".join(_cell(s, m, summaries) for m in methods)
                        + " |"
                        for s in rows
                    ),
                ]
            )
        )
    return "\n\n".join(parts)


FIGURE_CAPTION = (
    "Regret per episode of each method, mean over training seeds with its 95% CI (lower is "
    "better; 0: as good as the reference): against the exact per-instance optimum, an agent that "
    "knows the hidden instance, where the results have it (filled markers: the exact value of a "
    "memoryless method's policy; hollow: from sampled returns, recurrent and informed); elsewhere "
    f"against the `{CEILING}` head (rows marked 'vs {CEILING}': a learnt ceiling, which a method "
    "can beat). Rows without either are in the tables only."
)


FIGURE_TITLE = (
    "Regret per episode: the return lost to the exact per-instance optimum, an agent that knows "
    f"the hidden instance\n(rows 'vs {CEILING}': to the {CEILING} head, a learnt ceiling). Mean "
    "over training seeds with 95% CI; lower is better.\nFilled: exact values of memoryless "
    "policies; hollow: from sampled returns."
)


def results_png(summaries: Sequence[Mapping[str, Any]], software: str) -> bytes | None:
    """The regret figure: one panel per family with regret, a row per group, a marker and CI per
    method (PNG bytes, ``Software`` = ``software``); ``None`` where no group has a regret."""
    panels = [
        (f, [s for s in rows if s.get("regret")]) for f, rows in _by_family(summaries).items()
    ]
    panels = [(f, rows) for f, rows in panels if rows]
    if not panels:
        return None
    from matplotlib.lines import Line2D
    from matplotlib.ticker import FuncFormatter

    from taskvar_torch.experiments.plots import pyplot

    plt = pyplot()
    methods_all = _regret_methods([s for _, rows in panels for s in rows])
    heights = [0.5 + 0.22 * len(rows) * len(_regret_methods(rows)) for _, rows in panels]
    fig, axes = plt.subplots(
        len(panels),
        1,
        figsize=(8.0, 1.0 + 0.5 * len(panels) + sum(heights)),  # title and legend, then panels
        squeeze=False,
        gridspec_kw={"height_ratios": heights},
        layout="constrained",
    )
    for ax, (family, rows) in zip(axes[:, 0], panels):
        methods = _regret_methods(rows)
        width = 0.8 / len(methods)
        lows, highs = [0.0], [0.0]
        for i, s in enumerate(rows):
            for k, m in enumerate(methods):
                r = s["regret"]["methods"].get(m)
                if r is None:
                    continue
                y = i + (k - (len(methods) - 1) / 2) * width
                lo, hi = r["ci95"]
                lows.append(lo)
                highs.append(hi)
                ax.errorbar(
                    r["mean"],
                    y,
                    xerr=[[max(r["mean"] - lo, 0.0)], [max(hi - r["mean"], 0.0)]],
                    fmt="o",
                    ms=5,
                    capsize=2,
                    color=COLORS.get(m, "k"),
                    mfc="white" if r["sampled"] else COLORS.get(m, "k"),
                )
        ax.set_yticks(
            range(len(rows)),
            [
                s["row"]
                + ("" if s["regret"]["reference"] == EXACT else f" (vs {CEILING})")
                + f"\n{s['budget']}, {s['seeds']} seeds"
                for s in rows
            ],
            fontsize=8,
        )
        ax.set_ylim(len(rows) - 0.5, -0.5)
        ax.axvline(0.0, color="k", lw=0.8)
        lo, hi = min(lows), max(highs)
        if max(abs(lo), abs(hi)) > 20:  # a failing method would flatten the rest
            ax.set_xscale("symlog", linthresh=1.0)  # linear within 1, logarithmic beyond
            ax.set_xlim(lo - 0.5 if lo < 0 else -0.5, hi * 1.5 if hi > 0 else 0.5)
            ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
            ax.set_xlabel("regret per episode (linear within 1, logarithmic beyond)", fontsize=8)
        else:
            pad = 0.05 * (hi - lo or 1.0)
            ax.set_xlim(lo - pad, hi + pad)
            ax.set_xlabel("regret per episode", fontsize=8)
        ax.set_title(family, fontsize=9, loc="left")
        ax.grid(axis="x", alpha=0.3)
    handles = [
        Line2D([], [], ls="", marker="o", color=COLORS.get(m, "k"), label=m) for m in methods_all
    ]
    handles += [
        Line2D([], [], ls="", marker="o", color="k", label="exact"),
        Line2D([], [], ls="", marker="o", color="k", mfc="white", label="sampled"),
    ]
    fig.suptitle(FIGURE_TITLE, fontsize=8)
    fig.legend(handles=handles, loc="outside lower center", ncol=len(handles), fontsize=7)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, metadata={"Software": software})
    plt.close(fig)
    return buf.getvalue()


def _regret_methods(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    return _ordered(sorted({m for s in rows for m in s["regret"]["methods"]}))


def results_block(
    summaries: Sequence[Mapping[str, Any]], details: str, figure: str | None, missing: int = 0
) -> str:
    """The Results block: the regret figure (``figure``: its path from the page) and
    its caption, the per-family tables, then ``details`` (the table of every result) folded
    away; ``missing``: detail rows whose group has no summary (kept from an older README)."""
    parts = []
    if figure is not None:
        parts += [f"![Regret per method and family]({figure})", FIGURE_CAPTION]
    if summaries:
        parts.append(tables_markdown(summaries))
    if missing:
        parts.append(
            f"{missing} row(s) of the table below are in no table above: results added before "
            "taskvar report kept their data; rerun taskvar report with every results folder."
        )
    n = max(len(details.strip().splitlines()) - 2, 0)
    parts.append(
        f"{DETAILS_START} ({n} rows: headline with IQM, training seeds, config, claims)</summary>"
        f"\n\n{details.strip()}\n\n{DETAILS_END}"
    )
    return "\n\n".join(parts)


def details_of(block: str) -> str:
    """The table of every result inside a Results block (all of an older block, which held only
    that table)."""
    if DETAILS_START not in block:
        return block
    inner = block.split(DETAILS_START, 1)[1].split(DETAILS_END, 1)[0]
    return inner.split("</summary>", 1)[-1]


__all__ = [
    "CEILING",
    "NO_CEILING",
    "ceiling_gate",
    "is_ceiling_row",
    "EXACT",
    "FAILED",
    "FAILED_LEGEND",
    "FIGURE_CAPTION",
    "FIGURE_TITLE",
    "LEGEND",
    "ORDER",
    "TIE_MARK",
    "details_of",
    "failed_text",
    "frames_text",
    "marks",
    "regret_to_ceiling",
    "results_block",
    "results_png",
    "row_name",
    "summarise",
    "tables_markdown",
]
