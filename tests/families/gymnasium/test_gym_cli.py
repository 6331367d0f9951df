"""Gymnasium families through the ``taskvar`` command (docs/gymnasium.md): train, ``eval --method
all``, a ``--shift`` curve and a refused ``--resume``, on FrozenLake (Gymnasium's own) and DoorKey
(MiniGrid's): in this process (fast), and, marked slow, the example packages installed with pip
and run by the installed ``taskvar`` command, as a user would."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from taskvar_torch import cli
from taskvar_torch.families import FAMILIES, register_family

torch.set_num_threads(1)
ROOT = Path(__file__).resolve().parents[3]
EXAMPLES = {  # family -> (example folder, config, a shift)
    "frozenlake": ("gym_frozenlake", "frozenlake.yaml", "env.instances.low=0.3,0.9"),
    "doorkey": ("minigrid_doorkey", "doorkey.yaml", "env.instances.high=5,6"),
}
TINY = ["train.total_frames=1024", "train.frames_per_batch=256", "train.init_random_frames=256"]


def _commands(name: str, out: Path) -> list[tuple[list[str], str]]:
    """The command lines of one family, each with a phrase its output must hold."""
    folder, config, shift = EXAMPLES[name]
    final = str(out / "run" / "final.pt")
    cfg = str(ROOT / "examples" / folder / "configs" / config)
    return [
        (["train", cfg, "--out", str(out / "run"), "--no-progress", *TINY], "final bundle"),
        (["eval", "--checkpoint", final, "--method", "all", "--episodes", "16"], "interruption"),
        (
            ["eval", "--checkpoint", final, "--method", "options", "--episodes", "8",
             "--shift", shift, "--out", str(out / "shift")],
            shift.split(",")[-1].split("=")[0],
        ),
    ]  # fmt: skip


def test_the_walk_through_shows_the_example_as_it_is_in_under_100_lines():
    """docs/gymnasium.md's code is examples/minigrid_doorkey's module, which the tests here run."""
    code = (ROOT / "examples" / "minigrid_doorkey" / "taskvar_doorkey" / "__init__.py").read_text()
    doc = (ROOT / "docs" / "gymnasium.md").read_text()
    assert f"```python\n{code}```" in doc
    lines = len(code.splitlines())
    assert lines < 100 and f"DoorKey in {lines} lines" in doc


@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.slow) if n == "doorkey" else n for n in EXAMPLES]
)  # doorkey ~5 s: make test only
def test_train_eval_shift_and_a_refused_resume_in_process(name, tmp_path, capsys):
    sys.path.insert(0, str(ROOT / "examples" / EXAMPLES[name][0]))
    module = __import__("taskvar_frozenlake" if name == "frozenlake" else "taskvar_doorkey")
    register_family(module.family(), replace=True)
    try:
        for argv, phrase in _commands(name, tmp_path):
            assert cli.main(argv) == 0
            assert phrase in capsys.readouterr().out
        resume = [
            "train",
            "--resume",
            str(tmp_path / "run" / "final.pt"),
            "--out",
            str(tmp_path / "run"),
        ]
        assert cli.main(resume) != 0
        err = capsys.readouterr().err.strip()
        assert err.endswith("start a new run, or evaluate this checkpoint") and "\n" not in err
        assert f"family {name!r} is not resumable" in err
    finally:
        FAMILIES._families.pop(name, None)
        sys.path.remove(str(ROOT / "examples" / EXAMPLES[name][0]))


@pytest.mark.slow
def test_the_installed_command_runs_the_installed_examples(tmp_path):
    """``pip install`` (into a folder of its own: the shared environment is left as it is) puts
    each example's ``taskvar_torch.families`` entry point where the installed ``taskvar`` finds it."""
    site = tmp_path / "site"
    for folder, _, _ in EXAMPLES.values():
        source = (
            tmp_path / "src" / folder
        )  # a copy: the build writes its egg-info beside the sources
        shutil.copytree(
            ROOT / "examples" / folder, source, ignore=shutil.ignore_patterns("build", "*.egg-info")
        )
        install = [sys.executable, "-m", "pip", "install", "-q", "--no-deps",
                   "--no-build-isolation", "--target", str(site), str(source)]  # fmt: skip
        done = subprocess.run(install, capture_output=True, text=True, timeout=300, cwd=tmp_path)
        assert done.returncode == 0, done.stderr[-2000:]
    path = os.pathsep.join(p for p in (str(site), os.environ.get("PYTHONPATH", "")) if p)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": path}
    taskvar = str(Path(sys.executable).with_name("taskvar"))
    for name in EXAMPLES:
        out = tmp_path / name
        for argv, phrase in _commands(name, out):
            done = subprocess.run(
                [taskvar, *argv], capture_output=True, text=True, timeout=600, env=env
            )
            assert done.returncode == 0, done.stderr[-3000:]
            assert phrase in done.stdout
        resume = [
            taskvar,
            "train",
            "--resume",
            str(out / "run" / "final.pt"),
            "--out",
            str(out / "run"),
        ]
        done = subprocess.run(resume, capture_output=True, text=True, timeout=600, env=env)
        assert done.returncode != 0 and f"family {name!r} is not resumable" in done.stderr
        assert len(done.stderr.strip().splitlines()) == 1
