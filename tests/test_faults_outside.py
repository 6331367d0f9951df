"""Faults from outside the package (issue 58): the default config, signals during start-up, a
broken installed plugin, a second writer, Gymnasium constructors and the one-line messages.

Commands run in this process through :func:`taskvar_torch.cli.main` unless the attack is a signal,
an installed plugin or a locale (then ``python -m taskvar_torch.cli``, ~5 s each).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from taskvar_torch import cli

torch.set_num_threads(1)
ROOT = Path(__file__).resolve().parents[1]
TINY = [  # a run of ~2 s
    "env.num_envs=4",
    "train.frames_per_batch=100",
    "train.total_frames=300",
    "train.log_every=300",
    "train.init_random_frames=100",
    "train.batch_size=16",
    "train.updates_per_batch=1",
    "train.buffer_size=1000",
]


def run(argv: list[str], capsys) -> tuple[int, str, list[str]]:
    """``taskvar ARGV`` in this process: ``(status, stdout, stderr lines)``."""
    try:
        status = cli.main(argv)
    except SystemExit as e:
        status = e.code
    out, err = capsys.readouterr()
    return status, out, [line for line in err.splitlines() if line.strip()]


def refused(outcome: tuple[int, str, list[str]], command: str, *needles: str) -> str:
    """One line ``taskvar COMMAND: error: ...`` with every needle, status 2."""
    status, _, lines = outcome
    assert status == 2, lines
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"taskvar {command}: error: "), lines[0]
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def command(*args: str, env: dict | None = None, timeout: int = 120) -> subprocess.CompletedProcess:
    """``python -m taskvar_torch.cli ARGS`` (the command, as its console script starts it)."""
    full = {**os.environ, "OMP_NUM_THREADS": "1", **(env or {})}
    cmd = [sys.executable, "-m", "taskvar_torch.cli", *args]
    return subprocess.run(cmd, env=full, capture_output=True, text=True, timeout=timeout, cwd=ROOT)


# --------------------------------------------------------------------------------------------
# the default config: env.windy.horizon null


@pytest.mark.slow
@pytest.mark.parametrize(
    "text, extra",
    [
        ("", []),
        ("null\n", []),
        ("family: windy\nenv:\n  windy:\n    horizon: 30\n", ["env.windy.horizon=null"]),
    ],
)
def test_an_empty_config_trains_summarises_and_exits_0(text, extra, tmp_path, capsys):
    """The schema defaults (windy, env.windy.horizon null) train, print the oracle summary with
    the layout's default horizon, and exit 0."""
    config = tmp_path / "empty.yaml"
    config.write_text(text)
    out = tmp_path / "run"
    argv = ["train", str(config), "--out", str(out), *TINY, *extra, "--no-progress"]
    status, stdout, lines = run(argv, capsys)
    assert status == 0, lines
    assert (out / "final.pt").is_file()
    assert "learnt heads vs exact oracle" in stdout
    assert "Traceback" not in "\n".join(lines)
    assert "in 100 steps" in stdout or "not learnt" not in stdout  # the 5x5 default horizon


# --------------------------------------------------------------------------------------------
# signals during Python's start-up imports


@pytest.mark.slow
@pytest.mark.parametrize("delay", [0.3, 1.5])
def test_sigterm_during_the_start_up_imports_prints_the_documented_line(delay):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "taskvar_torch.cli", "train", "--help"]
    p = subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    time.sleep(delay)  # within `import torch` (seconds)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 128 + signal.SIGTERM, err
    assert err.decode().strip() == "taskvar train: interrupted by SIGTERM"


@pytest.mark.slow  # a real process or several agents trained: make test only
def test_a_program_importing_the_package_keeps_its_signal_handlers():
    code = "import signal, taskvar_torch; print(signal.getsignal(signal.SIGTERM) is signal.SIG_DFL)"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert done.stdout.strip() == "True", done.stderr[-2000:]


# --------------------------------------------------------------------------------------------
# a broken installed plugin: imported only when its family is asked for by name

