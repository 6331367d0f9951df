"""The public family API (docs/families.md): ``register_family``, the entry-point group,
``check_family``, a family's own ``env.<name>`` keys, and the outside example family
(``examples/corridor``) installed and run through the installed ``taskvar`` command."""

from __future__ import annotations

import dataclasses
import os
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from taskvar_torch import TestDistribution, check_family, family, register_family
from taskvar_torch.config import config_from_dict, config_to_dict, load_config
from taskvar_torch.experiments.shift import parse_shift, shift_points
from taskvar_torch.families import FAMILIES
from taskvar_torch.subtasks.base import Hierarchy

torch.set_num_threads(1)
ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "corridor"
sys.path.insert(0, str(EXAMPLE))  # the example's module, without installing it (in-process tests)
import taskvar_corridor as corridor  # noqa: E402

NAME = "hall"  # the example's family under a name of the tests' own (the installed one is left be)


@pytest.fixture
def hall():
    """The example family registered as ``hall`` for one test."""
    fam = dataclasses.replace(corridor.family(), name=NAME)
    register_family(fam, replace=True)
    yield fam
    FAMILIES._families.pop(NAME, None)


def _yaml(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "cfg.yaml"
    path.write_text(text)
    return path


def test_registered_family_is_found_and_its_keys_load_strictly(hall, tmp_path):
    assert family(NAME) is hall and NAME in FAMILIES
    path = _yaml(tmp_path, f"family: {NAME}\nenv:\n  num_envs: 4\n  {NAME}:\n    length: 9\n")
    cfg = load_config(path)
    assert cfg.env.hall.length == 9 and hall.env_config(cfg).length == 9
    assert config_from_dict(config_to_dict(cfg)) == cfg
    assert pickle.loads(pickle.dumps(cfg)) == cfg  # the schema class is made at run time
    with pytest.raises(ValueError, match=r"unknown config key 'env\.hall\.lenght'.*'length'"):
        load_config(path, ["env.hall.lenght=3"])
    with pytest.raises(ValueError, match=r"env\.hall\.length must be >= 3, got 2"):
        load_config(path, ["env.hall.length=2"])
    with pytest.raises(ValueError, match=r"env\.instances must be one of .*'slippery'"):
        load_config(path, ["env.instances=stormy"])


def test_another_familys_keys_are_refused(hall, tmp_path):
    path = _yaml(tmp_path, "family: windy\nenv:\n  hall:\n    length: 9\n")
    with pytest.raises(ValueError, match=r"unknown config key 'env\.hall'"):
        load_config(path)


def test_a_windy_config_dict_is_the_same_whichever_families_are_registered(hall):
    cfg = load_config(ROOT / "configs" / "windy.yaml")
    assert "hall" not in config_to_dict(cfg)["env"] and "taxi" not in config_to_dict(cfg)["env"]


def test_name_clashes_and_bad_declarations_are_refused(hall):
    with pytest.raises(ValueError, match="'windy' is built in"):
        register_family(dataclasses.replace(hall, name="windy"))
    with pytest.raises(ValueError, match="already registered; pass replace=True"):
        register_family(dataclasses.replace(hall))
    with pytest.raises(ValueError, match="name must be an identifier"):
        register_family(dataclasses.replace(hall, name="my family"))
    with pytest.raises(ValueError, match="config_class must be a frozen dataclass"):
        register_family(dataclasses.replace(hall, name="hall2", config_class=dict))
    with pytest.raises(ValueError, match="instance_dim and instance_features go together"):
        register_family(dataclasses.replace(hall, name="hall2", instance_dim=2))
    with pytest.raises(ValueError, match="takes a Family"):
        register_family("hall")  # type: ignore[arg-type]
    # an old spelling that is no KEY or SECTION.KEY of config_class would break every config load
    for bad in ("train.a.b", "nonexistent", "train.nonexistent", "1x"):
        with pytest.raises(ValueError, match=f"legacy_env_keys entries .* got '{bad}'"):
            register_family(dataclasses.replace(hall, name="hall2", legacy_env_keys=(bad,)))


class _SplitDependentEnv(corridor.CorridorEnv):
    """Breaks the contract: the instance depends on the batch position, not the global index."""

    def _set_seed(self, seed):
        self.index_offset = 0
        super()._set_seed(seed)


class _NoInstanceEnv(corridor.CorridorEnv):
    def _out(self, reward=None, terminated=None, truncated=None):
        return super()._out(reward, terminated, truncated).exclude("instance")


class _BadSubtasks(corridor.CorridorSubtasks):
    def initiation(self, td):
        return super().initiation(td)[..., :1]


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"env_class": _SplitDependentEnv}, "changes with the batch split"),
        ({"env_class": _NoInstanceEnv}, "check_env_specs fails|hidden instance"),
        (
            {"subtasks": lambda cfg, env: _BadSubtasks(env.length, env.horizon)},
            r"Subtasks\.initiation must be",
        ),
        ({"tests": {}}, "tests must name at least one test distribution"),
        ({"instance_names": ("east",)}, "instance_names must include 'train'"),
        (
            {"tests": {"x": TestDistribution("a bad one", "nope")}},
            "test distribution 'x' does not build",
        ),
    ],
)
def test_check_family_names_what_is_missing_in_one_line(change, message):
    fam = dataclasses.replace(corridor.family(), name="hall4", **change)
    with pytest.raises(ValueError, match=message) as e:
        check_family(fam)
    assert "\n" not in str(e.value) and "family 'hall4'" in str(e.value)
    assert "hall4" not in FAMILIES


