"""``taskvar report`` and the commit of its results (issue 56): every results folder records the
code it was computed with (``metrics.json``'s ``code``), and results of different commits are
refused in one line naming both, unless ``--mixed-commits``."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
from test_report import README, _block, _run, eval_folder, fig2_folder  # tests/study/

from taskvar_torch.experiments.bundle_eval import eval_bundle
from taskvar_torch.experiments.results import code_version

A, B = "a" * 40, "b" * 40


def _at(folder: Path, commit: str | None) -> Path:
    """``folder``'s metrics.json as computed at ``commit`` (``None``: none recorded)."""
    path = folder / "metrics.json"
    m = json.loads(path.read_text())
    m["code"] = {"version": "0.1.0", "commit": commit}
    path.write_text(json.dumps(m))
    return folder


def _folders(tmp_path: Path, fig2: str | None, ev: str | None) -> list[str]:
    for k in range(5):
        _at(fig2_folder(tmp_path / "fig2" / f"seed{k}", k, no_worse=0.9, better=0.1), fig2)
        _at(eval_folder(tmp_path / "eval" / f"seed{k}", k, {"averaging": 50.0, "options": 5.0}), ev)
    return [str(tmp_path / "fig2"), str(tmp_path / "eval")]


@pytest.mark.slow  # ~2-3.5 s on a 2-core CPU: make test only
def test_results_of_two_commits_are_refused_naming_both(tmp_path, capsys):
    dirs = _folders(tmp_path, A, B)
    out = tmp_path / "docs" / "claims.md"
    rc, _, err = _run([*dirs, "--out", str(out)], capsys)
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    assert "aaaaaaa" in err and "bbbbbbb" in err and "--mixed-commits" in err
    assert not out.exists()
    rc, _, err = _run([*dirs, "--out", str(out), "--mixed-commits"], capsys)
    assert rc == 0, err
    page = out.read_text()
    assert "| aaaaaaa |" in page and "| bbbbbbb |" in page  # the Results read table names each


def test_one_commit_passes_and_a_seed_of_another_or_of_none_is_refused(tmp_path, capsys):
    dirs = _folders(tmp_path, A, A)
    out = tmp_path / "claims.md"
    assert _run([*dirs, "--out", str(out)], capsys)[0] == 0
    _at(tmp_path / "eval" / "seed3", f"{B}-dirty")
    rc, _, err = _run([*dirs, "--out", str(out), "--overwrite"], capsys)
    assert rc == 2 and "aaaaaaa" in err and "bbbbbbb-dirty" in err
    _at(tmp_path / "eval" / "seed3", None)  # an older folder: no commit recorded
    rc, _, err = _run([*dirs, "--out", str(out), "--overwrite"], capsys)
    assert rc == 2 and "no recorded commit" in err and len(err.strip().splitlines()) == 1


def test_add_refuses_rows_of_another_commit_than_the_readme_rows(tmp_path, capsys):
    for k in range(5):
        _at(eval_folder(tmp_path / "one" / f"seed{k}", k, {"averaging": 1.0}, test="train"), A)
        _at(eval_folder(tmp_path / "two" / f"seed{k}", k, {"averaging": 2.0}, test="south"), B)
    readme = tmp_path / "README.md"
    readme.write_text(README)
    args = ["--readme", str(readme), "--add"]
    assert _run([str(tmp_path / "one"), *args], capsys)[0] == 0
    before = readme.read_text()
    rc, _, err = _run([str(tmp_path / "two"), *args], capsys)
    assert rc == 2 and "aaaaaaa" in err and "bbbbbbb" in err and readme.read_text() == before
    assert _run([str(tmp_path / "two"), *args, "--mixed-commits"], capsys)[0] == 0
    assert "south" in _block(readme)


def test_results_record_the_checkout_commit(windy_tiny_bundle, tmp_path):
    m = eval_bundle(windy_tiny_bundle, "averaging", "train", episodes=4, out_dir=tmp_path,
                    plots=False, progress=False)  # fmt: skip
    written = json.loads((tmp_path / "metrics.json").read_text())["code"]
    assert m["code"] == written == code_version()
    root = Path(__file__).resolve().parents[2]
    head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True,
                          text=True).stdout.strip()  # fmt: skip
    if head:  # a git checkout (an sdist has none: the commit is then None)
        assert written["commit"].removesuffix("-dirty") == head
