"""The sealed held-out split (families.HELDOUT_SEED, issue 33): no file outside the package names
a seed of its range (this test is the one file that may), and ``taskvar eval --test heldout``
plays exactly the sealed episodes, paired across methods, under no other seed."""

from __future__ import annotations

import csv
import re
from pathlib import Path

import pytest
import torch
from budgets import TINY  # tests/budgets.py

from taskvar_torch import cli
from taskvar_torch.config import load_config
from taskvar_torch.experiments.bundle_eval import eval_bundle
from taskvar_torch.factory import load_heads
from taskvar_torch.families import (
    FAMILIES,
    HELDOUT_SEED,
    HELDOUT_SEEDS,
    HELDOUT_SIZE,
    sealed_episode_seed,
)
from taskvar_torch.families.wargus.dynamics import NOMINAL_SEEDS
from taskvar_torch.families.windy.fig2 import heldout_seed, windy_fig2
from taskvar_torch.training import train

torch.set_num_threads(1)
ROOT = Path(__file__).resolve().parents[1]
SCANNED = ("configs", "tests", "scripts", "docs", "notebooks", "benchmarks", "examples")
"""Every folder a choice could be made or recorded in (the package itself declares the range)."""
TEXT = {".py", ".md", ".yaml", ".yml", ".ipynb", ".txt", ".toml", ".cfg", ".sh", ".json", ".csv"}
NUMBER = re.compile(r"(?<![\d_,.])\d{1,3}(?:[_,]?\d{3})+(?![\d_])|(?<![\d_,.])\d+(?![\d_])")


def held_out_numbers(text: str) -> list[str]:
    """The integers of ``text`` (digits, optionally grouped by ``_`` or ``,``) in the range."""
    hits = []
    for m in NUMBER.finditer(text):
        value = int(m.group().replace("_", "").replace(",", ""))
        if HELDOUT_SEED <= value < HELDOUT_SEED + HELDOUT_SIZE:
            hits.append(m.group())
    return hits


def test_the_scan_finds_the_range_in_every_spelling():
    text = "seeds 7000000, 7_000_123 and 7,000,299; not 7000300, 17000000, 6999999 or 0.7000001"
    assert held_out_numbers(text) == ["7000000", "7_000_123", "7,000,299"]


def test_no_config_doc_test_or_script_names_a_held_out_seed():
    me = Path(__file__).resolve()
    found = []
    for folder in SCANNED:
        for path in sorted((ROOT / folder).rglob("*")):
            if path == me or not path.is_file() or path.suffix not in TEXT:
                continue
            if any(part in (".ipynb_checkpoints", "__pycache__") for part in path.parts):
                continue
            hits = held_out_numbers(path.read_text(encoding="utf-8", errors="replace"))
            if hits:
                found.append(f"{path.relative_to(ROOT)}: {hits[:3]}")
    assert not found, found


def test_the_held_out_range_is_disjoint_from_the_nominal_and_config_seeds():
    assert not set(HELDOUT_SEEDS) & set(NOMINAL_SEEDS)
    for cfg_path in sorted((ROOT / "configs").glob("*.yaml")):
        text = cfg_path.read_text()
        seed = re.search(r"^seed:\s*(\d+)", text, re.M)
        s = int(seed.group(1)) if seed else 0
        # training seed, test runs seed + 1 + run, the scale test seed + 1000: far below the range
        assert s + 1000 + HELDOUT_SIZE < HELDOUT_SEED, cfg_path
    for fam in ("windy", "wargus", "taxi"):  # every family declares it, under the sealed seed
        assert FAMILIES[fam].tests["heldout"].seed == HELDOUT_SEED


@pytest.fixture(scope="module")
def bundles(tmp_path_factory, windy_tiny_bundle):
    """Bundles: Wargus trained here, windy's shared (tests/conftest.py; read only)."""
    d = tmp_path_factory.mktemp("wargus")
    train(load_config("configs/wargus.yaml", [*TINY, "env.wargus.horizon=40"]), d, progress=False)
    return {"wargus": d / "final.pt", "windy": windy_tiny_bundle}


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path) as f:
        return list(csv.DictReader(f))


def test_wargus_heldout_plays_the_sealed_instances_paired(bundles, tmp_path):
    m = eval_bundle(
        bundles["wargus"], "all", "heldout", episodes=6, out_dir=tmp_path, progress=False
    )
    seed = load_heads(bundles["wargus"])[1].seed  # the bundle's own draw of the sealed seed
    assert m["sealed_seed"] == HELDOUT_SEED and m["test"] == "heldout"
    assert m["seed"] == sealed_episode_seed(HELDOUT_SEED, seed)
    rows = _rows(tmp_path / "episodes.csv")
    per_method: dict[str, list[int]] = {}
    for r in rows:
        per_method.setdefault(r["method"], []).append(int(r["instance_seed"]))
    assert set(per_method) == {"averaging", "options", "interruption", "hierarchy"}
    for seeds in per_method.values():  # paired, and the range's first six instances in order
        assert seeds == list(HELDOUT_SEEDS[:6])