def test_shift_fields_take_their_types_and_unknown_fields_are_named(hall, tmp_path):
    cfg = load_config(_yaml(tmp_path, f"family: {NAME}\n"))
    points = shift_points(cfg, "train", [parse_shift("env.instances.slip_high=0.1,0.4")])
    assert [p.instances.slip_high for p in points] == [0.1, 0.4]
    with pytest.raises(ValueError, match=r"hall instance fields are \['east_share'"):
        shift_points(cfg, "train", [parse_shift("env.instances.p=0.5")])
    no_tests = dataclasses.replace(hall, tests={})
    register_family(no_tests, replace=True)
    with pytest.raises(ValueError, match="names no test distributions"):
        shift_points(cfg, None)


def test_a_broken_entry_point_is_reported_not_fatal(monkeypatch):
    import importlib.metadata as md

    import taskvar_torch.contract as fams

    broken = md.EntryPoint("broken_family", "no_such_module:family", fams.ENTRY_POINT_GROUP)
    monkeypatch.setattr(fams, "_entry_points", lambda: [broken])
    registry = fams._Registry()
    with pytest.warns(UserWarning, match="could not be loaded"):
        assert "broken_family" not in registry
    assert "no_such_module" in registry.broken["broken_family"]


def test_a_shared_hierarchy_component_is_refused_with_the_reason():
    with pytest.raises(ValueError, match="hierarchy must be a tree.*'navigate'.*its own copy"):
        Hierarchy("root", {"root": ("get", "put"), "get": ("navigate",), "put": ("navigate",)})


@pytest.mark.slow
def test_the_outside_family_installs_and_the_installed_command_runs_it(tmp_path):
    """Nothing under taskvar_torch/ names the corridor: pip installs the example package, and
    the installed ``taskvar`` finds it through its entry point (train, eval --method all, a shift
    curve, export)."""
    source = tmp_path / "corridor"  # a copy: the build writes its egg-info beside the sources
    shutil.copytree(EXAMPLE, source, ignore=shutil.ignore_patterns("build", "*.egg-info"))
    pip = [sys.executable, "-m", "pip"]
    install = [*pip, "install", "-q", "--no-deps", "--no-build-isolation", str(source)]
    done = subprocess.run(install, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    try:
        _run_the_installed_command(tmp_path)
    finally:  # leave the venv as it was: no stale copy of the example behind
        subprocess.run([*pip, "uninstall", "-q", "-y", "taskvar-corridor"], timeout=300)


def _run_the_installed_command(tmp_path: Path) -> None:
    taskvar = Path(sys.executable).with_name("taskvar")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}

    def run(*args: str) -> str:
        out = subprocess.run(
            [str(taskvar), *args], capture_output=True, text=True, timeout=600, env=env
        )
        assert out.returncode == 0, out.stderr[-3000:]
        return out.stdout

    out = tmp_path / "run"
    config = str(EXAMPLE / "configs" / "corridor.yaml")
    run("train", config, "--out", str(out), "--no-progress", "train.total_frames=4000")
    table = run(
        "eval", "--checkpoint", str(out / "final.pt"), "--method", "all", "--episodes", "200"
    )
    for method in ("averaging", "options", "interruption"):
        assert method in table
    curve = run(
        "eval", "--checkpoint", str(out / "final.pt"), "--method", "options", "--episodes", "100",
        "--shift", "env.instances.slip_high=0.0,0.4", "--out", str(tmp_path / "shift"),
    )  # fmt: skip
    assert "slip_high=0.4" in curve and (tmp_path / "shift" / "metrics.json").is_file()
    run("export", str(out / "final.pt"), "--out", str(tmp_path / "heads.pt"))
    assert (tmp_path / "heads.pt").is_file()
