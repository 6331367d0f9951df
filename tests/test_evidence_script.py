"""scripts/evidence.py's arguments: train from a config, or evaluate bundles already trained."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _script():
    spec = importlib.util.spec_from_file_location("evidence", ROOT / "scripts" / "evidence.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_config_or_bundles_not_both(tmp_path, capsys):
    ev = _script()
    for argv in ([], ["configs/windy.yaml", "--bundles", "x"]):
        with pytest.raises(SystemExit) as e:
            ev.main([*argv, "--out", str(tmp_path)])
        assert e.value.code == 2
    assert "give a config to train or --bundles" in capsys.readouterr().err


def test_bundles_without_final_pt_are_named(tmp_path):
    (tmp_path / "rep0").mkdir()
    with pytest.raises(SystemExit, match=r"--bundles: no final.pt in .*rep0"):
        _script().main(["--bundles", str(tmp_path / "rep0"), "--out", str(tmp_path / "out")])


def test_table_reads_each_seeds_metrics(tmp_path):
    """The table is the mean over the seeds' ``metrics.json`` with its 95% CI, per method."""
    for k, v in enumerate((1.0, 2.0, 3.0)):
        d = tmp_path / "eval-train" / f"seed{k}"
        d.mkdir(parents=True)
        point = {"methods": {"averaging": {"mean_return": v, "regret_mean": 3.0 - v}}}
        (d / "metrics.json").write_text(json.dumps({"points": [point]}))
    text = _script().table(tmp_path, ["train"], reps=200)
    assert "test train: 3 training seeds" in text
    row = next(line for line in text.splitlines() if line.strip().startswith("averaging"))
    assert "2.000" in row and "1.000" in row  # mean return 2, mean regret 1


def _results():
    spec = importlib.util.spec_from_file_location("results", ROOT / "scripts" / "results.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["results"] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def test_make_results_lists_every_readme_row_then_the_report(tmp_path, capsys):
    """scripts/results.py (make results): every Results family has a row, each row's folders are
    what the report reads, into the page whose markers ``taskvar report`` fills (docs/results.md,
    which the README links), Figure 4 runs >= 10 repetitions."""
    res = _results()
    assert res.main(["--list", "--out", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    for name in ("windy", "windy-whole-column", "wargus-fig4", "wargus-large", "taxi", "minigrid"):
        assert f"\n{name}" in "\n" + text, name
    assert "experiment.runs=10" in text and text.count("[report, to run]") == 1
    report = [line for line in text.splitlines() if "[report" in line][0]
    for row in res.rows(tmp_path):
        for folder in row.reads:
            assert str(tmp_path / folder) in report
    assert report.endswith(f"--out docs/claims.md --page {res.RESULTS_PAGE}")
    page = (ROOT / res.RESULTS_PAGE).read_text()
    assert page.count("<!-- report:results:start -->") == 1  # the markers the report fills
    assert res.RESULTS_PAGE in (ROOT / "README.md").read_text()
    assert res.FIG4_RUNS >= 10
    with pytest.raises(SystemExit) as e:
        res.main(["--list", "--only", "nope", "--out", str(tmp_path)])
    assert e.value.code == 2


def test_make_results_refuses_a_folder_of_another_commit(tmp_path, monkeypatch):
    res = _results()
    (tmp_path / ".commit").write_text("0000000\n")
    monkeypatch.setattr(res, "commit", lambda: ("1234567", False))
    with pytest.raises(SystemExit, match="holds rows of commit 0000000, this checkout is 1234567"):
        res.main(["--out", str(tmp_path)])
    monkeypatch.setattr(res, "commit", lambda: ("1234567", True))
    with pytest.raises(SystemExit, match="differ from the commit"):
        res.main(["--out", str(tmp_path / "new")])
