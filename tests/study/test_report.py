"""``taskvar report`` (study/report.py) on synthetic results folders whose answers are known:
each verdict follows the data (a clear lead reproduces a claim, a tie does not), the figures are
the per-seed numbers' own means, the README changes between its markers only, and every kind of
bad input is one line that writes nothing."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from taskvar_torch import cli
from taskvar_torch.checkpoint import make_bundle, save_checkpoint
from taskvar_torch.families import HELDOUT_SEED
from taskvar_torch.study import report, report_claims, report_folders
from taskvar_torch.study import report_results as glance

METHODS = ("averaging", "options", "interruption", "hierarchy")
START, END = report.README_START, report.README_END
README = f"# x\n\nintro\n\n## Results\n\n{START}\nold table\n{END}\n\ntail\n"
REPS = "100"  # bootstrap resamples: enough for the clear-cut answers below, and fast


def _write(folder: Path, metrics: dict, config: dict | None) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "metrics.json").write_text(json.dumps(metrics))
    if config is not None:
        (folder / "config.yaml").write_text(yaml.safe_dump(config))
    return folder


def fig4_folder(
    folder: Path, seeds, levels: dict, trials: int = 40, rise: dict | None = None, size: int = 12
):
    """A Wargus Figure 4 folder: method ``m``'s held-out curve rises linearly to ``levels[m]`` by
    trial ``rise[m]`` and stays there (plus small per-seed noise)."""
    rng = np.random.default_rng(seeds[0])
    rise = rise or dict.fromkeys(levels, trials // 4)
    methods = {}
    for m in levels:  # the paper's METHODS, and any experiment.baselines' curve
        t = np.arange(1, trials + 1)
        curve = levels[m] * np.minimum(t / rise[m], 1.0)
        per_rep = curve + rng.normal(0, 0.01, (len(seeds), trials))
        methods[m] = {"curve_per_rep": per_rep.tolist()}
    metrics = {
        "experiment": "wargus-fig4",
        "protocol": {"seeds": list(seeds)},
        "heldout": {"methods": methods},
    }
    cfg = {
        "seed": seeds[0],
        "family": "wargus",
        "env": {"wargus": {"size": size}},
        "experiment": {"trials": trials},
    }
    return _write(folder, metrics, cfg)


def fig2_folder(folder: Path, seed: int, no_worse: float, better: float, layout="default"):
    held = {
        "fraction_no_worse": no_worse,
        "fraction_better": better,
        "fraction_no_worse_null": 0.85,
        "mean_difference": better - (1 - no_worse),
        "mean_return": {m: {"mean": -6.0 + 0.1 * seed} for m in METHODS[:3]},
    }
    cfg = {"seed": seed, "family": "windy", "env": {"layout": layout}}
    return _write(folder, {"experiment": "windy-fig2", "heldout": held}, cfg)


def eval_folder(
    folder: Path,
    seed: int,
    ranges: dict,
    test: str = "heldout",
    family: str = "windy",
    sealed: bool | None = None,
) -> Path:
    """A ``taskvar eval`` shift curve of 3 points; method ``m`` spans ``ranges[m]``, with the
    bundle (a config-only checkpoint) of training seed ``seed``. ``sealed`` (default: the test is
    ``heldout``): the test has a sealed seed, recorded as ``taskvar eval`` does."""
    ckpt = folder / "bundle.pt"
    folder.mkdir(parents=True, exist_ok=True)
    save_checkpoint(ckpt, make_bundle({"seed": seed, "family": family}, models={}))
    points = [
        {"methods": {m: {"mean_return": -6.0 - r * i / 2 + 0.01 * seed} for m, r in ranges.items()}}
        for i in range(3)
    ]
    metrics = {
        "experiment": "eval",
        "checkpoint": str(ckpt),
        "family": family,
        "test": test,
        "shifts": ["env.instances.p=0.0,0.5,1.0"],
        "methods": list(ranges),
        "episodes": 100,
        "points": points,
    }
    if test == "heldout" if sealed is None else sealed:
        metrics["sealed_seed"] = HELDOUT_SEED
    return _write(folder, metrics, None)


def _run(argv, capsys):
    try:
        rc = cli.main(["report", *argv, "--reps", REPS])
    except SystemExit as e:
        rc = e.code
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


@pytest.mark.slow  # ~15 s: five groups' bootstraps (rliable's Mann-Whitney per resample)
def test_verdicts_follow_the_data(tmp_path, capsys):
    lead = {"averaging": 1.0, "options": 1.5, "interruption": 2.0, "hierarchy": 2.5}
    fast = {"averaging": 30, "options": 20, "interruption": 15, "hierarchy": 5}
    fig4_folder(tmp_path / "lead", range(5), lead, rise=fast)
    tie = dict.fromkeys(METHODS, 1.0)
    for k in range(5):  # a seed<k>/ layout; every method the same curve
        fig4_folder(tmp_path / "tie" / f"seed{k}", [10 + k], tie, size=16)
    for k in range(5):
        fig2_folder(tmp_path / "fig2" / f"seed{k}", k, no_worse=0.9, better=0.1)
        fig2_folder(tmp_path / "fig2tie" / f"seed{k}", k, 1.0, 0.0, layout="whole_column_windy")
        eval_folder(tmp_path / "eval" / f"seed{k}", k, {"averaging": 50.0, "options": 5.0})
    readme = tmp_path / "README.md"
    readme.write_text(README)
    out = tmp_path / "docs" / "claims.md"
    dirs = [str(tmp_path / d) for d in ("lead", "tie", "fig2", "fig2tie", "eval")]
    rc, stdout, err = _run([*dirs, "--out", str(out), "--readme", str(readme)], capsys)
    assert rc == 0, err
    verdicts = {
        line.split("]: ")[0]: line.split("]: ")[1].split(" ")[0]
        for line in stdout.splitlines()
        if "]: " in line
    }

    def verdict(claim: str, group: str) -> str:
        return verdicts[f"{report_claims.CLAIMS[claim][0]} [{group}"]

    assert verdict("fig4_order", "wargus-fig4, 12x12, 40 trials") == "reproduced"
    assert verdict("fig4_speed", "wargus-fig4, 12x12, 40 trials") == "reproduced"
    assert verdict("fig4_order", "wargus-fig4, 16x16, 40 trials") == "not"  # a tie: neither
    assert verdict("fig4_speed", "wargus-fig4, 16x16, 40 trials") == "not"
    assert verdict("fig2", "windy-fig2, layout default") == "reproduced"
    assert verdict("fig2", "windy-fig2, layout whole_column_windy") == "partly"  # a tie, not a gain
    premise = [v for k, v in verdicts.items() if k.startswith("§3.2")]
    assert premise == ["reproduced"]
    page = out.read_text()
    assert page.splitlines()[0] == report.GENERATED
    assert page.count("| **reproduced** |") == 4 and "| **partly** |" in page
    png = out.parent / "img" / "claims-profile.png"
    assert png.is_file() and report._ours_png(png)
    text = readme.read_text()
    assert text.startswith("# x\n\nintro\n\n## Results\n\n" + report.README_START)
    assert text.endswith(report.README_END + "\n\ntail\n") and "old table" not in text
    assert text.count("| windy-fig2, layout default |") == 1


@pytest.mark.slow  # 4-8 s: three reports (rliable's first import lands here)
def test_a_rerun_replaces_its_own_files_only(tmp_path, capsys):
    for k in range(5):
        fig2_folder(tmp_path / "fig2" / f"seed{k}", k, no_worse=0.9, better=0.1)
    readme = tmp_path / "README.md"
    readme.write_text(README)
    out = tmp_path / "claims.md"
    argv = [str(tmp_path / "fig2"), "--out", str(out), "--readme", str(readme)]
    assert _run(argv, capsys)[0] == 0
    first = readme.read_text()
    assert "old table" not in first and first.count(START) == 1
    assert _run(argv, capsys)[0] == 0  # its own page and PNG: replaced, the README block again
    assert readme.read_text() == first
    png = tmp_path / "img" / "claims-profile.png"
    png.write_bytes(b"someone's picture")
    rc, _, err = _run(argv, capsys)
    assert rc == 2 and "was not written by taskvar report" in err
    assert png.read_bytes() == b"someone's picture"


@pytest.mark.slow  # ~2-3.5 s on a 2-core CPU: make test only
def test_figures_are_the_per_seed_numbers(tmp_path):
    levels = {"averaging": 1.0, "options": 1.2, "interruption": 1.2, "hierarchy": 1.6}
    folder = fig4_folder(tmp_path / "f", range(6), levels, trials=20)
    groups = report_folders.collect([str(folder)])
    (order, speed), _, _ = report_claims._fig4(groups[0], 200)
    curves = json.loads((folder / "metrics.json").read_text())["heldout"]["methods"]
    first = {m: np.asarray(curves[m]["curve_per_rep"])[:, :10].mean(1) for m in METHODS}
    want = float(np.mean(first["hierarchy"] - first["averaging"]))
    assert f"hierarchy - averaging {want:+.3f}" in order.ours
    assert order.verdict == "partly"  # interruption = options (a tie) breaks the chain
    assert "interruption vs options: level" in order.reason or "tied" in order.reason


@pytest.mark.slow  # ~2-3.5 s on a 2-core CPU: make test only
def test_fig4_baseline_curve_joins_the_evidence(tmp_path):
    """A recurrent curve (``experiment.baselines``) is listed beside the paper's methods and in
    the probability of improvement; the verdicts still rest on the paper's methods alone."""
    levels = {"averaging": 1.0, "options": 1.2, "interruption": 1.4, "hierarchy": 1.6}
    plain = fig4_folder(tmp_path / "plain", range(5), levels, trials=20)
    both = fig4_folder(tmp_path / "both", range(5), {**levels, "recurrent": 0.5}, trials=20)
    (order_a, speed_a), _, _ = report_claims._fig4(report_folders.collect([str(plain)])[0], 200)
    (order_b, speed_b), _, profile = report_claims._fig4(
        report_folders.collect([str(both)])[0], 200
    )
    assert "recurrent" not in " ".join(order_a.details)
    assert "; recurrent IQM" in order_b.details[0] and "recurrent 0." in order_b.details[2]
    assert "recurrent" in profile
    assert (order_a.verdict, speed_a.verdict) == (order_b.verdict, speed_b.verdict)


