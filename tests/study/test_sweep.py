"""``taskvar sweep`` (docs/sweeps.md): point expansion, one-line errors, and local vs Ray backends.

A 2-repetition sweep (``seed=0,1``) of a tiny windy Figure 2 config runs once on the local backend
and once on a local Ray with 2 CPUs; every point's metrics must be equal (same seeds, same numbers).
"""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import pytest
import torch
from budgets import SWEEP_POINT  # tests/budgets.py

from taskvar_torch import cli
from taskvar_torch.factory import load_heads
from taskvar_torch.study.sweep import sweep
from taskvar_torch.study.sweep_grid import (
    expand_points,
    load_point_configs,
    point_name,
    split_values,
)

torch.set_num_threads(1)

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "windy.yaml"
TIMING = ("train_seconds", "eval_seconds", "wall_seconds", "checkpoint")


def _run_cli(argv: list[str], capsys) -> tuple[int, str, str]:
    try:
        status = cli.main(argv)
    except SystemExit as e:  # argparse errors
        status = e.code
    out, err = capsys.readouterr()
    return status, out, err


# --------------------------------------------------------------------------------------------
# point expansion


def test_two_swept_keys_give_their_cartesian_product_after_the_fixed_overrides():
    points = expand_points(["train.lr=0.001,0.002", "eval.episodes=7", "seed=0,1"])
    assert [p.values for p in points] == [
        {"train.lr": "0.001", "seed": "0"},
        {"train.lr": "0.001", "seed": "1"},
        {"train.lr": "0.002", "seed": "0"},
        {"train.lr": "0.002", "seed": "1"},
    ]
    assert points[2].overrides == ("eval.episodes=7", "train.lr=0.002", "seed=0")
    assert points[2].name == "train.lr=0.002,seed=0"
    assert len({p.name for p in points}) == 4


def test_fixed_overrides_only_give_one_point():
    (p,) = expand_points(["seed=3"])
    assert p.values == {} and p.overrides == ("seed=3",) and p.name == "run"


def test_commas_inside_brackets_do_not_split_and_names_are_filesystem_safe():
    assert split_values("[32],[64,64]") == ["[32]", "[64,64]"]
    points = expand_points(["heads.hidden=[32],[64,64]"])
    cfgs = load_point_configs(CONFIG, points)
    assert [c.heads.hidden for c in cfgs] == [(32,), (64, 64)]
    assert [p.name for p in points] == ["heads.hidden=_32_", "heads.hidden=_64,64_"]
    assert point_name({"env.windy.layout": "a/b c"}) == "env.windy.layout=a_b_c"
    # two values differing only in unsafe characters still get their own folders
    assert len({p.name for p in expand_points(["env.windy.layout=a/b,a_b"])}) == 2


def test_each_point_config_holds_its_swept_values():
    points = expand_points(["seed=0,1", "train.lr=0.004"])
    cfgs = load_point_configs(CONFIG, points, quick=True)
    assert [c.seed for c in cfgs] == [0, 1]
    assert all(c.train.lr == 0.004 and c.experiment.runs == 2 for c in cfgs)  # quick applied


# --------------------------------------------------------------------------------------------
# one-line errors


@pytest.mark.parametrize(
    "items, message",
    [
        (["sed=0,1"], "unknown config key 'sed'"),
        (["seed=0,"], "sweep key 'seed' has an empty value"),
        (["seed="], "sweep key 'seed' has an empty value"),
        (["seed=0,1", "seed=2"], "sweep key 'seed' is given twice"),
        (["train.lr=0.1,-1"], "train.lr must be a finite number in (0"),
    ],
)
def test_bad_sweeps_are_one_line_errors_before_any_run(items, message, capsys, tmp_path):
    status, out, err = _run_cli(
        ["sweep", str(CONFIG), "--backend", "local", "--out", str(tmp_path), *items], capsys
    )
    assert status == 2 and message in err
    assert err.startswith("taskvar sweep: error:") and err.count("\n") == 1
    assert not any(tmp_path.iterdir())  # nothing ran


def test_unknown_backend_is_a_one_line_error(capsys, tmp_path):
    status, _, err = _run_cli(["sweep", str(CONFIG), "--backend", "spark", "seed=0,1"], capsys)
    assert status == 2 and "invalid choice: 'spark'" in err and err.count("\n") == 1
    with pytest.raises(ValueError, match=r"--backend must be one of \['local', 'ray'\]"):
        sweep(CONFIG, ["seed=0,1"], tmp_path, backend="spark")


def test_workers_without_ray_backend_is_an_error(tmp_path):
    with pytest.raises(ValueError, match="--address and --workers are for --backend ray"):
        sweep(CONFIG, ["seed=0,1"], tmp_path, backend="local", workers=2)


def test_missing_ray_says_how_to_install_it(monkeypatch, capsys, tmp_path):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    status, _, err = _run_cli(
        ["sweep", str(CONFIG), "--backend", "ray", "--out", str(tmp_path), "seed=0,1"], capsys
    )
    assert status == 2 and err.count("\n") == 1
    assert 'pip install "taskvar-torch[distributed]"' in err


# --------------------------------------------------------------------------------------------
# local and Ray backends give the same numbers


def _point_metrics(folder: Path) -> dict:
    m = json.loads((folder / "metrics.json").read_text())
    return {k: v for k, v in m.items() if k not in TIMING}


