"""scripts/evidence.py's arguments: train from a config, or evaluate bundles already trained."""

from __future__ import annotations

import importlib.util
import json
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