def _bad_inputs(tmp_path: Path) -> dict[str, tuple[list[str], str]]:
    levels = dict.fromkeys(METHODS, 1.0)
    (tmp_path / "empty").mkdir()
    for k in range(5):
        fig4_folder(tmp_path / "mixed" / f"seed{k}", [k], levels, trials=40 if k < 4 else 50)
    fig4_folder(tmp_path / "a", range(5), levels)
    fig4_folder(tmp_path / "b", range(3, 8), levels)
    (tmp_path / "sweep").mkdir()
    (tmp_path / "sweep" / "metrics.json").write_text(json.dumps({"experiment": "sweep"}))
    for k in range(5):
        eval_folder(tmp_path / "nobundle" / f"seed{k}", k, {"averaging": 1.0, "options": 1.0})
        (tmp_path / "nobundle" / f"seed{k}" / "bundle.pt").unlink()
    old = tmp_path / "old"
    fig4_folder(old, range(5), levels)
    m = json.loads((old / "metrics.json").read_text())
    del m["heldout"]
    (old / "metrics.json").write_text(json.dumps(m))
    return {
        "not a folder": ([str(tmp_path / "missing")], "is not a folder"),
        "no metrics": ([str(tmp_path / "empty")], "is not a results folder"),
        "another kind": ([str(tmp_path / "sweep")], "is not a results folder of"),
        "mixed configs": ([str(tmp_path / "mixed")], "different configs as one claim"),
        "seed twice": ([str(tmp_path / "a"), str(tmp_path / "b")], "appears twice"),
        "no bundle": ([str(tmp_path / "nobundle")], "is not there"),
        "no held-out": ([str(old)], "without held-out scores"),
    }


