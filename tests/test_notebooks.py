"""The notebooks execute with small settings, and the outputs stored in them are current.

Each notebook is stored with its outputs (plots included) so that a reader sees them without
running anything. ``make notebooks`` produces them: it runs this file with ``TASKVAR_NB_WRITE=1``,
which executes every notebook with the small settings of :data:`SETTINGS` and writes it back with
its outputs. Without ``TASKVAR_NB_WRITE`` (CI), every notebook is executed the same way and its text
outputs are compared with the stored ones: a notebook whose code, settings or library changed
without ``make notebooks`` fails here. Every number a notebook prints is compared; not compared are
image bytes (regenerated: only the number of images per cell must match), the parts listed in
:data:`MASKS` (wall and CPU times) and the stderr stream (:data:`UNCOMPARED_STREAMS`), each with its
reason. The scratch folder (a temporary path) is stored as :data:`OUT_TOKEN`. The runs are
deterministic: fixed seeds, one thread.
"""

from __future__ import annotations

import base64
import difflib
import json
import os
import re
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

ROOT = Path(__file__).resolve().parent.parent
NOTEBOOKS = ROOT / "notebooks"
WRITE = os.environ.get("TASKVAR_NB_WRITE") == "1"
"""``make notebooks``: store the executed notebooks instead of comparing with them."""
OUT_TOKEN = "<TASKVAR_NB_OUT>"
"""Written in the stored outputs in place of the scratch folder (a temporary path)."""

