"""Command-line paths no other test runs (issue 32): ``experiment windy-fig2 --checkpoint``,
``wargus-fig4 --workers 2``, ``--overwrite`` and the refusal without it for ``experiment`` and
``sweep``, the ``sweep`` Ray options, ``eval --batch-size``, ``taskvar`` with no or an unknown
command, ``train`` with neither a config nor ``--resume``, the ``--overwrite``/``--resume`` guard,
and an ``--out`` that cannot be created, written or locked.

Every input error is one line ``taskvar[ COMMAND]: error: ...`` on stderr with exit status 2
(taskvar_torch/cli/). Everything runs in this process through :func:`taskvar_torch.cli.main`
(a fresh ``python -m taskvar_torch.cli`` costs ~10 s of imports on a shared CPU).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
import torch
from budgets import FIG4, TINY  # tests/budgets.py

from taskvar_torch import cli
from taskvar_torch.config import load_config
from taskvar_torch.run_folder import LOCK_NAME, ResultsFolder
from taskvar_torch.training import train

torch.set_num_threads(1)

ROOT = Path(__file__).resolve().parents[1]
WINDY = str(ROOT / "configs" / "windy.yaml")
EVAL_TINY = ["experiment.runs=1", "experiment.episodes_per_run=20", "eval.batch_size=10"]
WARGUS_TINY = [  # a small Figure 4 run: 2 repetitions of 2 trials
    "env.wargus.size=12",
    "env.wargus.horizon=60",
    "experiment.runs=2",
    "experiment.trials=2",
    *FIG4,
]


def run_cli(argv: list[str], capsys) -> tuple[int, str, str]:
    """``taskvar ARGV`` in this process: ``(status, stdout, stderr)``."""
    try:
        status = cli.main(argv)
    except SystemExit as e:  # argparse's errors and --help exit through SystemExit
        status = e.code
    out, err = capsys.readouterr()
    return status, out, err


def assert_one_line_error(status: int, err: str, command: str | None, needle: str) -> None:
    """Status 2 and exactly one stderr line ``taskvar COMMAND: error: ...`` containing ``needle``."""
    prefix = f"taskvar {command}: error: " if command else "taskvar: error: "
    assert status == 2, err
    assert err.count("\n") == 1 and err.endswith("\n"), err
    assert err.startswith(prefix), err
    assert needle in err, err
    assert "Traceback" not in err


@pytest.fixture(scope="module")
def bundle(tmp_path_factory) -> Path:
    """A tiny trained windy bundle (``final.pt``), ~2 s; 30-step episodes keep its evaluation
    short."""
    out = tmp_path_factory.mktemp("bundle")
    return train(load_config(WINDY, [*TINY, "env.windy.horizon=30"]), out, progress=False)["final"]


# --------------------------------------------------------------------------------------------
# taskvar with no command, an unknown command; train with neither a config nor --resume


def test_taskvar_with_no_command_is_a_one_line_error(capsys):
    """``taskvar`` alone names the missing COMMAND in one line, status 2."""
    status, _, err = run_cli([], capsys)
    assert_one_line_error(status, err, None, "COMMAND")


def test_taskvar_with_an_unknown_command_is_a_one_line_error_naming_the_commands(capsys):
    """``taskvar frobnicate``: one line naming the bad command and the valid ones, status 2."""
    status, _, err = run_cli(["frobnicate", "--out", "x"], capsys)
    assert_one_line_error(status, err, None, "invalid choice: 'frobnicate'")
    for name in cli.COMMANDS:
        assert repr(name) in err


def test_train_with_neither_config_nor_resume_is_a_one_line_error(tmp_path, capsys):
    """``taskvar train --out DIR`` asks for a CONFIG or ``--resume`` and writes nothing."""
    out = tmp_path / "run"
    status, _, err = run_cli(["train", "--out", str(out), "--no-progress"], capsys)
    assert_one_line_error(status, err, "train", "give a CONFIG file")
    assert not out.exists()


def test_overwrite_of_the_checkpoint_being_resumed_is_refused(bundle, capsys):
    """``--resume DIR/final.pt --out DIR --overwrite`` would delete what it resumes: refused,
    and the run folder is left as it was."""
    before = sorted(p.name for p in bundle.parent.iterdir())
    argv = ["train", "--resume", str(bundle), "--out", str(bundle.parent), "--overwrite"]
    status, _, err = run_cli([*argv, "--no-progress"], capsys)
    assert_one_line_error(status, err, "train", "--overwrite would delete")
    assert sorted(p.name for p in bundle.parent.iterdir()) == before


# --------------------------------------------------------------------------------------------
# an --out that cannot be created, written or locked


@pytest.mark.parametrize(
    "command",
    [
        ["train", WINDY, *TINY],
        ["experiment", "windy-fig2", *TINY],
        ["sweep", WINDY, "--backend", "local", "seed=0,1"],
        ["eval", "--checkpoint", "BUNDLE", "--episodes", "4"],
    ],
    ids=["train", "experiment", "sweep", "eval"],
)
def test_out_under_a_regular_file_is_a_one_line_error(command, bundle, tmp_path, capsys):
    """``--out FILE/sub``: one line saying it cannot be created (each command that writes)."""
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder\n")
    argv = [str(bundle) if a == "BUNDLE" else a for a in command]
    status, _, err = run_cli([*argv, "--out", str(blocker / "sub"), "--no-progress"], capsys)
    assert_one_line_error(status, err, command[0], "cannot be created")
    assert blocker.read_text() == "not a folder\n"


def test_train_out_in_a_read_only_folder_is_a_one_line_error(tmp_path, capsys):
    """``--out`` inside a folder without write permission (chmod 0o500): refused in one line.

    Root ignores permission bits, so as root this is skipped (see the next test for a folder
    root cannot write either)."""
    if os.geteuid() == 0:
        pytest.skip("running as root: chmod 0o500 does not stop root's writes")
    parent = tmp_path / "read_only"
    parent.mkdir()
    parent.chmod(0o500)
    try:
        argv = ["train", WINDY, *TINY, "--out", str(parent / "run"), "--no-progress"]
        status, _, err = run_cli(argv, capsys)
    finally:
        parent.chmod(0o700)
    assert_one_line_error(status, err, "train", "is not writable")
    assert not (parent / "run").exists()


def test_train_out_where_even_root_cannot_write_is_a_one_line_error(tmp_path, capsys):
    """``--out`` in sysfs, where creating a folder fails even for root: refused in one line."""
    target = Path("/sys/taskvar_cli_test")
    try:
        target.mkdir()
    except OSError:
        pass
    else:  # pragma: no cover - a writable /sys: nothing here to test with
        target.rmdir()
        pytest.skip("/sys is writable on this machine")
    argv = ["train", WINDY, *TINY, "--out", str(target), "--no-progress"]
    status, _, err = run_cli(argv, capsys)
    assert_one_line_error(status, err, "train", str(target))
    assert "choose another --out" in err


@pytest.mark.slow
def test_train_out_locked_by_another_run_is_a_one_line_error(tmp_path, capsys):
    """A folder held by another run (its ``.taskvar.lock`` flock-ed) is refused in one line
    naming the holder's pid; once released, the same folder trains."""
    out = tmp_path / "run"
    holder = ResultsFolder(out, staged=False)
    holder.acquire()
    try:
        argv = ["train", WINDY, *TINY, "--out", str(out), "--no-progress"]
        status, _, err = run_cli(argv, capsys)
        assert_one_line_error(status, err, "train", "is in use by another taskvar run")
        assert f"pid {os.getpid()}" in err
        assert (out / LOCK_NAME).exists()  # the holder's lock is untouched
        assert not (out / "config.yaml").exists()
    finally:
        holder.commit()
    status, _, err = run_cli(argv, capsys)
    assert status == 0, err
    assert (out / "final.pt").is_file() and not (out / LOCK_NAME).exists()