@pytest.mark.parametrize(
    "case",
    [
        "not a folder",
        "no metrics",
        "another kind",
        "mixed configs",
        "seed twice",
        "no bundle",
        "no held-out",
        "broken markers",
        "foreign page",
    ],
)
def test_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys, case):
    cases = _bad_inputs(tmp_path)
    readme = tmp_path / "README.md"
    readme.write_text(README)
    out = tmp_path / "docs" / "claims.md"
    good = str(tmp_path / "a")
    if case == "broken markers":  # one marker only: not a page to guess about
        readme.write_text(f"# x\n\n{START}\nno end marker\n")
        dirs, needle = [good], "must hold"
    elif case == "foreign page":
        out.parent.mkdir(parents=True)
        out.write_text("# my own notes\n")
        dirs, needle = [good], "was not written by taskvar report"
    else:
        dirs, needle = cases[case]
    before = readme.read_text()
    rc, _, err = _run([*dirs, "--out", str(out), "--readme", str(readme)], capsys)
    assert rc == 2
    assert len(err.strip().splitlines()) == 1 and needle in err, err
    assert readme.read_text() == before
    assert not (out.parent / "img").exists()
    assert case == "foreign page" or not out.exists()


def test_scale_rows_aggregate_the_gap_over_seeds_and_windy_cells(tmp_path):
    from scipy.stats import trim_mean

    gaps = {}
    for k in range(5):
        cells = []
        for case, n, g in (("windy-5x5", 16, 1.0), ("windy-25x25", 16, 0.6 + 0.05 * k)):
            gaps.setdefault(case, []).append(g)
            methods = {m: {"mean_return": -6.0, "gap_closed": g} for m in METHODS[:3]}
            cells.append({"case": case, "family": "windy", "num_envs": n, "methods": methods})
        wargus = {m: {"mean_return": 2.0, "gap_closed": None} for m in METHODS}
        cells.append(
            {"case": "wargus-32x32", "family": "wargus", "num_envs": 16, "methods": wargus}
        )
        _write(
            tmp_path / "scale" / f"seed{k}",
            {"experiment": "scale", "cells": cells},
            {"seed": k, "only": ["windy-5x5", "windy-25x25", "wargus-32x32"]},
        )
    rows = report_claims.build_report([str(tmp_path / "scale")], reps=100).rows
    assert len(rows) == 1 and rows[0][2] == 5
    want = trim_mean(np.array([gaps["windy-25x25"], gaps["windy-5x5"]]).T, 0.25, axis=None)
    assert f"averaging {want:.2f} [" in rows[0][1]
    assert "hierarchy" not in rows[0][1]  # no windy cell has it