@pytest.fixture(scope="module")
def ray_session():
    """A local Ray with 2 CPUs for the module, or None without Ray (sweep reuses a running Ray).

    Started before the local sweep, with one task per CPU importing torch and TorchRL, so the
    workers' start-up overlaps the local run instead of adding to it.
    """
    try:
        import ray
    except ImportError:
        yield None
        return
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    # a lambda travels by value (this test module is not importable in the workers)
    warm = ray.remote(num_cpus=1)(lambda: __import__("taskvar_torch.families.windy.fig2") and None)
    refs = [warm.remote() for _ in range(2)]
    yield ray
    ray.get(refs)
    ray.shutdown()


@pytest.fixture(scope="module")
def local_sweep(ray_session, tmp_path_factory):
    out = tmp_path_factory.mktemp("local")
    status = cli.main(
        [
            "sweep",
            str(CONFIG),
            "--backend",
            "local",
            "--quick",
            "--out",
            str(out),
            "--no-progress",
            "seed=0,1",
            *SWEEP_POINT,
        ]
    )
    assert status == 0
    return out


@pytest.mark.slow
def test_local_sweep_writes_each_point_folder_and_the_summary(local_sweep):
    out = local_sweep
    for name in ("seed=0", "seed=1"):
        assert (out / name / "metrics.json").is_file() and (out / name / "output.txt").is_file()
        assert "Windy Figure 2" in (out / name / "output.txt").read_text()
    with open(out / "summary.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["seed"] for r in rows] == ["0", "1"]
    for r in rows:
        m = json.loads((out / r["point"] / "metrics.json").read_text())
        assert float(r["fraction_no_worse"]) == pytest.approx(m["fraction_no_worse"])
        assert float(r["south_only.mean_difference"]) == pytest.approx(
            m["south_only"]["mean_difference"]
        )
    summary = json.loads((out / "summary.json").read_text())
    assert summary["backend"] == "local" and summary["experiment"] == ["windy-fig2"]
    assert [p["overrides"][-1] for p in summary["points"]] == ["seed=0", "seed=1"]
    assert summary["rows"][0]["mean_difference"] == float(rows[0]["mean_difference"])
    # the two repetitions are different runs
    assert _point_metrics(out / "seed=0") != _point_metrics(out / "seed=1")


@pytest.mark.slow
def test_ray_sweep_gives_the_local_sweeps_numbers(local_sweep, ray_session, tmp_path, capsys):
    pytest.importorskip("ray")
    rows = sweep(
        CONFIG,
        ["seed=0,1", *SWEEP_POINT],
        tmp_path,
        backend="ray",
        quick=True,
        progress=False,
        plots=False,
    )  # plots change no number: the local sweep drew them
    assert "2 points" in capsys.readouterr().out
    assert (tmp_path / "summary.csv").is_file() and (tmp_path / "summary.json").is_file()
    for name in ("seed=0", "seed=1"):
        ray_heads, _ = load_heads(tmp_path / name / "train" / "final.pt")
        local_heads, _ = load_heads(local_sweep / name / "train" / "final.pt")
        for (k, a), b in zip(ray_heads.state_dict().items(), local_heads.state_dict().values()):
            assert torch.equal(a, b), k
        assert _point_metrics(tmp_path / name) == _point_metrics(local_sweep / name)
        assert (tmp_path / name / "episodes.csv").read_bytes() == (
            local_sweep / name / "episodes.csv"
        ).read_bytes()
    # without plots the points hold no PNG; taskvar plot draws the local point's set from the folder
    local_pngs = sorted(p.name for p in (local_sweep / "seed=0").glob("*.png"))
    assert local_pngs and not list((tmp_path / "seed=0").glob("*.png"))
    assert json.loads((tmp_path / "summary.json").read_text())["plots"] is False
    assert cli.main(["plot", str(tmp_path / "seed=0")]) == 0
    assert sorted(p.name for p in (tmp_path / "seed=0").glob("*.png")) == local_pngs
    local_rows = json.loads((local_sweep / "summary.json").read_text())["rows"]
    drop = ("seconds",)
    assert [{k: v for k, v in r.items() if k not in drop} for r in rows] == [
        {k: v for k, v in r.items() if k not in drop} for r in local_rows
    ]


@pytest.mark.slow
def test_a_wargus_config_sweeps_the_wargus_figure_4_experiment(tmp_path):
    tiny = [
        "experiment.runs=1",
        "experiment.trials=2",
        "experiment.learning_episodes_per_trial=2",
        "experiment.test_episodes_per_trial=1",
        "env.wargus.size=8",
        "env.wargus.sight=4",
        "env.wargus.shoot_range=2",
        "env.wargus.horizon=20",
        "train.init_random_frames=64",
        "train.frames_per_batch=32",
        "train.batch_size=32",
    ]
    config = CONFIG.parent / "wargus.yaml"
    rows = sweep(config, ["seed=0,1", *tiny], tmp_path, quick=True, progress=False, plots=False)
    assert not list(tmp_path.glob("*/fig4.png"))
    assert cli.main(["plot", str(tmp_path / "seed=0")]) == 0
    assert (tmp_path / "seed=0" / "fig4.png").is_file()
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["experiment"] == ["wargus-fig4"] and [r["seed"] for r in rows] == ["0", "1"]
    for r in rows:
        m = json.loads((tmp_path / r["point"] / "metrics.json").read_text())
        assert m["protocol"]["seeds"] == [int(r["seed"])]
        for method, v in m["methods"].items():
            assert r[f"final_score.{method}"] == v["final_score"]
