"""``taskvar sweep`` seed batches (docs/sweeps.md#seed-batches): points that differ only in
consecutive seeds train as one ``train.seeds=k`` run, each point evaluates its seed's bundle and
reads as an unbatched point; other points (a non-consecutive seed, a Wargus sweep, the opt-out)
train alone."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
import torch
from budgets import SWEEP_POINT  # tests/budgets.py

from taskvar_torch.factory import load_heads
from taskvar_torch.families.windy import fig2 as windy_fig2
from taskvar_torch.study import sweep_jobs
from taskvar_torch.study.sweep import sweep
from taskvar_torch.study.sweep_grid import expand_points, load_point_configs
from taskvar_torch.study.sweep_jobs import plan_jobs

torch.set_num_threads(1)

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
TIMING = ("train_seconds", "eval_seconds", "wall_seconds", "checkpoint", "train_batch")


def _plan(config, items, batch_seeds=True):
    points = expand_points(items)
    cfgs = load_point_configs(CONFIGS / config, points)
    jobs, notes = plan_jobs(points, cfgs, range(len(points)), Path("/o"), batch_seeds)
    return [(j.points, j.batch) for j in jobs], notes


def test_only_consecutive_seeds_of_one_config_are_batched():
    jobs, notes = _plan("windy.yaml", ["train.lr=0.001,0.002", "seed=0,1,2,5"])
    assert jobs == [
        ((0, 1, 2), "/o/batches/train.lr=0.001,seed=0-2"),
        ((3,), None),
        ((4, 5, 6), "/o/batches/train.lr=0.002,seed=0-2"),
        ((7,), None),
    ]
    assert len(notes) == 2 and all("are not consecutive" in n for n in notes)
    jobs, notes = _plan("windy.yaml", ["seed=1,0"])  # the batch runs in seed order
    assert jobs == [((1, 0), "/o/batches/seed=0-1")] and not notes
    assert _plan("windy.yaml", ["seed=0,1"], batch_seeds=False) == (
        [((0,), None), ((1,), None)],
        [],
    )
    jobs, (note,) = _plan("wargus.yaml", ["seed=0,1"])  # wargus-fig4: its own learning loop
    assert jobs == [((0,), None), ((1,), None)] and "trains in its own loop" in note
    jobs, (note,) = _plan("windy.yaml", ["seed=0,1", "collector.num_workers=2"])
    assert jobs == [((0,), None), ((1,), None)] and "collector.num_workers=1" in note


def _metrics(folder: Path) -> dict:
    m = json.loads((folder / "metrics.json").read_text())
    return {k: v for k, v in m.items() if k not in TIMING}


@pytest.mark.slow
def test_a_seed_sweep_trains_once_and_each_point_evaluates_its_seed(tmp_path, monkeypatch, capsys):
    calls = []

    def counted(train):
        def wrapper(cfg, out, **kwargs):
            calls.append(cfg.train.seeds)
            return train(cfg, out, **kwargs)

        return wrapper

    monkeypatch.setattr(sweep_jobs, "train", counted(sweep_jobs.train))
    monkeypatch.setattr(windy_fig2, "train", counted(windy_fig2.train))
    out = tmp_path / "sweep"
    items = ["seed=0,1", *SWEEP_POINT]
    rows = sweep(CONFIGS / "windy.yaml", items, out, progress=False, plots=False)
    assert calls == [2]  # one training run, of both seeds
    assert "seed batches: 1 training run(s) for 2 points" in capsys.readouterr().out
    batch = out / "batches" / "seed=0-1"
    for k, name in enumerate(("seed=0", "seed=1")):
        link = out / name / "train"
        assert link.is_symlink() and os.readlink(link) == os.path.join(
            "..", "batches", "seed=0-1", f"seed{k}"
        )
        heads, cfg = load_heads(link / "final.pt")
        assert cfg.seed == k and cfg.train.seeds == 1
        m = json.loads((out / name / "metrics.json").read_text())
        assert m["train_batch"] == {"folder": "../batches/seed=0-1", "seeds": 2, "seed_index": k}
        assert m["checkpoint"] == str(link / "final.pt") and m["train_seconds"] > 0
        assert rows[k]["fraction_no_worse"] == m["fraction_no_worse"]
    assert _metrics(out / "seed=0") != _metrics(out / "seed=1")
    # a point's results are its seed bundle evaluated directly
    cfg1 = load_point_configs(CONFIGS / "windy.yaml", expand_points(["seed=1", *SWEEP_POINT]))[0]
    windy_fig2.windy_fig2(
        cfg1, tmp_path / "direct", batch / "seed1" / "final.pt", progress=False, plots=False
    )
    assert _metrics(tmp_path / "direct") == _metrics(out / "seed=1")
    assert calls == [2]

    # --resume: the batched points' config.yaml is the sweep's, so nothing runs again
    sweep(CONFIGS / "windy.yaml", items, out, progress=False, plots=False, resume=True)
    assert "2 of 2 points complete, running 0" in capsys.readouterr().out and calls == [2]
    # a lost point runs alone on --resume: a real train/ folder, the batch left as it was
    (out / "seed=1" / "metrics.json").unlink()
    sweep(CONFIGS / "windy.yaml", items, out, progress=False, plots=False, resume=True)
    assert calls == [2, 1]
    assert (
        not (out / "seed=1" / "train").is_symlink()
        and (out / "seed=1" / "train" / "final.pt").is_file()
    )
    assert (batch / "seed1" / "final.pt").is_file()
    alone = json.loads((out / "seed=1" / "metrics.json").read_text())
    batched = json.loads((out / "seed=0" / "metrics.json").read_text())
    assert set(alone) | {"train_batch"} == set(batched) and "train_batch" not in alone
    summary = json.loads((out / "summary.json").read_text())
    assert [p["batch"] for p in summary["points"]] == ["../batches/seed=0-1", None]