def test_a_capability_that_fails_everywhere_is_unaffected_not_robust(tmp_path):
    for k in range(5):
        folder = eval_folder(tmp_path / "e" / f"seed{k}", k, {"averaging": 50.0, "options": 0.0})
        m = json.loads((folder / "metrics.json").read_text())
        for p in m["points"]:
            p["methods"]["options"]["mean_return"] = -100.0  # the same failure at every point
        (folder / "metrics.json").write_text(json.dumps(m))
    (claim,) = report_claims.build_report([str(tmp_path / "e")], reps=100).claims
    assert claim.key == "premise" and claim.verdict == "partly"
    assert "fail everywhere" in claim.reason


def test_a_scale_folder_of_several_seeds_counts_each(tmp_path):
    per_seed = [
        {
            "seed": k,
            "methods": {m: {"mean_return": -6.0, "gap_closed": 0.5 + 0.1 * k} for m in METHODS[:3]},
        }
        for k in range(5)
    ]
    cell = {
        "case": "windy-5x5",
        "family": "windy",
        "num_envs": 16,
        "methods": per_seed[0]["methods"],
        "seeds": list(range(5)),
        "per_seed": per_seed,
    }
    _write(
        tmp_path / "s",
        {"experiment": "scale", "seeds": 5, "cells": [cell]},
        {"seed": 0, "seeds": 5},
    )
    (g,) = report_folders.collect([str(tmp_path / "s")])
    assert g.seeds == [0, 1, 2, 3, 4]
    (row,) = report_claims.build_report([str(tmp_path / "s")], reps=100).rows
    assert "averaging 0.70 [" in row[1]  # the IQM of 0.5 ... 0.9


def test_the_readme_header_does_not_call_every_row_held_out():
    """An eval row of ``--test train`` sits in the same table as the held-out claims, and a
    family may have no sealed split at all: the header says each row names its test, held-out
    meaning the sealed instances (found on the real windy tables; issue 59)."""
    rows = [("eval windy --test train", "IQM mean return (--test train, 1 point(s))", 5, "abc")]
    table = report.results_table(report_claims.Report([], [], rows, [], 100))
    header = table.splitlines()[0]
    assert "(held-out instances;" not in header
    assert "on the test each row names; held-out: the sealed instances" in header
    assert "| eval windy --test train |" in table