def test_windy_heldout_is_the_training_distribution_under_the_sealed_seed(
    bundles, tmp_path, capsys
):
    def episodes(test: str, seed: int | None, name: str) -> list[tuple[str, str, str]]:
        out = tmp_path / name
        eval_bundle(
            bundles["windy"],
            "averaging,options",
            test,
            episodes=40,
            seed=seed,
            out_dir=out,
            plots=False,
            progress=False,
        )
        rows = _rows(out / "episodes.csv")
        by_method = {}
        for r in rows:
            by_method.setdefault(r["method"], []).append(
                (r["instance_p"], r["instance_direction"], r["start"])
            )
        assert by_method["averaging"] == by_method["options"]  # paired
        return by_method["averaging"]

    held = episodes("heldout", None, "held")
    own = sealed_episode_seed(HELDOUT_SEED, load_heads(bundles["windy"])[1].seed)
    assert held == episodes("train", own, "same")  # the training winds, the bundle's sealed draw
    assert held != episodes("train", None, "nominal")  # not the nominal test episodes
    argv = ["eval", "--checkpoint", str(bundles["windy"]), "--test", "heldout", "--seed", "3"]
    assert cli.main([*argv, "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "sealed held-out seed" in err


def test_sealed_draws_differ_per_training_seed_and_stay_out_of_the_range():
    """Issue 56: each training seed plays its own draw of a sealed test (a CI over seeds then counts
    the episodes' noise); a deterministic one, never a seed of the sealed range itself."""
    draws = [sealed_episode_seed(HELDOUT_SEED, k) for k in range(1000)]
    assert len(set(draws)) == 1000 and draws == [
        sealed_episode_seed(HELDOUT_SEED, k) for k in range(1000)
    ]
    assert not set(draws) & set(HELDOUT_SEEDS)
    assert sealed_episode_seed(HELDOUT_SEED + 1, 0) != draws[0]  # each sealed run its own


@pytest.fixture(scope="module")
def windy_seed1(tmp_path_factory):
    """A windy bundle like tests/conftest.py's but of training seed 1."""
    d = tmp_path_factory.mktemp("windy-seed1")
    train(load_config("configs/windy.yaml", [*TINY, "seed=1"]), d, progress=False)
    return d / "final.pt"


def test_each_bundle_plays_its_own_heldout_episodes_paired_across_its_methods(
    bundles, windy_seed1, tmp_path
):
    def played(bundle, name):
        m = eval_bundle(
            bundle, "averaging,options", "heldout", episodes=40, out_dir=tmp_path / name,
            plots=False, progress=False,
        )  # fmt: skip
        by_method: dict[str, list] = {}
        for r in _rows(tmp_path / name / "episodes.csv"):
            by_method.setdefault(r["method"], []).append(
                (r["instance_p"], r["instance_direction"], r["start"])
            )
        assert by_method["averaging"] == by_method["options"]  # paired within the bundle
        return m, by_method["averaging"]

    m0, eps0 = played(bundles["windy"], "seed0")
    m1, eps1 = played(windy_seed1, "seed1")
    assert load_heads(windy_seed1)[1].seed == 1 + load_heads(bundles["windy"])[1].seed
    assert m0["sealed_seed"] == m1["sealed_seed"] == HELDOUT_SEED
    assert m0["seed"] != m1["seed"] and eps0 != eps1  # independent draws per training seed


@pytest.mark.slow  # a real process or several agents trained: make test only
def test_figure2_heldout_run0_is_eval_heldout(windy_seed1, tmp_path):
    """The Figure 2 protocol's held-out row and ``taskvar eval --test heldout`` are one measurement
    on the same bundle: its run 0 is the evaluation's episodes (the row pools ``runs`` of them)."""
    heads, cfg = load_heads(windy_seed1)
    cfg = load_config("configs/windy.yaml", [*TINY, "seed=1", "experiment.runs=2",
                                             "experiment.episodes_per_run=40"])  # fmt: skip
    fig = windy_fig2(cfg, tmp_path / "fig2", windy_seed1, progress=False, plots=False)
    ev = eval_bundle(
        windy_seed1, "averaging,options,interruption", "heldout", episodes=40,
        out_dir=tmp_path / "eval", plots=False, progress=False,
    )  # fmt: skip
    held = fig["heldout"]
    assert held["seeds"] == [heldout_seed(cfg, 0), heldout_seed(cfg, 1)]
    assert held["seeds"][0] == ev["seed"]
    run0 = held["per_run"][0]["mean_return"]
    for m in ("averaging", "options", "interruption"):
        assert run0[m] == pytest.approx(ev["points"][0]["methods"][m]["mean_return"], abs=1e-9)