# --------------------------------------------------------------------------------------------
# taskvar experiment windy-fig2 --checkpoint, --overwrite and its refusal


@pytest.mark.slow
def test_windy_fig2_evaluates_a_checkpoint_then_refuses_then_overwrites(bundle, tmp_path, capsys):
    """``experiment windy-fig2 --checkpoint B``: evaluates B (no training, no ``train/``),
    writes metrics naming B; a second run into the same ``--out`` is refused in one line and
    leaves the results; with ``--overwrite`` it replaces them."""
    out = tmp_path / "fig2"
    argv = ["experiment", "windy-fig2", "--checkpoint", str(bundle), "--out", str(out)]
    argv += [*EVAL_TINY, "--no-progress", "--no-plots"]
    status, stdout, err = run_cli(argv, capsys)
    assert status == 0, err
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["checkpoint"] == str(bundle) and metrics["train_seconds"] == 0.0
    assert 0.0 <= metrics["fraction_no_worse"] <= 1.0
    assert not (out / "train").exists() and (out / "episodes.csv").is_file()
    assert "Windy Figure 2" in stdout

    (out / "metrics.json").write_text('{"marker": 1}')
    status, _, err = run_cli(argv, capsys)
    assert_one_line_error(status, err, "experiment", "already holds results")
    assert "--overwrite" in err
    assert json.loads((out / "metrics.json").read_text()) == {"marker": 1}

    status, _, err = run_cli([*argv, "--overwrite"], capsys)
    assert status == 0, err
    assert json.loads((out / "metrics.json").read_text())["checkpoint"] == str(bundle)