def test_two_configs_of_one_label_are_named_by_the_key_that_differs(tmp_path):
    """Two Figure 4 folders of one grid and length but another ``train.compile`` are two claims,
    each labelled by that key's value; a third config of the same label falls back to digests."""
    level = {"averaging": 1.0, "options": 1.0, "interruption": 1.0, "hierarchy": 1.2}
    for name, compile_ in (("eager", False), ("compiled", True)):
        folder = fig4_folder(tmp_path / name, range(5), level)
        cfg = yaml.safe_load((folder / "config.yaml").read_text())
        cfg["train"] = {"compile": compile_}
        (folder / "config.yaml").write_text(yaml.safe_dump(cfg))
    groups = report_folders.collect([str(tmp_path / "eager"), str(tmp_path / "compiled")])
    assert [g.label for g in groups] == [
        "wargus-fig4, 12x12, 40 trials (train.compile=false)",
        "wargus-fig4, 12x12, 40 trials (train.compile=true)",
    ]
    third = fig4_folder(tmp_path / "third", range(5), level)
    cfg = yaml.safe_load((third / "config.yaml").read_text())
    cfg["train"] = {"compile": False, "lr": 0.1}
    (third / "config.yaml").write_text(yaml.safe_dump(cfg))
    groups = report_folders.collect([str(tmp_path / d) for d in ("eager", "compiled", "third")])
    assert all(g.label.endswith(f"(config {g.digest})") for g in groups)
    assert len({g.label for g in groups}) == 3


def test_add_grows_the_readme_table_and_keeps_the_other_rows(tmp_path, capsys):
    """``--add`` appends the rows of results that score no claim, replaces a row of the same
    experiment and config where it stands on a rerun, keeps rows of results not given, writes no
    claims page, and refuses results that score a claim."""
    old = "| eval windy --test south | old headline | 5 | abcd1234 | - ([claims](docs/claims.md)) |"
    head = report.results_table(report_claims.Report([], [], [], [], 100)).splitlines()
    readme = tmp_path / "README.md"
    readme.write_text(README.replace("old table", "\n".join([*head, old])))
    for k in range(5):
        eval_folder(tmp_path / "e" / f"seed{k}", k, {"averaging": 1.0, "options": 2.0}, "train")
    rc, out, err = _run([str(tmp_path / "e"), "--readme", str(readme), "--add"], capsys)
    assert rc == 0, err
    block = readme.read_text().split(START)[1].split(END)[0]
    rows = glance.details_of(block).strip().splitlines()
    assert rows[:3] == [*head, old] and len(rows) == 4
    assert rows[3].startswith("| eval windy --test train --shift") and "averaging -6.48" in rows[3]
    assert rows[3].endswith("| - |")  # no verdict, and --add writes no claims page to link
    assert "1 row(s) of the table below are in no table above" in block  # the old row: no data
    assert readme.read_text().endswith(f"{END}\n\ntail\n")
    assert not (tmp_path / "docs" / "claims.md").exists()  # no claims page: the summaries only
    kept = json.loads((tmp_path / "docs" / "claims-results.json").read_text())["groups"]
    assert [g["label"] for g in kept] == [
        "eval windy --test train --shift env.instances.p=0.0,0.5,1.0"
    ]
    for k in range(5):  # a rerun on other numbers replaces its own row, in place
        m = json.loads((tmp_path / "e" / f"seed{k}" / "metrics.json").read_text())
        m["points"][0]["methods"]["averaging"]["mean_return"] = -9.5
        (tmp_path / "e" / f"seed{k}" / "metrics.json").write_text(json.dumps(m))
    assert _run([str(tmp_path / "e"), "--readme", str(readme), "--add"], capsys)[0] == 0
    block = readme.read_text().split(START)[1].split(END)[0]
    again = glance.details_of(block).strip().splitlines()
    assert again[:3] == rows[:3] and len(again) == 4 and again[3] != rows[3]
    kept_again = json.loads((tmp_path / "docs" / "claims-results.json").read_text())["groups"]
    assert len(kept_again) == 1 and kept_again[0] != kept[0]  # replaced, not added
    before = readme.read_text()
    fig4_folder(tmp_path / "f4", range(5), dict.fromkeys(METHODS, 1.0))
    rc, out, err = _run([str(tmp_path / "f4"), "--readme", str(readme), "--add"], capsys)
    assert rc != 0 and "score the paper's claims" in err and len(err.strip().splitlines()) == 1
    assert readme.read_text() == before
    rc, out, err = _run([str(tmp_path / "e"), "--add"], capsys)
    assert rc != 0 and "--add needs --readme" in err


def test_a_wargus_evaluation_is_labelled_by_its_grid(tmp_path):
    for k in range(5):
        folder = eval_folder(tmp_path / "w" / f"seed{k}", k, {"averaging": 1.0}, "train")
        cfg = {"seed": k, "family": "wargus", "env": {"wargus": {"size": 64}}}
        save_checkpoint(folder / "bundle.pt", make_bundle(cfg, models={}))
        m = json.loads((folder / "metrics.json").read_text())
        m["family"] = "wargus"
        (folder / "metrics.json").write_text(json.dumps(m))
    (group,) = report_folders.collect([str(tmp_path / "w")])
    assert group.label.startswith("eval wargus 64x64 --test train")


