"""The scale experiment's seeds axis (docs/scale.md#seeds): ``seeds=2`` trains each cell once with
``train.seeds=2``, evaluates every seed's bundle on the same test episodes, writes one scale.csv row
per (seed, method) and aggregates over the seeds; ``seeds=1`` writes today's keys and columns."""

from __future__ import annotations

import csv
import dataclasses

import numpy as np
import pytest
import torch
from scale_runs import run_scale

from taskvar_torch.checkpoint import CheckpointError
from taskvar_torch.config import METHODS
from taskvar_torch.factory import load_heads
from taskvar_torch.study import scale, scale_eval, scale_report

torch.set_num_threads(1)

CELL = "windy-5x5-n4"
TINY = [  # one small windy cell, a few hundred frames, short episodes
    "num_envs=[4]",
    "eval_episodes=8",
    "eval_batch_size=8",
    "only=[windy-5x5]",
    "curve_episodes=8",
    "head_report=false",
    'overrides=["heads.hidden=[32]",train.batch_size=32,env.horizon=30]',
]
# metrics.json's keys before the seeds axis: a one-seed run must keep exactly these
TOP_KEYS = {
    "experiment", "quick", "methods", "total_frames", "num_envs", "eval_episodes", "test_seed",
    "threads", "references", "cells", "wall_seconds", "notes",
    "code",  # the code's version and commit, in every results folder (taskvar report, issue 56)
}  # fmt: skip
CELL_KEYS = {
    "peak_rss_mb", "peak_cuda_mb", "case", "family", "grid_side", "cells", "num_envs", "frames",
    "updates", "frames_per_batch", "updates_per_batch", "hidden", "obs_encoding", "train_seconds",
    "frames_per_second", "eval_seconds", "methods", "curve", "heads",
}  # fmt: skip


@pytest.fixture(scope="module")
def two_seeds(tmp_path_factory):
    out = tmp_path_factory.mktemp("scale-seeds")
    m = run_scale(
        out, *TINY, "seeds=2", "total_frames=600", "curve_points=2", "keep_checkpoints=true"
    )
    return out, m


@pytest.mark.slow
def test_each_seed_row_is_its_bundle_evaluated_on_the_same_episodes(two_seeds):
    out, m = two_seeds
    (c,) = m["cells"]
    cell = out / "cells" / CELL
    assert m["seeds"] == 2 and c["seeds"] == [0, 1] and m["test_seed"] == 1000
    # one training run: the cell's final.pt is the batch (not evaluable), one bundle per seed
    with pytest.raises(CheckpointError, match="batch of 2 training runs"):
        load_heads(cell / "final.pt")
    heads = []
    for k, run in enumerate(c["per_seed"]):
        h, bcfg = load_heads(cell / f"seed{k}" / "final.pt")
        assert run["seed"] == k and bcfg.seed == k and bcfg.train.seeds == 1
        heads.append(h)
        # evaluated directly from the bundle's own config, on the scale's test episodes (seed 0's)
        ecfg = dataclasses.replace(bcfg, seed=0)
        for method in METHODS:
            direct = scale_eval.evaluate(ecfg, method, 8, 8, h)
            row = run["methods"][method]
            if direct is None:
                assert row is None  # windy: no hierarchy
                continue
            assert {key: row[key] for key in direct} == direct, (k, method)
    assert c["per_seed"][0]["methods"] == c["methods"]  # the cell's own keys: seed `seed`'s run
    assert (
        c["curve"][-1]["methods"]["averaging"]["mean_return"]
        == (c["methods"]["averaging"]["mean_return"])
    )
    assert len(c["curve"]) >= 2 and list((cell / "seed1" / "heads").glob("heads_*.pt"))
    # the seeds are different runs: their own initialisation and data
    a, b = (h.state_dict() for h in heads)
    assert any(not torch.equal(a[k], b[k]) for k in a)
    assert c["per_seed"][0]["methods"] != c["per_seed"][1]["methods"]
    assert c["frames_per_second_all_seeds"] == pytest.approx(2 * c["frames_per_second"])


@pytest.mark.slow
def test_csv_has_a_row_per_seed_and_the_aggregate_is_over_the_seeds(two_seeds):
    out, m = two_seeds
    (c,) = m["cells"]
    with open(out / "scale.csv", newline="") as f:
        reader = csv.DictReader(f)
        rows = list(reader)
    assert tuple(reader.fieldnames) == scale_report.csv_fields(m) and "seed" in reader.fieldnames
    assert len(rows) == 2 * len(METHODS)
    for r in rows:
        v = c["per_seed"][int(r["seed"])]["methods"][r["method"]]
        assert r["mean_return"] == ("n/a" if v is None else str(v["mean_return"]))
    rand = m["references"]["windy-5x5"]["random"]["mean_return"]
    orc = m["references"]["windy-5x5"]["oracle_averaging"]["mean_return"]
    for method, agg in c["over_seeds"].items():
        per = [run["methods"][method] for run in c["per_seed"]]
        if per[0] is None:
            assert agg is None
            continue
        returns = [p["mean_return"] for p in per]
        assert agg["returns"] == returns and agg["seeds"] == 2
        assert agg["mean_return"] == pytest.approx(np.mean(returns))
        lo, hi = agg["mean_ci95"]
        assert min(returns) - 1e-9 <= lo <= agg["mean_return"] <= hi <= max(returns) + 1e-9
        assert agg["gap_closed"] == pytest.approx((agg["mean_return"] - rand) / (orc - rand))
    assert "Over the training seeds" in scale_report.format_table(m)
    # the figure's final returns are the means over the seeds, with their bootstrap CI
    mean, (below, above) = scale_report.final_return(c, "averaging")
    agg = c["over_seeds"]["averaging"]
    assert mean == agg["mean_return"]
    assert [mean - below, mean + above] == pytest.approx(agg["mean_ci95"])
    assert [p.name for p in scale_report.plot_results(out)] == ["scale.png", "scale_curves.png"]


@pytest.mark.slow
def test_one_seed_writes_todays_keys_and_columns(tmp_path):
    # held-out off: its block is new keys only (tests/study/test_scale_heldout.py)
    m = run_scale(tmp_path, *TINY, "total_frames=200", "curve_points=0", "heldout_episodes=0")
    assert set(m) == TOP_KEYS
    (c,) = m["cells"]
    assert set(c) == CELL_KEYS
    with open(tmp_path / "scale.csv", newline="") as f:
        assert tuple(csv.DictReader(f).fieldnames) == scale_report.CSV_FIELDS
    cell = tmp_path / "cells" / CELL
    assert (cell / "heads.pt").is_file() and not list(cell.glob("seed*"))


@pytest.mark.parametrize("value", ["0", "-1", "1.5", "true"])
def test_bad_seeds_are_one_line_errors(value):
    with pytest.raises(ValueError, match="seeds"):
        scale.load_scale_config(scale.default_config_path(), [f"seeds={value}"])
