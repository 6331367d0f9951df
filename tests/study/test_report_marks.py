"""The compact tables' marks (study/report_results.py, issue 56): the best mean is bold, a method
whose CI is not separated from the best's carries a distinct mark, and a wide CI earns no bold."""

from __future__ import annotations

import numpy as np

from taskvar_torch.study import report_results as glance

REPS = 200


def _summary(per_seed: dict[str, list[float]]) -> dict:
    info = {"label": "eval taxi --test train", "digest": "d", "kind": "eval", "family": "taxi"}
    info |= {"row": "train", "budget": "300k frames", "seeds": 5, "score": "mean return"}
    return glance.summarise(info, {m: np.asarray(v) for m, v in per_seed.items()}, None, REPS)


def _cells(summary: dict) -> dict[str, str]:
    table = glance.tables_markdown([summary])
    head, _, row = [line for line in table.splitlines() if line.startswith("|")]
    names = [c.strip().removesuffix(" (ceiling)") for c in head.strip("|").split("|")][2:]
    return dict(zip(names, [c.strip() for c in row.strip("|").split("|")][2:]))


TAXI_LIKE = {  # the README's Taxi row: a wide interruption CI, a tight options one behind the best
    "averaging": [6.3, 4.0, 6.5, 5.2, 6.4],
    "options": [3.8, 3.9, 3.7, 3.9, 3.85],
    "interruption": [7.0, 7.0, -19.7, 7.0, -14.0],
    "recurrent": [6.1, 6.2, 6.15, 6.2, 6.15],
    "informed": [6.5, 6.6, 6.4, 6.5, 6.6],
}


def test_the_best_mean_is_bold_and_a_wide_ci_earns_a_mark_not_bold():
    s = _summary(TAXI_LIKE)
    assert s["best"] == "recurrent" and s["separation"] == "paired"
    assert s["not_separated"] == ["averaging", "interruption"]
    cells = _cells(s)
    assert cells["recurrent"].startswith("**6.16 [") and cells["recurrent"].endswith("]**")
    for m in ("averaging", "interruption"):  # not separated from the best: marked, not bold
        assert cells[m].endswith(f"] {glance.TIE_MARK}") and not cells[m].startswith("**")
    assert not cells["options"].startswith("**") and glance.TIE_MARK not in cells["options"]
    assert not cells["informed"].startswith("**") and glance.TIE_MARK not in cells["informed"]
    assert glance.LEGEND in glance.tables_markdown([s])


def test_scores_not_paired_by_seed_fall_back_on_ci_overlap():
    s = _summary({"averaging": [1.0, 1.1, 0.9, 1.0, 1.05], "options": [0.2, 1.4, 0.8]})
    assert s["best"] == "averaging" and s["separation"] == "overlap"
    assert s["not_separated"] == ["options"]  # CIs overlap
    far = _summary({"averaging": [1.0, 1.1, 0.9, 1.0, 1.05], "options": [-3.0, -3.1, -2.9]})
    assert far["not_separated"] == [] and far["separation"] == "overlap"


def test_a_summary_kept_by_an_older_report_keeps_its_marks():
    s = _summary(TAXI_LIKE)
    old = {k: v for k, v in s.items() if k not in ("best", "not_separated", "separation")}
    old["winners"] = ["recurrent", "averaging"]  # the old rule: the best, then the ties
    cells = _cells(old)
    assert cells["recurrent"].startswith("**") and cells["averaging"].endswith(glance.TIE_MARK)
    assert not cells["interruption"].startswith("**")
    assert glance.TIE_MARK not in cells["interruption"]


def _row(label, **means):
    return {
        "label": label,
        "methods": {m: {"mean": v, "ci95": [v - 0.1, v + 0.1]} for m, v in means.items()},
    }


def test_informed_is_called_a_ceiling_only_where_the_gate_holds():
    """docs/memory.md#the-ceiling-gate: on the validation row (--test train) informed's CI
    reaches every memoryless method's mean (blind included, recurrent not), and in the row its
    mean is at least theirs; else the cell says 'no ceiling' and the gate says why."""
    from taskvar_torch.study.report_results import NO_CEILING, _cell, ceiling_gate

    train = _row("eval x --test train", averaging=3.0, blind=2.5, recurrent=9.0, informed=2.95)
    held = _row("eval x --test heldout", averaging=3.0, blind=2.5, recurrent=9.0, informed=3.2)
    rows = [train, held]
    assert ceiling_gate(held, rows) == (True, "")  # 2.95 + 0.1 >= 3.0; 3.2 >= 3.0 here
    ok, why = ceiling_gate(train, rows)
    assert not ok and "below a memoryless method's in this row" in why
    assert _cell(train, "informed", rows).endswith(f"({NO_CEILING})")
    behind = _row("eval x --test train", averaging=2.0, blind=3.5, informed=2.3)
    ok, why = ceiling_gate(held, [behind, held])
    assert not ok and "behind blind on the validation row" in why
    ok, why = ceiling_gate(held, [held])
    assert not ok and "no --test train row" in why
    assert NO_CEILING not in _cell(held, "informed", rows)
    # a shift curve of the same bundles is validated on their --test train row too
    shift = _row("eval x --test heldout --shift env.instances.p=0.0,1.0", averaging=-13.8,
                 blind=-14.5, recurrent=-4.6, informed=-4.3)  # fmt: skip
    assert ceiling_gate(shift, [train, shift]) == (True, "")