def test_an_evaluation_of_a_named_layout_is_labelled_by_it(tmp_path):
    """Whole-column windy's rows are not the default layout's: added in separate runs (``--add``)
    their labels still tell them apart; the default layout adds nothing."""
    for layout in ("default", "whole_column_windy"):
        for k in range(5):
            folder = eval_folder(tmp_path / layout / f"seed{k}", k, {"averaging": 1.0}, "train")
            cfg = {"seed": k, "family": "windy", "env": {"layout": layout}}
            save_checkpoint(folder / "bundle.pt", make_bundle(cfg, models={}))
    (default,) = report_folders.collect([str(tmp_path / "default")])
    (column,) = report_folders.collect([str(tmp_path / "whole_column_windy")])
    assert default.label.startswith("eval windy --test train")
    assert column.label.startswith("eval windy whole_column_windy --test train")


def methods_folder(
    folder: Path,
    seed: int,
    family: str,
    test: str,
    returns: dict,
    regret: dict | None = None,
    frames: int = 50_000,
) -> Path:
    """A one-point ``taskvar eval`` folder of training seed ``seed``: method ``m`` returns
    ``returns[m] + 0.01 * seed``; with ``regret``, each method's regret to the exact optimum
    (``regret[m] - 0.01 * seed``), the baselines' marked as sampled."""
    ckpt = folder / "bundle.pt"
    folder.mkdir(parents=True, exist_ok=True)
    cfg = {"seed": seed, "family": family, "train": {"total_frames": frames}}
    save_checkpoint(ckpt, make_bundle(cfg, models={}))
    methods = {}
    for m, v in returns.items():
        methods[m] = {"mean_return": v + 0.01 * seed}
        if regret is not None:
            methods[m]["regret_mean"] = regret[m] - 0.01 * seed
            if m in ("recurrent", "informed"):
                methods[m]["regret_sampled"] = True
    metrics = {
        "experiment": "eval",
        "checkpoint": str(ckpt),
        "family": family,
        "test": test,
        "shifts": [],
        "methods": list(returns),
        "episodes": 100,
        "points": [{"shift": "", "methods": methods}],
    }
    return _write(folder, metrics, None)


WINDY = {
    "averaging": -5.0,
    "options": -5.0,
    "interruption": -7.0,
    "recurrent": -6.0,
    "informed": -4.0,
}
WINDY_REGRET = {m: -4.0 - v for m, v in WINDY.items()}  # to the optimum, -4.0
WARGUS = {"averaging": 2.0, "hierarchy": 2.1, "recurrent": 3.0, "informed": 4.0}


def _block(readme: Path) -> str:
    return readme.read_text().split(START)[1].split(END)[0]


def _table(block: str, family: str) -> list[str]:
    """The lines of ``family``'s table in a Results block."""
    lines = block.split(f"**{family}**:")[1].strip().splitlines()[2:]  # its heading, a blank line
    return lines[: next((i for i, line in enumerate(lines) if not line.startswith("|")), None)]