def test_windy_fig2_with_checkpoint_refuses_a_config_file_and_env_overrides(
    bundle, tmp_path, capsys
):
    """With ``--checkpoint`` the bundle's config is used: a CONFIG file or an ``env.*`` override
    would be ignored, so each is a one-line error."""
    base = ["experiment", "windy-fig2", "--checkpoint", str(bundle), "--out", str(tmp_path / "o")]
    status, _, err = run_cli([*base, WINDY, "--no-progress"], capsys)
    assert_one_line_error(status, err, "experiment", "cannot apply with --checkpoint")
    status, _, err = run_cli([*base, "env.windy.horizon=10", "--no-progress"], capsys)
    assert_one_line_error(status, err, "experiment", "env.windy.horizon=10")
    assert not (tmp_path / "o").exists()


# --------------------------------------------------------------------------------------------
# taskvar experiment wargus-fig4 --workers 2


@pytest.mark.slow
def test_wargus_fig4_with_two_workers_writes_both_repetitions(tmp_path, capsys):
    """``wargus-fig4 --workers 2``: the two repetitions run in two spawned processes and the
    folder holds both, with the protocol recording the workers; rerun without ``--overwrite``
    is refused in one line."""
    out = tmp_path / "fig4"
    argv = ["experiment", "wargus-fig4", "--workers", "2", "--out", str(out), *WARGUS_TINY]
    status, _, err = run_cli([*argv, "--no-progress", "--no-plots"], capsys)
    assert status == 0, err
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["protocol"]["workers"] == 2 and metrics["protocol"]["repetitions"] == 2
    assert metrics["protocol"]["seeds"] == [0, 1]
    for rep in (0, 1):
        assert (out / f"rep{rep}" / "final.pt").is_file()
    for m in metrics["methods"].values():
        assert len(m["curve_per_rep"]) == 2

    status, _, err = run_cli([*argv, "--no-progress", "--no-plots"], capsys)
    assert_one_line_error(status, err, "experiment", "already holds results")


def test_wargus_fig4_workers_below_one_is_a_one_line_error(tmp_path, capsys):
    """``--workers 0`` is refused before any work."""
    argv = ["experiment", "wargus-fig4", "--workers", "0", "--out", str(tmp_path / "o")]
    status, _, err = run_cli([*argv, *WARGUS_TINY, "--no-progress"], capsys)
    assert_one_line_error(status, err, "experiment", "workers must be >= 1")
    assert not (tmp_path / "o").exists()


# --------------------------------------------------------------------------------------------
# taskvar sweep: --overwrite and its refusal; the Ray options


SWEEP_TINY = [*TINY, "env.windy.horizon=30", *EVAL_TINY]


@pytest.mark.slow
def test_sweep_refuses_an_existing_sweep_then_overwrites_it(tmp_path, capsys):
    """A finished sweep's folder is refused without ``--overwrite`` (one line, summary kept);
    with ``--overwrite`` the sweep runs again and rewrites its summary."""
    out = tmp_path / "sweep"
    argv = ["sweep", WINDY, "--backend", "local", "--out", str(out), *SWEEP_TINY, "seed=3"]
    argv += ["--no-progress", "--no-plots"]
    status, _, err = run_cli(argv, capsys)
    assert status == 0, err
    summary = json.loads((out / "summary.json").read_text())
    assert [p["name"] for p in summary["points"]] == ["run"]
    assert (out / "run" / "metrics.json").is_file()

    (out / "summary.json").write_text('{"marker": 1}')
    status, _, err = run_cli(argv, capsys)
    assert_one_line_error(status, err, "sweep", "already holds results")
    assert json.loads((out / "summary.json").read_text()) == {"marker": 1}

    status, _, err = run_cli([*argv, "--overwrite"], capsys)
    assert status == 0, err
    assert json.loads((out / "summary.json").read_text())["points"][0]["name"] == "run"


