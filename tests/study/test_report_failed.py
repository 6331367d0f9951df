"""A cell says ``k/n seeds failed`` (docs/report.md#failed-seeds, issue 56): where a family
declares what failure means for its score (``Family.failed_below``), ``taskvar report`` counts the
training seeds of each method and row scoring below it; a family without the rule keeps its cells,
and a summary kept by an older report (no count) renders as before."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import pytest
from test_report import methods_folder  # tests/study/

from taskvar_torch import cli
from taskvar_torch.families import FAMILIES, family, register_family
from taskvar_torch.study import report_results as glance

REPS = "100"
EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "corridor"
FAILING = {  # per seed: options fails on seeds 1 and 3 (below 0.5), the rest never
    "averaging": [2.0, 2.1, 1.9, 2.0, 2.05],
    "options": [2.2, 0.1, 2.3, -1.0, 2.1],
    "interruption": [1.0, 0.9, 1.1, 1.0, 0.95],
    "informed": [3.0, 3.1, 2.9, 3.0, 3.05],
}


@pytest.fixture(scope="module")
def strict():
    """A registered test family whose own failure rule is 0.5 (the corridor example's env)."""
    sys.path.insert(0, str(EXAMPLE))
    import taskvar_corridor as corridor

    fam = register_family(
        dataclasses.replace(corridor.family(), name="corridor_strict", failed_below=0.5),
        replace=True,
    )
    yield fam
    FAMILIES._families.pop(fam.name, None)


def _folders(root: Path, fam: str, returns: dict[str, list[float]]) -> Path:
    """Five one-point ``taskvar eval`` folders of family ``fam``: seed ``k``'s method ``m``
    returns ``returns[m][k]`` (tests/study/test_report.py's layout)."""
    for k in range(5):
        methods_folder(root / f"seed{k}", k, fam, "train", {m: v[k] for m, v in returns.items()})
        path = root / f"seed{k}" / "metrics.json"
        metrics = json.loads(path.read_text())
        for m, v in returns.items():  # exactly these numbers (no per-seed offset)
            metrics["points"][0]["methods"][m]["mean_return"] = v[k]
        path.write_text(json.dumps(metrics))
    return root


def _report(dirs: list[Path], page: Path, capsys) -> str:
    try:
        rc = cli.main(["report", *map(str, dirs), "--page", str(page), "--add", "--reps", REPS])
    except SystemExit as e:
        rc = e.code
    assert rc == 0, capsys.readouterr().err
    return page.read_text()


def _cells(page: str, fam: str) -> dict[str, str]:
    lines = page.split(f"**{fam}**:")[1].strip().splitlines()
    head, _, row = lines[2:5]
    names = [c.strip() for c in head.strip("|").split("|")][2:]
    return dict(zip(names, [c.strip() for c in row.strip("|").split("|")][2:]))


def test_a_method_failing_on_two_seeds_of_five_says_so_and_no_other_cell_does(
    strict, tmp_path, capsys
):
    page = _report([_folders(tmp_path / "e", strict.name, FAILING)], tmp_path / "r.md", capsys)
    cells = _cells(page, strict.name)
    assert cells["options"].endswith(f"(2/5 {glance.FAILED})")
    assert [m for m, c in cells.items() if glance.FAILED in c] == ["options"]
    assert "a seed below 0.5 failed" in page.split(f"**{strict.name}**:")[1].splitlines()[0]
    assert glance.FAILED_LEGEND in page
    (group,) = json.loads((tmp_path / "docs" / "claims-results.json").read_text())["groups"]
    assert group["failed_below"] == 0.5  # the family's own threshold, read from the registry
    counts = {m: (e["seeds_failed"], e["seeds"]) for m, e in group["methods"].items()}
    assert counts == {
        "averaging": (0, 5),
        "options": (2, 5),
        "interruption": (0, 5),
        "informed": (0, 5),
    }


def test_the_marks_stay_and_the_count_follows_them():
    info = {"label": "eval x --test train", "digest": "d", "kind": "eval", "family": "x"}
    info |= {"row": "train", "budget": "1k frames", "seeds": 5, "score": "mean return"}
    per_seed = {m: np.asarray(v) for m, v in FAILING.items()}
    s = glance.summarise(info, per_seed, None, int(REPS), failed_below=2.0)
    plain = glance.summarise(info, per_seed, None, int(REPS))
    assert s["best"] == plain["best"] and s["not_separated"] == plain["not_separated"]
    table = glance.tables_markdown([s])
    row = table.splitlines()[-1]
    cells = [c.strip() for c in row.strip("|").split("|")][2:]
    best = f"**{glance._cell(plain, s['best'])[2:-2]}**"
    assert best in row  # bold unchanged, the count after it
    assert cells[0] == f"{glance._cell(plain, 'averaging')} (1/5 {glance.FAILED})"  # 1.9 < 2.0
    assert cells[2] == f"{glance._cell(plain, 'interruption')} (5/5 {glance.FAILED})"


@pytest.mark.parametrize("fam", ["windy", "wargus"])
def test_a_family_without_the_rule_keeps_its_cells(fam, tmp_path, capsys):
    assert family(fam).failed_below is None
    page = _report([_folders(tmp_path / "e", fam, FAILING)], tmp_path / "r.md", capsys)
    assert glance.FAILED not in page and "failed" not in page.split(f"**{fam}**:")[1]
    (group,) = json.loads((tmp_path / "docs" / "claims-results.json").read_text())["groups"]
    assert "failed_below" not in group
    assert all("seeds_failed" not in e for e in group["methods"].values())


def test_a_summary_kept_by_an_older_report_renders_without_counts():
    info = {"label": "eval x --test train", "digest": "d", "kind": "eval", "family": "x"}
    info |= {"row": "train", "budget": "1k frames", "seeds": 5, "score": "mean return"}
    per_seed = {m: np.asarray(v) for m, v in FAILING.items()}
    new = glance.summarise(info, per_seed, None, int(REPS), failed_below=0.5)
    old = {k: v for k, v in new.items() if k != "failed_below"}
    old["methods"] = {
        m: {k: v for k, v in e.items() if k in ("mean", "ci95")} for m, e in new["methods"].items()
    }
    assert glance.FAILED not in glance.tables_markdown([old])
    assert glance.FAILED in glance.tables_markdown([new])


def test_the_builtin_rules_are_declared_on_the_families():
    """Taxi and MiniGrid declare a rule (their docstrings justify it from the reward), windy and
    Wargus none; a bad value is one line naming the field."""
    assert family("taxi").failed_below == -100.0 and family("minigrid").failed_below == 0.1
    assert family("windy").failed_below is None and family("wargus").failed_below is None
    for bad in ("low", float("nan"), True):
        with pytest.raises(ValueError, match=r"'taxi_bad': failed_below must be a finite number"):
            register_family(dataclasses.replace(family("taxi"), name="taxi_bad", failed_below=bad))