PLUGINS = {
    "hangs": "import time\nwhile True:\n    time.sleep(1)\n",
    "segfaults": "import ctypes\nctypes.string_at(0)\n",
    "exits": "import os\nos._exit(5)\n",
    "interrupts": "raise KeyboardInterrupt\n",
    "terminates": "import os, signal, time\nos.kill(os.getpid(), signal.SIGTERM)\ntime.sleep(30)\n",
}


def installed_plugin(root: Path, body: str, name: str = "bad_plugin") -> dict[str, str]:
    """A package installed the way pip leaves one (a ``*.dist-info`` with ``entry_points.txt``
    on the path), whose ``taskvar_torch.families`` entry point runs ``body`` on import; the
    environment of a process that has it installed."""
    site = root / "site"
    dist = site / f"{name}-1.0.dist-info"
    dist.mkdir(parents=True)
    (site / f"{name}.py").write_text(body)
    (dist / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text(f"[taskvar_torch.families]\n{name} = {name}:family\n")
    path = [str(ROOT), str(site), os.environ.get("PYTHONPATH", "")]
    return {"PYTHONPATH": os.pathsep.join(p for p in path if p)}


@pytest.mark.slow
@pytest.mark.parametrize("kind", sorted(PLUGINS))
def test_a_broken_plugin_cannot_take_down_a_command_that_does_not_use_it(kind, tmp_path):
    env = installed_plugin(tmp_path, PLUGINS[kind])
    listing = command("train", "--help", env=env, timeout=60)
    assert listing.returncode == 0, listing.stderr[-2000:]
    assert "bad_plugin: installed from 'bad_plugin:family'" in listing.stdout  # named, not run
    assert listing.stderr == ""
    taxi = str(ROOT / "configs" / "taxi.yaml")
    other = command("train", taxi, "--out", str(tmp_path / "o"), "seed=-1", env=env, timeout=60)
    assert other.returncode == 2, other.stderr[-2000:]
    lines = other.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("taskvar train: error: seed must be"), lines


@pytest.mark.slow
def test_a_plugin_raising_keyboardinterrupt_is_one_warning_when_asked_for(tmp_path):
    env = installed_plugin(tmp_path, PLUGINS["interrupts"])
    taxi = str(ROOT / "configs" / "taxi.yaml")
    done = command("train", taxi, "--out", str(tmp_path / "o"), "family=bad_plugin", env=env)
    assert done.returncode == 2, done.stderr[-2000:]
    assert "Traceback" not in done.stderr
    warning = [x for x in done.stderr.splitlines() if "Warning" in x]
    assert len(warning) == 1 and "family 'bad_plugin'" in warning[0], done.stderr
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith("taskvar train: error: family 'bad_plugin' is installed but could not")
    assert not (tmp_path / "o").exists()


# --------------------------------------------------------------------------------------------
# train-baselines: one writer per folder, of the bundle's family


@pytest.fixture
def bundle_dir(tmp_path) -> Path:
    """A folder holding a windy bundle's config (what train-baselines reads of it)."""
    from taskvar_torch.config import load_config, save_config_yaml

    out = tmp_path / "bundle"
    out.mkdir()
    save_config_yaml(
        load_config(str(ROOT / "configs" / "windy_corridor.yaml")), out / "config.yaml"
    )
    return out


def test_a_second_train_baselines_on_a_folder_in_use_is_refused(bundle_dir, capsys):
    from taskvar_torch.run_folder import LOCK_NAME, lock_folder, unlock_folder

    fd = lock_folder(bundle_dir)  # the first train-baselines, still running
    try:
        argv = ["train-baselines", "--out", str(bundle_dir), "--method", "recurrent", *TINY]
        refused(
            run(argv, capsys),
            "train-baselines",
            "in use by another taskvar run",
            f"pid {os.getpid()}",
        )
        assert sorted(p.name for p in bundle_dir.iterdir()) == sorted(["config.yaml", LOCK_NAME])
    finally:
        unlock_folder(bundle_dir, fd)


@pytest.mark.parametrize(
    "items, needle",
    [
        (["configs/taxi.yaml"], "family 'taxi' differs from the bundle's 'windy'"),
        (["configs/windy.yaml"], "env.windy.layout="),
        (["configs/windy_corridor.yaml", "env.windy.horizon=7"], "env.windy.horizon=7"),
        (["HEADS"], "heads.hidden=[32]"),
    ],
)
def test_train_baselines_refuses_a_config_of_another_task_than_the_bundle(
    items, needle, bundle_dir, capsys
):
    if items == ["HEADS"]:  # the bundle's config with other heads, in a file of its own
        text = (ROOT / "configs" / "windy_corridor.yaml").read_text()
        assert "hidden: [64, 64]" in text
        (bundle_dir.parent / "other.yaml").write_text(
            text.replace("hidden: [64, 64]", "hidden: [32]")
        )
        items = [str(bundle_dir.parent / "other.yaml")]
    argv = ["train-baselines", *[str(ROOT / i) if i.startswith("configs/") else i for i in items]]
    outcome = run([*argv, "--out", str(bundle_dir), *TINY, "--no-progress"], capsys)
    refused(outcome, "train-baselines", needle, str(bundle_dir))
    assert sorted(p.name for p in bundle_dir.iterdir()) == ["config.yaml"]


@pytest.mark.slow
def test_train_baselines_with_the_bundle_config_and_a_heads_override_trains(bundle_dir, capsys):
    """The help's documented use: the heads' settings as overrides shape the baselines."""
    argv = ["train-baselines", str(ROOT / "configs" / "windy_corridor.yaml"), "--out"]
    argv += [str(bundle_dir), "--method", "recurrent", "heads.hidden=[16]", *TINY, "--no-progress"]
    status, stdout, lines = run(argv, capsys)
    assert status == 0, lines
    assert "trained recurrent" in stdout
    assert sorted(p.name for p in bundle_dir.iterdir()) == ["config.yaml", "recurrent.pt"]


# --------------------------------------------------------------------------------------------
# gym.make: the bounds and memory estimate of the CLI's config


@pytest.mark.parametrize(
    "env_id, kwargs, needle",
    [
        ("taskvar/WindyGrid-v0", {"horizon": 0}, "env.windy.horizon must be in [1, "),
        ("taskvar/WindyGrid-v0", {"horizon": -5}, "env.windy.horizon must be in [1, "),
        ("taskvar/WindyGrid-v0", {"horizon": 2.5}, "env.windy.horizon"),
        ("taskvar/WindyGrid-v0", {"patch_radius": 10**6}, "env.windy.patch_radius must be in"),
        ("taskvar/WindyGrid-v0", {"obs_encoding": "pixels"}, "env.windy.obs_encoding"),
        ("taskvar/WindyGrid-v0", {"layout": "BIG"}, "asks for too much memory"),
        ("taskvar/WindyGrid-v0", {"layout": "BIGMAP"}, "asks for too much memory"),
        ("taskvar/Taxi-v0", {"horizon": 0}, "env.taxi.horizon must be in [1, "),
        ("taskvar/Wargus-v0", {"size": 10**6}, "env.wargus.size must be"),
        ("taskvar/Wargus-v0", {"hit_prob": float("nan")}, "env.wargus.hit_prob"),
    ],
)
def test_gym_make_refuses_what_the_config_refuses(env_id, kwargs, needle):
    import gymnasium as gym

    from taskvar_torch.families.windy import dynamics as windy

    if kwargs.get("layout") == "BIG":  # 3000 x 3000 cells, one-hot: 324 TB of observations
        kwargs = {"layout": windy.make_layout(3000, 3000)}
    elif kwargs.get("layout") == "BIGMAP":  # the same as a map string
        kwargs = {"layout": "\n".join(windy.make_layout(3000, 3000).rows)}
    start = time.perf_counter()
    with pytest.raises(ValueError) as caught:
        gym.make(env_id, **kwargs)
    message = str(caught.value)
    assert needle in message and "\n" not in message, message
    assert "checked as config keys" in message
    assert time.perf_counter() - start < 30  # the exits of a big map are found in a second


@pytest.mark.parametrize(
    "kwargs", [{}, {"horizon": None}, {"horizon": 7}, {"obs_encoding": "coords_patch"}]
)
def test_gym_make_accepts_what_the_config_accepts(kwargs):
    import gymnasium as gym

    env = gym.make("taskvar/WindyGrid-v0", **kwargs)
    env.reset(seed=0)
    assert env.unwrapped.horizon == (kwargs.get("horizon") or 100)


# --------------------------------------------------------------------------------------------
# one-liners that say what to change: the locale, a full disk, a dangling link

EVAL = ["--episodes", "8", "--batch-size", "8", "--no-progress"]


@pytest.fixture(scope="module")
def bundle(tmp_path_factory) -> Path:
    """A tiny trained windy bundle (``final.pt``)."""
    out = tmp_path_factory.mktemp("outside") / "run"
    config = str(ROOT / "configs" / "windy_corridor.yaml")
    assert cli.main(["train", config, "--out", str(out), *TINY, "--no-progress"]) == 0
    return out / "final.pt"


@pytest.mark.slow
@pytest.mark.parametrize("utf8_mode", ["1", "0"])
def test_a_non_ascii_out_under_an_ascii_locale_exits_0(utf8_mode, bundle, tmp_path):
    """All results written, then the last line "wrote ..." failed to print: exit 2."""
    out = tmp_path / "résultats"
    env = {"LC_ALL": "C", "LANG": "C", "PYTHONIOENCODING": "ascii", "PYTHONUTF8": utf8_mode}
    done = command("eval", "--checkpoint", str(bundle), *EVAL, "--out", str(out), env=env)
    assert done.returncode == 0, done.stderr[-2000:]
    assert (out / "metrics.json").is_file()
    assert "wrote " in done.stdout and "metrics.json" in done.stdout
    assert "Traceback" not in done.stderr


def test_a_full_disk_names_the_file_it_could_not_write(bundle, tmp_path, capsys, monkeypatch):
    import errno

    out = tmp_path / "E"

    def full(fd):  # every write reaches the disk at fsync: the disk is full
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full)
    argv = ["eval", "--checkpoint", str(bundle), *EVAL, "--out", str(out)]
    line = refused(run(argv, capsys), "eval", "No space left on device")
    assert f"'{out}{os.sep}" in line, line  # the file, in --out (not the staging folder)
    assert not out.exists()