@pytest.mark.slow  # ~10 s: three groups' bootstraps, twice
def test_results_at_a_glance_follow_the_per_seed_numbers(tmp_path, capsys):
    """Per family one table (methods as columns, a row per group, mean [95% CI] over seeds, the
    the best mean of those that do not see the instance bold, a mark on every method not
    separated from it; informed never), and the regret figure's data: to the exact optimum where the results have it
    (the baselines' from sampled returns), to informed elsewhere, none without either."""
    for k in range(5):
        methods_folder(tmp_path / "windy" / f"seed{k}", k, "windy", "train", WINDY, WINDY_REGRET)
        methods_folder(tmp_path / "wargus" / f"seed{k}", k, "wargus", "heldout", WARGUS)
        methods_folder(
            tmp_path / "plain" / f"seed{k}", k, "wargus", "train", WARGUS | {"informed": 0}
        )
    plain = [tmp_path / "plain" / f"seed{k}" / "metrics.json" for k in range(5)]
    for path in plain:  # a group without informed: in the tables only
        m = json.loads(path.read_text())
        m["methods"] = ["averaging", "hierarchy"]
        m["points"][0]["methods"] = {
            k: v for k, v in m["points"][0]["methods"].items() if k in m["methods"]
        }
        path.write_text(json.dumps(m))
    readme = tmp_path / "README.md"
    readme.write_text(README)
    out = tmp_path / "docs" / "claims.md"
    dirs = [str(tmp_path / d) for d in ("windy", "wargus", "plain")]
    rc, _, err = _run([*dirs, "--out", str(out), "--readme", str(readme)], capsys)
    assert rc == 0, err
    block = _block(readme)
    assert block.strip().startswith("![Regret per method and family](docs/img/claims-results.png)")
    png = tmp_path / "docs" / "img" / "claims-results.png"
    assert png.is_file() and report._ours_png(png)
    head, _, row = _table(block, "windy")
    assert head == (
        "| results | budget, seeds | averaging | options | interruption | recurrent | informed |"
    )
    cells = [c.strip() for c in row.strip("|").split("|")]
    want = np.mean([-5.0 + 0.01 * k for k in range(5)])  # the per-seed numbers' own mean
    assert cells[0] == "train" and cells[1] == "50k frames, 5"
    assert cells[2].startswith(f"**{want:.2f} [")  # the best mean: bold (the first of a tie)
    assert cells[3] == f"{cells[2].strip('*')} {glance.TIE_MARK}"  # not separated: the mark
    assert not cells[4].startswith("**") and not cells[5].startswith("**")  # behind, CIs apart
    assert glance.TIE_MARK not in cells[4] + cells[5]
    assert cells[6].startswith(f"{want + 1:.2f} [")  # informed: highest, never marked
    assert glance.NO_CEILING not in cells[6]  # its own train row validates it: a ceiling
    _, _, wargus, plain_row = _table(block, "wargus")
    wargus_cells = [c.strip() for c in wargus.strip("|").split("|")]
    assert wargus_cells[0] == "heldout" and wargus_cells[4].startswith("**3.02 [")
    assert wargus_cells[-1].endswith(f"({glance.NO_CEILING})")  # no train row: the gate never ran
    assert not wargus_cells[2].startswith("**") and not wargus_cells[5].startswith("**")
    assert plain_row.split("|")[-2].strip() == "-"  # informed not evaluated there
    groups = json.loads((tmp_path / "docs" / "claims-results.json").read_text())["groups"]
    windy, wargus_group, plain_group = groups
    assert windy["regret"]["reference"] == glance.EXACT
    assert windy["regret"]["methods"]["averaging"]["mean"] == pytest.approx(1.0 - 0.02)
    assert windy["regret"]["methods"]["recurrent"]["sampled"]
    assert not windy["regret"]["methods"]["averaging"]["sampled"]
    assert wargus_group["regret"]["reference"] == glance.CEILING
    assert wargus_group["regret"]["methods"]["recurrent"]["mean"] == pytest.approx(1.0)
    assert "informed" not in wargus_group["regret"]["methods"]
    assert plain_group["regret"] is None and plain_group["best"] == "hierarchy"
    assert plain_group["not_separated"] == [] and plain_group["separation"] == "paired"
    assert glance.LEGEND in block
    details = glance.details_of(block)
    assert details.count("| eval ") == 3 and "<details>" in block and "</details>" in block
    page = out.read_text()
    assert (
        "## Every result" in page
        and "![regret per method and family](img/claims-results.png)" in page
    )
    every = page.split("## Every result")[1].splitlines()
    row = next(line for line in every if line.startswith("| eval windy --test train |"))
    assert row.endswith("| - |")  # no verdict: nothing on the claims page to link


@pytest.mark.slow  # ~8 s
def test_add_redraws_the_tables_from_every_kept_summary(tmp_path, capsys):
    for k in range(5):
        methods_folder(tmp_path / "windy" / f"seed{k}", k, "windy", "train", WINDY, WINDY_REGRET)
        methods_folder(tmp_path / "wargus" / f"seed{k}", k, "wargus", "heldout", WARGUS)
    readme = tmp_path / "README.md"
    readme.write_text(README)
    out = tmp_path / "docs" / "claims.md"
    assert (
        _run([str(tmp_path / "windy"), "--out", str(out), "--readme", str(readme)], capsys)[0] == 0
    )
    assert "**wargus**" not in _block(readme)
    rc, _, err = _run([str(tmp_path / "wargus"), "--readme", str(readme), "--add"], capsys)
    assert rc == 0, err
    block = _block(readme)
    assert "**windy**" in block and "**wargus**" in block and "in no table above" not in block
    assert glance.details_of(block).count("| eval ") == 2
    groups = json.loads((tmp_path / "docs" / "claims-results.json").read_text())["groups"]
    assert [g["family"] for g in groups] == ["windy", "wargus"]


