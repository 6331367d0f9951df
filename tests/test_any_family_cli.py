"""The commands know the family registry (issue 46 item 5): ``taskvar train --help`` names every
registered family with its instance distributions, tests and own keys (an outside family's
included, read from the registry), ``--help-all`` documents its keys, and ``taskvar experiment
scale`` takes any family's config as its one case (examples/corridor, registered here under a
name of the tests' own)."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import pytest
import torch

from taskvar_torch import register_family
from taskvar_torch.cli import main
from taskvar_torch.families import FAMILIES

torch.set_num_threads(1)
ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "corridor"
sys.path.insert(0, str(EXAMPLE))
import taskvar_corridor as corridor  # noqa: E402

NAME = "hall2"  # the example under a name no other test or installed package uses


@pytest.fixture
def hall():
    fam = dataclasses.replace(corridor.family(), name=NAME)
    register_family(fam, replace=True)
    yield fam
    FAMILIES._families.pop(NAME, None)


def _help(argv, capsys) -> str:
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 0
    return capsys.readouterr().out


def test_train_help_names_the_registered_families_and_their_keys(hall, capsys):
    text = _help(["train", "--help"], capsys)
    for name, fam in FAMILIES.items():
        line = next((ln for ln in text.splitlines() if ln.startswith(f"  {name}: ")), None)
        assert line is not None, name
        assert f"env.instances {', '.join(fam.instance_names)}" in line
        assert f"eval.test {', '.join(fam.tests)}" in line
    assert f"own keys env.{NAME}.{{length, horizon}}" in text
    full = _help(["train", "--help-all"], capsys)
    assert f"  env.{NAME}.length (int" in full and f"  {NAME}: " in full


def _family_yaml(tmp_path: Path) -> Path:
    text = (EXAMPLE / "configs" / "corridor.yaml").read_text()
    text = text.replace("family: corridor", f"family: {NAME}").replace("corridor:", f"{NAME}:")
    path = tmp_path / "hallway.yaml"
    path.write_text(text)
    return path


def test_the_scale_experiment_takes_a_family_config_as_its_one_case(hall, tmp_path, capsys):
    from taskvar_torch.study.scale import default_config_path, load_scale_config

    config = _family_yaml(tmp_path)
    quick = load_scale_config(config, quick=True)
    default = load_scale_config(default_config_path(), quick=True)
    assert [c.name for c in quick.cases] == ["hallway"] and quick.only == ()
    assert quick.total_frames == default.total_frames and quick.num_envs == default.num_envs
    out = tmp_path / "scale"
    argv = ["experiment", "scale", str(config), "--out", str(out), "--no-progress", "--no-plots"]
    sizes = [
        "total_frames=1024",
        "num_envs=[8]",
        "eval_episodes=16",
        "eval_batch_size=16",
        "heldout_episodes=0",
        "curve_points=0",
    ]
    assert main([*argv, *sizes]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    (cell,) = metrics["cells"]
    assert cell["case"] == "hallway" and cell["family"] == NAME and cell["frames"] == 1024
    assert set(cell["methods"]) >= {"averaging", "options", "interruption"}


def test_a_scale_config_still_loads_as_one(tmp_path):
    from taskvar_torch.study.scale import default_config_path, load_scale_config

    cfg = load_scale_config(default_config_path(), quick=True)
    assert len(cfg.cases) > 1 and cfg.only  # the quick overrides' own selection
    bad = tmp_path / "bad.yaml"
    bad.write_text("famly: windy\n")
    with pytest.raises(ValueError, match="unknown config key 'famly'"):
        load_scale_config(bad)
