"""``taskvar report`` for a new user's results (issue 59, "Friction" and "No silent mistakes"):
fewer than five seeds make an exploratory table, labelled, with no claim; a page without the
marker comments gets the Results on a page of its own, said in one line; and a family without a
sealed held-out split is never described as played on one, nor linked to a claims page that
``--add`` never writes."""

from __future__ import annotations

from test_report import END, README, START, _block, _run, eval_folder, fig2_folder  # tests/study/

from taskvar_torch.study import report


def test_fewer_than_five_seeds_make_an_exploratory_table_and_no_claim(tmp_path, capsys):
    for k in range(3):
        fig2_folder(tmp_path / "fig2" / f"seed{k}", k, 0.99, 0.10)
    page = tmp_path / "docs" / "results.md"
    page.parent.mkdir()
    page.write_text(README)
    out = tmp_path / "docs" / "claims.md"
    rc, stdout, err = _run([str(tmp_path / "fig2"), "--out", str(out), "--page", str(page)], capsys)
    assert rc == 0, err  # refused before: "a claim needs >= 5"
    verdicts = [line for line in stdout.splitlines() if line.startswith("Figure 2")]
    assert len(verdicts) == 1 and ": not measured (exploratory: 3 seeds, no claims" in verdicts[0]
    claims = out.read_text()
    assert "**not measured**" in claims and "**reproduced**" not in claims
    assert "1 exploratory result(s) of fewer seeds, labelled, score none" in claims
    block = _block(page)
    assert "| Figure 2 protocol, layout default | -, 3 (exploratory: 3 seeds, no claims) |" in block
    row = next(line for line in block.splitlines() if line.startswith("| windy-fig2"))
    assert "| exploratory: 3 seeds, no claims; interruption no worse" in row
    assert row.endswith("| Fig. 2 not measured ([claims](claims.md)) |")
    for k in range(3, 5):  # five seeds: a claim again
        fig2_folder(tmp_path / "fig2" / f"seed{k}", k, 0.99, 0.10)
    rc, stdout, err = _run([str(tmp_path / "fig2"), "--out", str(out), "--page", str(page)], capsys)
    assert rc == 0 and ": reproduced" in stdout and "exploratory" not in _block(page), err


def test_a_page_without_markers_gets_a_results_page_of_its_own(tmp_path, capsys):
    for k in range(5):
        fig2_folder(tmp_path / "fig2" / f"seed{k}", k, 0.99, 0.10)
        eval_folder(tmp_path / "e" / f"seed{k}", k, {"averaging": 1.0, "options": 2.0}, "train")
    readme = tmp_path / "README.md"
    readme.write_text("# x\n\nno markers here\n")
    out = tmp_path / "docs" / "claims.md"
    argv = [str(tmp_path / "fig2"), "--out", str(out), "--readme", str(readme)]
    rc, stdout, err = _run(argv, capsys)
    assert rc == 0, err  # refused before: "must hold <!-- report:results:start --> ..."
    own = tmp_path / "docs" / report.RESULTS_PAGE
    assert readme.read_text() == "# x\n\nno markers here\n"  # the user's page: untouched
    notes = [line for line in stdout.splitlines() if "no Results markers" in line]
    assert len(notes) == 1 and str(readme) in notes[0] and str(own) in notes[0]
    text = own.read_text()
    assert text.startswith(report.GENERATED) and START in text and END in text
    assert "| windy-fig2, layout default |" in _block(own)
    assert "Fig. 2 reproduced ([claims](claims.md))" in _block(own)  # linked from the page
    rc, stdout, err = _run([str(tmp_path / "e"), "--readme", str(readme), "--add"], capsys)
    assert rc == 0 and "no Results markers" in stdout, err  # --add finds the same page
    assert "| eval windy --test train" in _block(own) and "| windy-fig2" in _block(own)
    fresh = tmp_path / "elsewhere" / "table.md"  # a --page that does not exist: written there
    rc, stdout, err = _run(
        [str(tmp_path / "e"), "--page", str(fresh), "--add", "--out", str(out)], capsys
    )
    assert rc == 0 and fresh.read_text().startswith(report.GENERATED), err
    assert f"{fresh}: no Results markers there, wrote a Results page of its own" in stdout
    own.write_text("# my own results notes\n")  # someone else's page there: refused, one line
    before = own.read_text()
    rc, _, err = _run(argv + ["--overwrite"], capsys)
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "not written by taskvar report" in err
    assert own.read_text() == before and readme.read_text() == "# x\n\nno markers here\n"


def test_a_family_without_a_sealed_split_is_not_called_held_out(tmp_path, capsys):
    """An outside family (the Gymnasium adapter's) names its tests after its instances and has
    no sealed seed: a test it calls ``heldout`` is its own, so no claim is scored on it, its
    page says so, and its rows, added with ``--add``, link no claims page."""
    for k in range(5):
        eval_folder(
            tmp_path / "own" / f"seed{k}",
            k,
            {"averaging": 2.0, "options": 0.5},  # a premise "reproduced" were it sealed
            test="heldout",
            family="pendulum_masses",
            sealed=False,
        )
    out = tmp_path / "docs" / "claims.md"
    page = tmp_path / "docs" / "results.md"
    rc, stdout, err = _run([str(tmp_path / "own"), "--out", str(out), "--page", str(page)], capsys)
    assert rc == 0, err
    assert "]: " not in stdout  # no claim scored
    claims = out.read_text()
    assert "on the sealed held-out instances" not in claims
    assert "on each family's own test distributions, named in each row (none" in claims
    assert "held-out instances unless" not in claims + _block(page)  # no header says otherwise
    assert "| §3.2: a capability is less affected by variability than the full task |" in claims
    assert "| none given | - | not measured |" in claims
    row = next(line for line in _block(page).splitlines() if line.startswith("| eval pendulum"))
    assert "(--test heldout, 3 point(s))" in row and "held-out," not in row
    assert row.endswith("| - |")  # no verdict: no link
    added = tmp_path / "added.md"
    added.write_text(README)
    rc, _, err = _run([str(tmp_path / "own"), "--page", str(added), "--add"], capsys)
    assert rc == 0, err
    rows = [line for line in _block(added).splitlines() if line.startswith("| eval pendulum")]
    assert len(rows) == 1 and "[claims]" not in rows[0]