def test_a_foreign_results_file_is_refused_and_nothing_written(tmp_path, capsys):
    for k in range(5):
        fig2_folder(tmp_path / "fig2" / f"seed{k}", k, no_worse=0.9, better=0.1)
    readme = tmp_path / "README.md"
    readme.write_text(README)
    (tmp_path / "docs").mkdir()
    foreign = tmp_path / "docs" / "claims-results.json"
    foreign.write_text('{"mine": 1}')
    out = tmp_path / "docs" / "claims.md"
    rc, _, err = _run([str(tmp_path / "fig2"), "--out", str(out), "--readme", str(readme)], capsys)
    assert rc == 2 and "was not written by taskvar report" in err
    assert len(err.strip().splitlines()) == 1
    assert (
        readme.read_text() == README and not out.exists() and foreign.read_text() == '{"mine": 1}'
    )


def test_row_names_and_budgets_are_short():
    label = "eval windy --test heldout --shift env.instances.p=0.0,0.25,0.5,0.75,1.0"
    assert glance.row_name(label, "windy") == "heldout, shift p (5 points)"
    assert glance.row_name("eval wargus 64x64 --test heldout", "wargus") == "64x64 heldout"
    assert glance.row_name("eval windy --test train (env.layout=default)", "windy") == (
        "train (env.layout=default)"
    )
    assert [glance.frames_text(n) for n in (50_000, 5_000_000, 10_240, 300_000)] == [
        "50k frames",
        "5M frames",
        "10240 frames",
        "300k frames",
    ]


def test_a_baseline_on_its_own_budget_is_named_in_the_budget_column(tmp_path):
    """A baseline trained on another budget than the heads (``metrics.json``'s
    ``baseline_frames``, written by ``taskvar eval``) is named beside the heads' budget."""
    for k in range(5):
        folder = methods_folder(
            tmp_path / "t" / f"seed{k}", k, "windy", "train", WINDY, frames=300_000
        )
        m = json.loads((folder / "metrics.json").read_text())
        m["baseline_frames"] = {"recurrent": 1_200_000, "informed": 300_000}
        (folder / "metrics.json").write_text(json.dumps(m))
    (summary,) = report.build_report([str(tmp_path / "t")], 100).summaries
    assert summary["budget"] == "300k frames (recurrent 1.2M)"


def test_drop_removes_the_rows_of_a_superseded_config(tmp_path):
    """``--drop DIGEST`` removes that config's rows and kept summaries; a digest naming no row
    is a one-line error listing the digests there are."""
    head = report.results_table(report_claims.Report([], [], [], [], 100)).splitlines()
    rows = [
        "| eval taxi --test train | old | 5 | 047e3af1 | - ([claims](docs/claims.md)) |",
        "| eval windy --test train | kept | 5 | 87219546 | - ([claims](docs/claims.md)) |",
    ]
    kept = [{"label": "eval taxi --test train", "digest": "047e3af1"}]
    block, summaries = report.drop_rows("\n".join([*head, *rows]), kept, ["047e3af1"])
    assert block.splitlines() == [*head, rows[1]] and summaries == []
    with pytest.raises(report.ReportError, match="--drop deadbeef: no Results row .* 047e3af1"):
        report.drop_rows("\n".join([*head, *rows]), kept, ["deadbeef"])


def test_a_figure2_folder_is_labelled_by_its_layout_where_either_version_wrote_it(tmp_path):
    """The layout sits in ``env.windy`` since the restructuring, at ``env.*`` before: the label
    reads either (it read ``layout None`` from today's folders)."""
    for k in range(5):
        fig2_folder(tmp_path / "old" / f"seed{k}", k, 0.9, 0.1, layout="middle_exits")
        folder = fig2_folder(tmp_path / "new" / f"seed{k}", k, 0.9, 0.1)
        cfg = yaml.safe_load((folder / "config.yaml").read_text())
        cfg["env"] = {"windy": {"layout": "middle_exits"}}
        (folder / "config.yaml").write_text(yaml.safe_dump(cfg))
    for name in ("old", "new"):
        (group,) = report_folders.collect([str(tmp_path / name)])
        assert group.label == "windy-fig2, layout middle_exits"
