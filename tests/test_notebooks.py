"""The notebooks execute: small settings through environment variables."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = Path(__file__).resolve().parent.parent / "notebooks"


def run_notebook(name: str, tmp_path: Path, env: dict[str, str]) -> nbformat.NotebookNode:
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        NotebookClient(
            nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(NOTEBOOKS)}}
        ).execute()
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return nb


@pytest.mark.slow
def test_quickstart_notebook_executes(tmp_path):
    nb = run_notebook(
        "01_quickstart.ipynb",
        tmp_path,
        {
            "TASKVAR_NB_FRAMES": "3000",
            "TASKVAR_NB_OUT": str(tmp_path / "run"),
            "OMP_NUM_THREADS": "1",
        },
    )
    text = "".join(
        o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
    )
    assert "interruption" in text and "exact expected return" in text


def _code_text(nb: nbformat.NotebookNode) -> str:
    return "".join(
        o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
    )


def _images(nb: nbformat.NotebookNode) -> int:
    return sum(
        "image/png" in o.get("data", {})
        for c in nb.cells
        if c.cell_type == "code"
        for o in c.get("outputs", [])
    )


@pytest.mark.slow
def test_windy_interruption_notebook_executes(tmp_path):
    env = {
        "TASKVAR_NB_FRAMES": "3000",
        "TASKVAR_NB_RUNS": "2",
        "TASKVAR_NB_EPISODES": "100",
        "TASKVAR_NB_OUT": str(tmp_path / "run"),
        "OMP_NUM_THREADS": "1",
    }
    nb = run_notebook("02_windy_interruption.ipynb", tmp_path, env)
    text = _code_text(nb)
    assert "twin identical in every episode: True" in text
    assert (
        "null: averaging - averaging" in text
        and "Theorem 1" in text
        and "null rollouts tie" in text
    )
    assert (tmp_path / "run" / "fig2" / "metrics.json").is_file()
    assert _images(nb) >= 2  # Figure 2 and the heat-map, inline
    metrics = json.loads((tmp_path / "run" / "fig2" / "metrics.json").read_text())
    assert _printed_fig2_rows_match(text, metrics) >= 8  # the printed table, number by number


FIG2_ROW = re.compile(
    r"^(train|south_only|heldout)\s+(.+?)\s+(\d+\.\d)%\s+(\d+\.\d)%\s+(\d+\.\d)%\s+"
    r"([+-]\d+\.\d{3})",
    re.M,
)
FIG2_BLOCKS = {
    "interruption - averaging (sampled, paired)": None,
    "null: averaging - averaging (indep. gusts)": "null",
    "interruption - averaging (exact, learnt)": "exact",
    "options - averaging (sampled, paired)": "options_vs_averaging",
    "interruption - options (sampled, paired)": "interruption_vs_options",
}


def _printed_fig2_rows_match(text: str, metrics: dict) -> int:
    """Every Figure 2 row the notebook printed equals metrics.json's figures to the printed
    digits; returns the rows checked."""
    checked = 0
    for dist, name, no_worse, better, worse, diff in FIG2_ROW.findall(text):
        block = metrics if dist == "train" else metrics[dist]
        s = block if FIG2_BLOCKS[name] is None else block[FIG2_BLOCKS[name]]
        assert float(no_worse) == pytest.approx(100 * s["fraction_no_worse"], abs=0.051), name
        assert float(better) == pytest.approx(100 * s["fraction_better"], abs=0.051), name
        assert float(worse) == pytest.approx(100 * s["fraction_worse"], abs=0.051), name
        assert float(diff) == pytest.approx(s["mean_difference"], abs=0.00051), name
        checked += 1
    return checked


@pytest.mark.slow
def test_wargus_composition_notebook_executes(tmp_path):
    tiny = [
        "env.wargus.size=16",
        "env.wargus.horizon=60",
        "experiment.runs=2",
        "experiment.trials=3",
        "experiment.learning_episodes_per_trial=8",
        "train.init_random_frames=100",
        "train.batch_size=32",
        "train.frames_per_batch=64",
        "train.buffer_size=5000",
        "heads.hidden=[32]",
    ]
    env = {
        "TASKVAR_NB_OVERRIDES": " ".join(tiny),
        "TASKVAR_NB_OUT": str(tmp_path / "run"),
        "TASKVAR_NB_RESULTS": "",
        "OMP_NUM_THREADS": "1",
    }
    nb = run_notebook("03_wargus_composition.ipynb", tmp_path, env)
    text = _code_text(nb)
    assert "hierarchy control" in text and "instance seed 0:" in text and "root TG+FE ->" in text
    assert (tmp_path / "run" / "rep0" / "final.pt").is_file()
    assert _images(nb) >= 3  # Figure 4, the decision traces and a rendered frame


@pytest.mark.slow
def test_shift_notebook_executes(tmp_path):
    tiny_wargus = [
        "env.num_envs=4",
        "train.frames_per_batch=100",
        "train.total_frames=300",
        "train.init_random_frames=100",
        "train.batch_size=16",
        "train.updates_per_batch=1",
        "train.buffer_size=1000",
        "train.log_every=300",
        "env.wargus.horizon=60",
    ]
    env = {
        "TASKVAR_NB_FRAMES": "3000",
        "TASKVAR_NB_EPISODES": "100",
        "TASKVAR_NB_WARGUS_OVERRIDES": " ".join(tiny_wargus),
        "TASKVAR_NB_OUT": str(tmp_path / "run"),
        "OMP_NUM_THREADS": "1",
    }
    nb = run_notebook("04_shift.ipynb", tmp_path, env)
    text = _code_text(nb)
    assert "interruption" in text and "env.instances.p=1.0:" in text
    assert "test stormy" in text and "env.horizon=200:" in text and "fast_patrol" in text
    assert "interruption fired at" in text and "sampled mean within its 95% CI" in text
    for folder in ("p_sweep", "horizon", "wargus_fast_patrol"):
        assert (tmp_path / "run" / folder / "metrics.json").is_file()
    assert _images(nb) >= 5  # eval.png twice, the two reference plots, Wargus's eval.png