WARGUS_TINY = [
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
WARGUS_SHIFT_TINY = [
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
SETTINGS: dict[str, dict[str, str]] = {
    "01_quickstart.ipynb": {"TASKVAR_NB_FRAMES": "3000"},
    "02_windy_interruption.ipynb": {
        "TASKVAR_NB_FRAMES": "3000",
        "TASKVAR_NB_RUNS": "2",
        "TASKVAR_NB_EPISODES": "100",
    },
    "03_wargus_composition.ipynb": {
        "TASKVAR_NB_OVERRIDES": " ".join(WARGUS_TINY),
        "TASKVAR_NB_RESULTS": "",
    },
    "04_shift.ipynb": {
        "TASKVAR_NB_FRAMES": "3000",
        "TASKVAR_NB_EPISODES": "100",
        "TASKVAR_NB_WARGUS_OVERRIDES": " ".join(WARGUS_SHIFT_TINY),
    },
}
"""Each notebook's small settings (its ``TASKVAR_NB_*`` knobs; every notebook also gets a scratch
``TASKVAR_NB_OUT`` and one thread): what CI runs and what the stored outputs were made with."""
THREADS = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
"""One thread (the notebooks also call ``torch.set_num_threads(1)``): the same float reductions
on every run, so the same numbers."""
MASKS = [
    (re.compile(r"(updates in )\d+(s)"), r"\1<wall>\2", "a training run's wall time"),
    (
        re.compile(r"(wall time )[\d.]+ s \([\d.]+ s per trial\)"),
        r"\1<wall>",
        "the Figure 4 protocol's wall time",
    ),
    (re.compile(r"^(CPU s per trial: ).*$", re.M), r"\1<cpu>", "its CPU seconds per trial"),
]
"""(pattern, replacement, why): the parts of a text output that differ between two runs of the
same code and are not compared."""
UNCOMPARED_STREAMS = {"stderr"}
"""Not compared: the libraries' warnings and log lines go to stderr, and they name local paths and
change with the installed versions; every number a notebook prints goes to stdout."""
MIN_IMAGES = {
    "01_quickstart.ipynb": 1,  # the rendered grid
    "02_windy_interruption.ipynb": 2,  # Figure 2 and the heat-map
    "03_wargus_composition.ipynb": 3,  # Figure 4, the decision traces and a rendered frame
    "04_shift.ipynb": 5,  # eval.png twice, the two reference plots, Wargus's eval.png
}
MAX_IMAGE_BYTES = 150_000
"""A stored plot's PNG at most (the notebooks' figures are saved at a low dpi)."""
MAX_NOTEBOOK_BYTES = 1_000_000
"""A stored notebook at most: plots as small PNGs, no megabyte dumps."""


def run_notebook(name: str, tmp_path: Path) -> nbformat.NotebookNode:
    """``name`` executed in ``notebooks/`` with its :data:`SETTINGS`, one thread and the scratch
    folder ``tmp_path/run``; the scratch path in its outputs replaced by :data:`OUT_TOKEN`."""
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    out = str(tmp_path / "run")
    env = {**SETTINGS[name], **THREADS, "TASKVAR_NB_OUT": out}
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        NotebookClient(
            nb,
            timeout=600,
            kernel_name="python3",
            record_timing=False,  # no per-cell timestamps in the stored file
            resources={"metadata": {"path": str(NOTEBOOKS)}},
        ).execute()
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    for cell in nb.cells:
        for o in cell.get("outputs", []):
            if "text" in o:
                o["text"] = o["text"].replace(out, OUT_TOKEN)
            if "text/plain" in o.get("data", {}):
                o["data"]["text/plain"] = o["data"]["text/plain"].replace(out, OUT_TOKEN)
    return nb


def _output_text(o: nbformat.NotebookNode) -> str:
    """One output as the comparison sees it: its kind, its text with :data:`MASKS` applied, and a
    placeholder per image (the bytes are not compared)."""
    if o["output_type"] == "stream":
        text = f"[{o['name']}]\n{o['text']}"
    elif o["output_type"] == "error":
        text = f"[error] {o['ename']}: {o['evalue']}"
    else:
        data = o.get("data", {})
        text = f"[{o['output_type']}]\n{data.get('text/plain', '')}"
        text += "".join(f"\n[{k}]" for k in sorted(data) if k.startswith("image/"))
    for pattern, repl, _ in MASKS:
        text = pattern.sub(repl, text)
    return text


def _compared(outputs: list) -> list:
    """The outputs the comparison reads: stderr left out, and the stdout chunks it separated
    merged back into one (where a library's stderr line lands between two prints is timing)."""
    out = []
    for o in outputs:
        if o["output_type"] == "stream" and o["name"] in UNCOMPARED_STREAMS:
            continue
        if o["output_type"] == "stream" and out and out[-1]["output_type"] == "stream":
            if out[-1]["name"] == o["name"]:
                out[-1] = nbformat.from_dict({**out[-1], "text": out[-1]["text"] + o["text"]})
                continue
        out.append(o)
    return out


def cell_outputs(nb: nbformat.NotebookNode) -> list[str]:
    """Every code cell's outputs, as the comparison sees them."""
    return [
        "\n".join(_output_text(o) for o in _compared(c.get("outputs", [])))
        for c in nb.cells
        if c.cell_type == "code"
    ]


def check_or_store(
    name: str, nb: nbformat.NotebookNode, folder: Path = NOTEBOOKS, write: bool = WRITE
) -> None:
    """``write`` (``TASKVAR_NB_WRITE=1``): write the executed notebook ``nb`` back as
    ``folder/name``; else fail where a stored output differs from the fresh one (a stale
    notebook), naming the cell and the lines."""
    path = folder / name
    if write:
        nb.metadata["taskvar"] = {"executed_with": SETTINGS.get(name)}
        nbformat.write(nb, path)
        return
    stored = nbformat.read(path, as_version=4)
    old, new = cell_outputs(stored), cell_outputs(nb)
    assert len(old) == len(new), f"{name}: {len(old)} stored code cells, {len(new)} now"
    for k, (a, b) in enumerate(zip(old, new)):
        if a != b:
            diff = "\n".join(
                difflib.unified_diff(
                    a.splitlines(), b.splitlines(), "stored", "now", lineterm="", n=1
                )
            )
            pytest.fail(
                f"notebooks/{name}: the stored outputs of code cell {k} are stale; run `make "
                f"notebooks` and commit the notebook\n{diff}"
            )


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
def test_quickstart_notebook_executes(tmp_path):
    nb = run_notebook("01_quickstart.ipynb", tmp_path)
    text = _code_text(nb)
    assert "interruption" in text and "exact expected return" in text
    assert _images(nb) >= MIN_IMAGES["01_quickstart.ipynb"]
    check_or_store("01_quickstart.ipynb", nb)


@pytest.mark.slow
def test_windy_interruption_notebook_executes(tmp_path):
    nb = run_notebook("02_windy_interruption.ipynb", tmp_path)
    text = _code_text(nb)
    assert "twin identical in every episode: True" in text
    assert (
        "null: averaging - averaging" in text
        and "Theorem 1" in text
        and "null rollouts tie" in text
    )
    assert (tmp_path / "run" / "fig2" / "metrics.json").is_file()
    assert _images(nb) >= MIN_IMAGES["02_windy_interruption.ipynb"]  # inline
    metrics = json.loads((tmp_path / "run" / "fig2" / "metrics.json").read_text())
    assert _printed_fig2_rows_match(text, metrics) >= 8  # the printed table, number by number
    check_or_store("02_windy_interruption.ipynb", nb)


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
    nb = run_notebook("03_wargus_composition.ipynb", tmp_path)
    text = _code_text(nb)
    assert "hierarchy control" in text and "instance seed 0:" in text and "root TG+FE ->" in text
    assert (tmp_path / "run" / "rep0" / "final.pt").is_file()
    assert _images(nb) >= MIN_IMAGES["03_wargus_composition.ipynb"]
    check_or_store("03_wargus_composition.ipynb", nb)


@pytest.mark.slow
def test_shift_notebook_executes(tmp_path):
    nb = run_notebook("04_shift.ipynb", tmp_path)
    text = _code_text(nb)
    assert "interruption" in text and "env.instances.p=1.0:" in text
    assert "test stormy" in text and "env.windy.horizon=200:" in text and "fast_patrol" in text
    assert "interruption fired at" in text and "sampled mean within its 95% CI" in text
    for folder in ("p_sweep", "horizon", "wargus_fast_patrol"):
        assert (tmp_path / "run" / folder / "metrics.json").is_file()
    assert _images(nb) >= MIN_IMAGES["04_shift.ipynb"]
    check_or_store("04_shift.ipynb", nb)


@pytest.mark.parametrize("name", sorted(SETTINGS))
def test_notebook_is_stored_with_its_outputs_and_plots(name):
    """After the executions (``make notebooks`` writes them first), what a reader sees without
    running anything: every code cell executed in order, no error,
    the plots inline, small PNGs, made with the settings CI runs."""
    path = NOTEBOOKS / name
    assert path.stat().st_size <= MAX_NOTEBOOK_BYTES, f"{name}: {path.stat().st_size} bytes"
    nb = nbformat.read(path, as_version=4)
    code = [c for c in nb.cells if c.cell_type == "code"]
    counts = [c.get("execution_count") for c in code]
    assert counts == list(range(1, len(code) + 1)), f"{name}: not stored executed: {counts}"
    outputs = [o for c in code for o in c.get("outputs", [])]
    assert not [o for o in outputs if o["output_type"] == "error"], f"{name} stored an error"
    assert _images(nb) >= MIN_IMAGES[name], f"{name}: {_images(nb)} stored plots"
    for o in outputs:
        png = o.get("data", {}).get("image/png")
        if png is not None:
            assert len(base64.b64decode(png)) <= MAX_IMAGE_BYTES, f"{name}: a plot too large"
    assert nb.metadata.get("taskvar", {}).get("executed_with") == SETTINGS[name], (
        f"{name}: stored outputs made with other settings than CI's; run `make notebooks`"
    )
    assert OUT_TOKEN in _code_text(nb) or name == "01_quickstart.ipynb"  # no temporary path


def test_a_stale_output_fails_and_names_the_cell(tmp_path):
    """The comparison itself: a stored number that differs fails, naming the cell; a masked wall
    time and a different image do not."""
    cell = nbformat.v4.new_code_cell("print(1)")
    cell.outputs = [
        nbformat.v4.new_output("stream", name="stdout", text="trained 8 updates in 3s\n")
    ]
    cell.outputs.append(
        nbformat.v4.new_output("display_data", data={"image/png": "AAAA", "text/plain": "<Figure>"})
    )
    stored = nbformat.v4.new_notebook(cells=[cell])
    nbformat.write(stored, tmp_path / "x.ipynb")
    fresh = nbformat.from_dict(json.loads(json.dumps(stored)))
    fresh.cells[0].outputs[0]["text"] = "trained 8 updates in 5s\n"  # wall time: masked
    fresh.cells[0].outputs[1]["data"]["image/png"] = "BBBB"  # image bytes: not compared
    check_or_store("x.ipynb", fresh, tmp_path, write=False)
    fresh.cells[0].outputs[0]["text"] = "trained 9 updates in 5s\n"
    with pytest.raises(pytest.fail.Exception, match="code cell 0 are stale"):
        check_or_store("x.ipynb", fresh, tmp_path, write=False)
    fresh.cells[0].outputs.pop()  # an image less
    with pytest.raises(pytest.fail.Exception, match="stale"):
        check_or_store("x.ipynb", fresh, tmp_path, write=False)