@pytest.mark.parametrize(
    "options, needle",
    [
        (["--backend", "ray", "--address", "auto", "--workers", "2"], "with --address the cluster"),
        (["--backend", "local", "--address", "auto"], "--address and --workers are for"),
        (["--backend", "local", "--workers", "2"], "--address and --workers are for"),
        (["--backend", "ray", "--workers", "0"], "--workers must be >= 1, got 0"),
        (["--backend", "ray", "--workers", "-3"], "--workers must be >= 1, got -3"),
        (["--backend", "ray", "--workers", "two"], "invalid int value: 'two'"),
    ],
)
def test_sweep_ray_options_that_do_not_fit_are_one_line_errors(options, needle, tmp_path, capsys):
    """``--address`` / ``--workers`` with the wrong backend, together, or out of range: one line,
    before anything runs or is written."""
    out = tmp_path / "sweep"
    argv = ["sweep", WINDY, *options, "--out", str(out), "seed=0,1", "--no-progress"]
    status, _, err = run_cli(argv, capsys)
    assert_one_line_error(status, err, "sweep", needle)
    assert not out.exists()


# --------------------------------------------------------------------------------------------
# taskvar eval --batch-size


@pytest.mark.slow  # ~2-3.5 s on a 2-core CPU: make test only
def test_eval_batch_size_does_not_change_the_paired_episodes(bundle, tmp_path, capsys):
    """``eval --batch-size N`` plays the same paired episodes in batches of N: the metrics and
    every episode's row equal those of one batch."""
    base = ["eval", "--checkpoint", str(bundle), "--method", "averaging,interruption"]
    base += ["--episodes", "12", "--seed", "5", "--no-progress"]
    for n in (12, 5):
        status, _, err = run_cli(
            [*base, "--batch-size", str(n), "--out", str(tmp_path / f"b{n}")], capsys
        )
        assert status == 0, err
    one, five = tmp_path / "b12", tmp_path / "b5"
    assert json.loads((one / "metrics.json").read_text()) == json.loads(
        (five / "metrics.json").read_text()
    )
    assert (one / "episodes.csv").read_text() == (five / "episodes.csv").read_text()


@pytest.mark.parametrize("size", ["0", "-4"])
def test_eval_batch_size_below_one_is_a_one_line_error(size, bundle, tmp_path, capsys):
    """``--batch-size 0`` (which used to fall back to the config's silently) or a negative one:
    refused in one line before anything is played or written."""
    out = tmp_path / "o"
    argv = ["eval", "--checkpoint", str(bundle), "--batch-size", size, "--out", str(out)]
    status, _, err = run_cli([*argv, "--no-progress"], capsys)
    assert_one_line_error(status, err, "eval", f"--batch-size must be >= 1, got {size}")
    assert not out.exists()


def test_eval_help_names_each_registered_familys_tests():
    """``taskvar eval --help`` lists every registered family's ``--test`` names, computed only
    when the help is printed (a command that runs does not load the family registry for it)."""
    from taskvar_torch.cli import build_parser
    from taskvar_torch.families import FAMILIES

    _, parsers = build_parser()
    assert parsers["eval"].epilog is None  # not built yet
    text = parsers["eval"].format_help()
    for name, fam in FAMILIES.items():
        assert f"  {name}: {', '.join(fam.tests)}" in text


def test_an_interrupt_inside_a_torchrl_loss_is_the_interrupt_not_a_bug(capsys):
    """SIGTERM inside TorchRL's DQN loss: tensordict's ``to_module`` exit fails on the way out
    (a TensorDict's truth value raises); the command still ends with the interrupt's one line and
    status 143, not an internal error (found stopping ``train-baselines --method recurrent``)."""
    import argparse

    from tensordict import TensorDict

    from taskvar_torch.cli.failures import _Terminated, run_command

    module = torch.nn.Linear(2, 2)
    params = TensorDict.from_module(module).clone()

    def run(args):
        with params.to_module(module):
            raise _Terminated

    code = run_command("train-baselines", run, argparse.Namespace())
    err = capsys.readouterr().err.strip()
    assert code == 143, err
    assert err == "taskvar train-baselines: interrupted by SIGTERM"

    def bug(args):
        with params.to_module(module):
            raise ZeroDivisionError("a bug")

    assert run_command("eval", bug, argparse.Namespace()) == 1  # a bug stays a bug
    assert "internal error (ZeroDivisionError)" in capsys.readouterr().err