def test_atomic_write_and_save_figure_name_the_file_a_full_disk_refused(tmp_path, monkeypatch):
    import errno

    from taskvar_torch.experiments.plots import pyplot, save_figure
    from taskvar_torch.io import atomic_write

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    with pytest.raises(OSError) as caught:
        atomic_write(tmp_path / "a.json", full)
    assert caught.value.filename == str(tmp_path / "a.json")
    fig = pyplot().figure()
    monkeypatch.setattr(fig, "savefig", full)
    with pytest.raises(OSError) as caught:
        save_figure(fig, tmp_path / "b.png")
    assert caught.value.filename == str(tmp_path / "b.png")
    assert sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.mark.parametrize("where", ["out", "parent"])
def test_a_dangling_symlink_out_says_so_and_where_it_points(where, bundle, tmp_path, capsys):
    link = tmp_path / "link"
    link.symlink_to(tmp_path / "nowhere" / "x")
    out = link if where == "out" else link / "E"
    argv = ["eval", "--checkpoint", str(bundle), *EVAL, "--out", str(out)]
    line = refused(run(argv, capsys), "eval", "dangling symbolic link", str(tmp_path / "nowhere"))
    assert "File exists" not in line
    assert link.is_symlink() and not (tmp_path / "nowhere").exists()
