"""``taskvar report`` refuses non-finite inputs (issue 58): a ``nan`` or ``inf`` in an
``episodes.csv`` or a ``metrics.json`` it aggregates (or the ``null`` the library writes for
one) is one line naming the file, the row and the column, and nothing is written."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from test_report import _run, eval_folder, fig2_folder, fig4_folder  # tests/study/

CSV = "shift,method,episode,return,length,interruptions\n"


def _evals(tmp_path: Path) -> list[Path]:
    folders = []
    for k in range(5):
        f = eval_folder(tmp_path / "eval" / f"seed{k}", k, {"averaging": 5.0, "informed": 1.0})
        rows = [f",averaging,{i},{-5.0 - i},{7 + i},0" for i in range(3)]
        rows += [f",informed,{i},-4.0,6,0" for i in range(3)]
        (f / "episodes.csv").write_text(CSV + "\n".join(rows) + "\n")
        folders.append(f)
    return folders


def _refused(argv, capsys, *words):
    rc, _, err = _run(argv, capsys)
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    for w in words:
        assert w in err, (w, err)
    assert "finite" in err
    return err


def test_finite_results_pass_and_a_method_named_like_inf_is_no_number(tmp_path, capsys):
    _evals(tmp_path)
    assert _run([str(tmp_path / "eval"), "--out", str(tmp_path / "c.md")], capsys)[0] == 0


@pytest.mark.parametrize("bad", ["nan", "inf", "-Infinity", "NaN"])
def test_a_non_finite_episode_is_refused_naming_file_row_and_column(tmp_path, capsys, bad):
    folders = _evals(tmp_path)
    path = folders[2] / "episodes.csv"
    lines = path.read_text().splitlines()
    lines[3] = f",averaging,2,{bad},9,0"  # line 4 of the file (the header is line 1)
    path.write_text("\n".join(lines) + "\n")
    out = tmp_path / "docs" / "claims.md"
    _refused([str(tmp_path / "eval"), "--out", str(out)], capsys, str(path), "row 4", "'return'")
    assert not out.parent.exists()


def test_a_non_finite_number_in_metrics_json_is_refused_naming_its_key(tmp_path, capsys):
    folders = _evals(tmp_path)
    path = folders[1] / "metrics.json"
    m = json.loads(path.read_text())
    m["points"][1]["methods"]["informed"]["mean_return"] = float("inf")  # json writes Infinity
    path.write_text(json.dumps(m))
    out = tmp_path / "claims.md"
    key = "points[1].methods.informed.mean_return"
    _refused([str(tmp_path / "eval"), "--out", str(out)], capsys, str(path), key, "inf")
    m["points"][1]["methods"]["informed"]["mean_return"] = None  # the library's non-finite
    path.write_text(json.dumps(m))
    _refused([str(tmp_path / "eval"), "--out", str(out)], capsys, str(path), key, "None")
    assert not out.exists()


def test_a_null_figure2_or_figure4_score_is_refused(tmp_path, capsys):
    for k in range(5):
        fig2_folder(tmp_path / "fig2" / f"seed{k}", k, no_worse=0.9, better=0.1)
    path = tmp_path / "fig2" / "seed3" / "metrics.json"
    m = json.loads(path.read_text())
    m["heldout"]["fraction_better"] = None
    path.write_text(json.dumps(m))
    out = tmp_path / "claims.md"
    _refused([str(tmp_path / "fig2"), "--out", str(out)], capsys, "heldout.fraction_better")
    lead = {"averaging": 1.0, "options": 1.5, "interruption": 2.0, "hierarchy": 2.5}
    folder = fig4_folder(tmp_path / "fig4", range(5), lead)
    m = json.loads((folder / "metrics.json").read_text())
    m["heldout"]["methods"]["options"]["curve_per_rep"][2][7] = None
    (folder / "metrics.json").write_text(json.dumps(m))
    _refused([str(folder), "--out", str(out)], capsys, "options.curve_per_rep[2][7]")
    assert not out.exists()
