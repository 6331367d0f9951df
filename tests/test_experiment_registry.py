"""The experiment registry: every entry's functions exist, folders are recognised by their
``metrics.json``, not by their files, and unknown folders are one-line errors."""

from __future__ import annotations

import json

import pytest

from taskvar_torch.cli.study import EXPERIMENTS as CLI_EXPERIMENTS
from taskvar_torch.experiments.registry import EXPERIMENTS, experiment, experiment_of_folder


@pytest.mark.parametrize("name", sorted(EXPERIMENTS))
def test_every_entry_points_at_real_functions_and_a_config(name):
    exp = experiment(name)
    for attr in ("run", "plot", "default_config"):
        assert callable(exp.function(attr)), (name, attr)
    assert exp.default_config_path().is_file()
    assert name in CLI_EXPERIMENTS


def test_folders_are_recognised_by_their_metrics(tmp_path):
    for name in EXPERIMENTS:
        (tmp_path / name).mkdir()
        (tmp_path / name / "metrics.json").write_text(json.dumps({"experiment": name}))
        assert experiment_of_folder(tmp_path / name).name == name


@pytest.mark.parametrize(
    ("content", "part"),
    [
        (None, "no metrics.json"),
        ("{not json", "not a metrics file"),
        ('{"experiment": "x"}', "'x'"),
    ],
)
def test_unknown_folders_are_one_line_errors(tmp_path, content, part):
    if content is not None:
        (tmp_path / "metrics.json").write_text(content)
    with pytest.raises(ValueError) as info:
        experiment_of_folder(tmp_path)
    assert "\n" not in str(info.value) and part in str(info.value)


def test_unknown_experiment_names_the_known_ones():
    with pytest.raises(ValueError, match="experiment must be one of"):
        experiment("fig3")


def test_call_refuses_an_option_the_run_does_not_take(monkeypatch):
    seen = {}

    def run(cfg, out_dir, workers=1, plots=True):
        seen.update(cfg=cfg, out_dir=out_dir, workers=workers, plots=plots)
        return {"ok": True}

    exp = experiment("wargus-fig4")
    monkeypatch.setattr(type(exp), "function", lambda self, attr: run)
    assert exp.call("cfg", "out", workers=3, plots=False) == {"ok": True}
    assert seen == {"cfg": "cfg", "out_dir": "out", "workers": 3, "plots": False}
    with pytest.raises(ValueError, match="^quick is not an option of wargus-fig4$"):
        exp.call("cfg", "out", quick=True)  # never dropped
    with pytest.raises(ValueError, match="learns from scratch"):  # the experiment's own reason
        exp.call("cfg", "out", checkpoint="x.pt")
