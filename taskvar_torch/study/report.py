"""``taskvar report``: the paper's claims and the Results tables, regenerated from results folders
(docs/report.md#taskvar-report is its guide, docs/claims.md its output).

This module writes the claims page, the Results block (docs/results.md or a page of its own,
:func:`target_page`), the summaries beside the claims page and the figures, atomically; bad input
is one line (:class:`ReportError`) and nothing is written. Folders are read by
:mod:`.report_folders`, claims scored by :mod:`.report_claims`.
"""

from __future__ import annotations

import io
import json
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from taskvar_torch.io import atomic_write
from taskvar_torch.run_folder import ResultsFolder, check_out_path
from taskvar_torch.study import aggregate
from taskvar_torch.study import report_results as at_a_glance
from taskvar_torch.study.report_claims import CLAIMS, RULES, Report, build_report
from taskvar_torch.study.report_folders import (
    MIN_SEEDS,
    ReportError,
    check_commits,
    commit_text,
    read_json,
)

README_START = "<!-- report:results:start -->"
README_END = "<!-- report:results:end -->"
GENERATED = "<!-- written by taskvar report: rerun it rather than editing this page -->"
"""First line of the claims page; a file without it is not replaced (unless ``overwrite``)."""
PNG_SOFTWARE = "taskvar report"
"""The PNG's ``Software`` text: a profile PNG without it is not replaced."""


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def claims_markdown(
    report: Report,
    png_name: str | None,
    dirs: Sequence[str],
    results_png: str | None = None,
    self_link: str = "claims.md",
) -> str:
    """The claims page; ``results_png``: the regret figure beside it, shown with the table of
    every result (``self_link``: the page's own file name, where that table's rows link)."""
    lines = [
        GENERATED,
        "# The paper's claims against ours",
        "",
        f"Written by `taskvar report {' '.join(dirs)}`. {_scope(report)}, aggregated with "
        "rliable: interquartile mean (IQM) and mean with stratified-bootstrap 95% CIs "
        f"({report.reps} resamples, seeded), paired per seed where the methods played the same "
        "episodes; probability of improvement over the averaging policy as rliable defines it "
        "(unpaired).",
        "",
        "| claim | paper | results | ours (mean [95% CI]) | verdict | why |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for key, (title, paper) in CLAIMS.items():
        got = [c for c in report.claims if c.key == key]
        if not got:
            lines.append(f"| {title} | {paper} | none given | - | not measured | no results |")
        for c in got:
            lines.append(
                f"| {_cell(title)} | {_cell(paper)} | {_cell(c.group)} | {_cell(c.ours)} | "
                f"**{c.verdict}** | {_cell(c.reason)} |"
            )
    lines += ["", "## How the verdicts are decided", ""]
    lines += [f"- {CLAIMS[k][0]}: {v}." for k, v in RULES.items()]
    lines += ["", "## Details", ""]
    for c in report.claims:
        lines.append(f"**{CLAIMS[c.key][0]}, {c.group}**")
        lines.append("")
        lines += [f"- {d}" for d in c.details]
        lines.append("")
    lines += ["## Results read", ""]
    lines.append("| results | kind | training seeds | config | commit | folders |")
    lines.append("| --- | --- | --- | --- | --- | --- |")
    for g in report.groups:
        folders = ", ".join(f"`{r.path}`" for r in g.results)
        commits = ", ".join(dict.fromkeys(commit_text(r.commit) for r in g.results))
        lines.append(
            f"| {_cell(g.label)} | {g.kind} | {', '.join(map(str, g.seeds))} | {g.digest} | "
            f"{commits} | {folders} |"
        )
    if png_name:
        lines += ["", f"![performance profiles]({png_name})", ""]
        lines.append(
            "Performance profiles (rliable's score distributions): the fraction of each method's "
            "scores above tau, with 95% bootstrap bands."
        )
    lines += ["", "## Every result", "", results_table(report, self_link)]
    if results_png:
        lines += ["", f"![regret per method and family]({results_png})", ""]
        lines.append(at_a_glance.FIGURE_CAPTION)
    return "\n".join(lines) + "\n"


def _scope(report: Report) -> str:
    """What every figure is over and on: training seeds (an exploratory group's fewer), and each
    result's own test distribution: the sealed held-out instances only where the results have
    them."""
    n = len(report.groups)
    sealed = sum(g.sealed for g in report.groups)
    few = sum(g.exploratory for g in report.groups)
    seeds = f"over training seeds (>= {MIN_SEEDS} for a claim" + (
        f"; {few} exploratory result(s) of fewer seeds, labelled, score none)" if few else ")"
    )
    held = (
        "the sealed held-out instances (`families.HELDOUT_SEED`: no design choice was made on them)"
    )
    if sealed == n:
        on = f"on {held}"
    elif sealed == 0:
        on = (
            "on each family's own test distributions, named in each row (none of these results "
            "has a sealed held-out split, so they score none of the paper's claims)"
        )
    else:
        on = (
            f"on {held} for {sealed} of the {n} results, on their family's own test distributions "
            "(named in each row) for the others; claims are scored on the sealed instances only"
        )
    return f"Every figure is {seeds}, {on}"


SHORT = {"fig2": "Fig. 2", "fig4_order": "order", "fig4_speed": "speed", "premise": "§3.2"}


def results_table(report: Report, claims_link: str | None = None) -> str:
    """The table of every result (in the Results block between :data:`README_START` and
    :data:`README_END`); ``claims_link``: the claims page, relative to the page holding the
    table, linked from the rows that have a verdict there (``None``: no claims page is written,
    as with ``--add``, so no row links one)."""
    lines = [
        "| experiment | headline (IQM or mean [95% CI] over seeds, on the test each row names; "
        "held-out: the sealed instances) | training seeds | config | claims |",
        "| --- | --- | --- | --- | --- |",
    ]
    for label, headline, n, digest in report.rows:
        verdicts = ", ".join(
            f"{SHORT[c.key]} {c.verdict}" for c in report.claims if c.group == label
        )
        link = f" ([claims]({claims_link}))" if verdicts and claims_link else ""
        lines.append(
            f"| {_cell(label)} | {_cell(headline)} | {n} | {digest} | {verdicts or '-'}{link} |"
        )
    return "\n".join(lines)


def replace_block(text: str, block: str, where: str) -> str:
    """``text`` with what lies between the marker comments replaced by ``block``."""
    if text.count(README_START) != 1 or text.count(README_END) != 1:
        raise ReportError(
            f"{where} must hold {README_START} and {README_END} once each (the Results table "
            "goes between them)"
        )
    a = text.index(README_START) + len(README_START)
    b = text.index(README_END)
    if b < a:
        raise ReportError(f"{where}: {README_END} comes before {README_START}")
    return text[:a] + "\n" + block + "\n" + text[b:]


RESULTS_PAGE = "results.md"
"""The page of its own, beside the claims page, that takes the Results where the page given
(``--page``/``--readme``) exists without the marker comments."""


def own_page() -> str:
    """A Results page of ``taskvar report``'s own: its first line :data:`GENERATED`, a title,
    one line on what it holds, and the markers the Results block goes between."""
    return (
        f"{GENERATED}\n# Results\n\nWritten by `taskvar report` (docs/report.md): every results "
        "group over its training seeds, each on the test distribution its row names; rerun it, or "
        f"`taskvar report --add`, rather than editing between the markers.\n\n{README_START}\n"
        f"{README_END}\n"
    )


def _read_page(path: Path, flag: str) -> str | None:
    """``path``'s text, ``None`` where there is no such file."""
    if not path.exists():
        return None
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        why = getattr(e, "strerror", None) or "not UTF-8 text"
        raise ReportError(f"{flag} {str(path)!r} cannot be read ({why})") from None


def _has_markers(text: str) -> bool:
    return README_START in text or README_END in text


def target_page(
    page: str | os.PathLike, beside: str | os.PathLike, flag: str = "--page"
) -> tuple[Path, str, str | None]:
    """Where the Results block goes, checked before anything is computed: ``(path, its text with
    the markers, a note for stdout or None)``. ``page`` itself where it holds both markers (a
    README or docs page); where it does not exist, or is a page ``taskvar report`` wrote, a page of
    its own there (:func:`own_page`); where it is someone else's page without markers, the page
    :data:`RESULTS_PAGE` beside the claims page ``beside`` instead, said in the note. Markers
    present but broken, or no page left to write, are one line (:class:`ReportError`)."""
    page = Path(page)
    text = _read_page(page, flag)
    if text is not None and _has_markers(text):
        replace_block(text, "", str(page))  # both markers, once each, in order
        return page, text, None
    if text is None or _ours_md(page):
        return (
            page,
            own_page(),
            f"{page}: no Results markers there, wrote a Results page of its own",
        )
    other = Path(beside).with_name(RESULTS_PAGE)
    note = (
        f"{page} has no Results markers ({README_START} ... {README_END}): wrote the Results to "
        f"{other} instead"
    )
    if other.resolve() == Path(beside).resolve():
        raise ReportError(
            f"{flag} {str(page)!r} has no Results markers and the page beside the claims page is "
            f"the claims page itself; give {flag} a page with the markers"
        )
    found = _read_page(other, flag)
    if found is not None and _has_markers(found):
        replace_block(found, "", str(other))
        return other, found, note
    if found is None or _ours_md(other):
        return other, own_page(), note
    raise ReportError(
        f"{flag} {str(page)!r} has no {README_START} and {README_END} markers, and {str(other)!r} "
        "(where the Results would go instead) was not written by taskvar report; add the markers "
        f"to one of them, or give another {flag}"
    )


def _row_key(line: str) -> tuple[str, str] | None:
    """A Results row's (experiment label, config digest): the cells a row is known by."""
    cells = [c.strip() for c in re.split(r"(?<!\\)\|", line.strip())]
    if len(cells) < 6 or cells[1] in ("experiment", "---"):
        return None
    return cells[1], cells[4]


def merge_rows(block: str, table: str) -> str:
    """``table``'s rows merged into the Results table ``block``: a row of the same experiment
    and config replaces the old one where it stands, new ones go last, the others are kept."""
    new = {_row_key(line): line for line in table.splitlines()[2:]}
    head = table.splitlines()[:2]
    kept = []
    for line in block.strip().splitlines():
        key = _row_key(line)
        if key is None:
            continue
        kept.append(new.pop(key, line))
    return "\n".join(head + kept + list(new.values()))


def results_files(claims: str | os.PathLike) -> tuple[Path, Path]:
    """Beside the claims page ``claims``: the regret figure ``img/<stem>-results.png`` and the
    summaries behind it and the compact tables, ``<stem>-results.json``."""
    claims = Path(claims)
    return claims.parent / "img" / f"{claims.stem}-results.png", claims.with_name(
        f"{claims.stem}-results.json"
    )


def _read_summaries(path: Path) -> list[dict[str, Any]]:
    """The summaries ``taskvar report`` kept in ``path`` (none where there is no file)."""
    if not path.exists():
        return []
    data = read_json(path)
    if data.get("written_by") != PNG_SOFTWARE:
        raise ReportError(f"{str(path)!r} exists and was not written by taskvar report; move it")
    return list(data.get("groups", []))


def _summaries_json(summaries: Sequence[dict[str, Any]]) -> bytes:
    data = {"written_by": PNG_SOFTWARE, "groups": list(summaries)}
    return (json.dumps(data, indent=1) + "\n").encode()


def _results_block(
    summaries: Sequence[dict[str, Any]], details: str, png: Path | None, readme: str | os.PathLike
) -> str:
    """The Results block: the figure (linked from the page), the compact tables, the
    table of every result ``details`` folded away, and a note on rows without a summary."""
    known = {(s["label"], s["digest"]) for s in summaries}
    keys = [_row_key(line) for line in details.splitlines()]
    missing = sum(1 for k in keys if k is not None and k not in known)
    figure = None if png is None else Path(os.path.relpath(png, Path(readme).parent)).as_posix()
    return at_a_glance.results_block(summaries, details, figure, missing)


def drop_rows(block: str, summaries: list[dict[str, Any]], digests: Sequence[str]):
    """The Results table ``block`` and the kept ``summaries`` without the rows of the config
    digests ``digests`` (``taskvar report --add --drop DIGEST``: results a rerun supersedes);
    a digest that names no row is a one-line :class:`ReportError` listing those there are."""
    lines = block.strip().splitlines()
    present = {k[1] for k in map(_row_key, lines) if k is not None}
    present |= {s["digest"] for s in summaries}
    missing = [d for d in digests if d not in present]
    if missing:
        raise ReportError(
            f"--drop {missing[0]}: no Results row has that config digest; the rows have "
            f"{', '.join(sorted(present)) or 'none'}"
        )
    gone = set(digests)
    kept = [line for line in lines if (_row_key(line) or ("", ""))[1] not in gone]
    return "\n".join(kept), [s for s in summaries if s["digest"] not in gone]


def default_claims(page: str | os.PathLike) -> Path:
    """The claims page ``taskvar report --add`` keeps its summaries beside where no ``--out`` is
    given: ``claims.md`` beside the page where there is one or the page lies in ``docs/``
    (``docs/results.md``), else ``docs/claims.md`` under the page's folder (a README's)."""
    page = Path(page)
    here = page.with_name("claims.md")
    if here.resolve() != page.resolve() and (here.is_file() or page.parent.name == "docs"):
        return here
    return page.parent / "docs" / "claims.md"


def add_rows(
    dirs: Sequence[str],
    readme: str | os.PathLike,
    claims: str | os.PathLike | None = None,
    reps: int = aggregate.REPS,
    drop: Sequence[str] = (),
    mixed_commits: bool = False,
) -> tuple[list[Path], Report]:
    """``taskvar report --add``: add these folders' rows to the Results of the page ``readme``
    (:func:`target_page`), keeping the rows of results not given and the summaries beside
    ``claims``; ``drop``: config digests whose rows go. Refused where a folder scores one of the
    paper's claims (then rewrite the claims page from every folder) and, unless ``mixed_commits``,
    for results of different commits (docs/report.md).
    """
    if int(reps) < 100:
        raise ReportError(f"--reps must be >= 100 bootstrap resamples, got {reps}")
    claims_path = default_claims(readme) if claims is None else Path(claims)
    _refuse_inside_results(dirs, readme, "--page")
    readme, text, note = target_page(readme, claims_path)
    _refuse_inside_results(dirs, readme, "--page")
    if readme.resolve() == claims_path.resolve():
        raise ReportError(f"--page {str(readme)!r} is the claims page; give the Results page")
    png, data = results_files(claims_path)
    kept = _read_summaries(data)
    a = text.index(README_START) + len(README_START)
    old_rows, kept = drop_rows(at_a_glance.details_of(text[a : text.index(README_END)]), kept, drop)
    if png.exists() and not _ours_png(png):
        raise ReportError(
            f"{str(png)!r} exists and was not written by taskvar report; move it or rerun without "
            "--add and with --overwrite"
        )
    report = build_report(dirs, reps, mixed_commits)
    if report.scored:
        scored = sorted({c.group for c in report.scored})
        raise ReportError(
            f"--add: {'; '.join(scored)} score the paper's claims; rerun taskvar report with "
            "every results folder and --out docs/claims.md instead"
        )
    details = merge_rows(old_rows, results_table(report))  # no claims page: no link
    new = {(s["label"], s["digest"]): s for s in report.summaries}
    others = [s for s in kept if (s["label"], s["digest"]) not in new]
    check_commits(
        [(r.commit, str(r.path)) for g in report.groups for r in g.results[:1]]
        + [(s.get("commit"), f"the Results row {s['label']!r}") for s in others],
        mixed_commits,
    )
    summaries = [new.pop((s["label"], s["digest"]), s) for s in kept] + list(new.values())
    image = at_a_glance.results_png(summaries, PNG_SOFTWARE)
    block = _results_block(summaries, details, png if image is not None else None, readme)
    new_text = replace_block(text, block, str(readme)).encode()
    written = []
    data_bytes = _summaries_json(summaries)
    with ResultsFolder(readme.resolve().parent, staged=False, flag="--page"):
        if image is not None:
            written.append(atomic_write(png, lambda f: f.write(image)))
        written.append(atomic_write(data, lambda f: f.write(data_bytes)))
        written.append(atomic_write(readme, lambda f: f.write(new_text)))
    report.notes += [note] if note else []
    return written, report


def profile_png(report: Report, reps: int) -> bytes | None:
    """The performance profiles, one panel per group with methods, as PNG bytes."""
    panels = [p for p in report.profiles if p[1]]
    if not panels:
        return None
    from taskvar_torch.experiments.plots import pyplot

    plt = pyplot()
    fig, axes = plt.subplots(1, len(panels), figsize=(5.0 * len(panels), 3.6), squeeze=False)
    for ax, (title, scores, xlabel) in zip(axes[0], panels):
        allv = np.concatenate([np.asarray(v, dtype=float).ravel() for v in scores.values()])
        allv = allv[np.isfinite(allv)]
        lo, hi = (float(allv.min()), float(allv.max())) if allv.size else (0.0, 1.0)
        taus = np.linspace(lo, hi if hi > lo else lo + 1.0, 41)
        prof, cis = aggregate.performance_profile(scores, taus, reps=min(reps, 1000))
        aggregate.plot_performance_profiles(ax, prof, cis, taus, xlabel)
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, metadata={"Software": PNG_SOFTWARE})
    plt.close(fig)
    return buf.getvalue()


def _ours_md(path: Path) -> bool:
    try:
        with path.open(encoding="utf-8") as f:
            return f.readline().rstrip("\n") == GENERATED
    except (OSError, UnicodeDecodeError):
        return False


def _ours_png(path: Path) -> bool:
    try:
        from PIL import Image

        with Image.open(path) as im:
            return im.info.get("Software") == PNG_SOFTWARE
    except Exception:  # not an image, unreadable: not ours
        return False


def write_report(
    dirs: Sequence[str],
    out: str | os.PathLike,
    readme: str | os.PathLike | None = None,
    reps: int = aggregate.REPS,
    overwrite: bool = False,
    mixed_commits: bool = False,
) -> tuple[list[Path], Report]:
    """``taskvar report``: check everything, compute everything, then write the regret figure
    and the summaries behind it and the compact tables (:func:`results_files`), the claims page
    ``out``, its profile PNG (``img/<out stem>-profile.png`` beside it) and, with ``readme``
    (``--page``/``--readme``), the Results block of that page (:func:`target_page`: a page of
    its own where it has no markers). Results of different commits are refused unless
    ``mixed_commits`` (docs/report.md). Returns the files written and the report (its
    ``notes``: where the Results went, when not to ``readme``)."""
    out = check_out_path(out)
    _refuse_inside_results(dirs, out, "--out")
    note = None
    if readme is not None:
        _refuse_inside_results(dirs, readme, "--page")
    png = out.parent / "img" / f"{out.stem}-profile.png"
    results_png, data = results_files(out)
    if int(reps) < 100:
        raise ReportError(f"--reps must be >= 100 bootstrap resamples, got {reps}")
    if out.exists() and not overwrite and not _ours_md(out):
        raise ReportError(
            f"--out {str(out)!r} exists and was not written by taskvar report; choose another "
            "--out or pass --overwrite"
        )
    for path in (png, results_png):
        if path.exists() and not overwrite and not _ours_png(path):
            raise ReportError(
                f"{str(path)!r} exists and was not written by taskvar report; move it or pass "
                "--overwrite"
            )
    if not overwrite:
        _read_summaries(data)  # refused where it is someone else's
    readme_text = None
    if readme is not None:
        readme, readme_text, note = target_page(readme, out)
        _refuse_inside_results(dirs, readme, "--page")
        if readme.resolve() == out.resolve():
            raise ReportError(f"--page {str(readme)!r} is the claims page --out; give another")
    report = build_report(dirs, reps, mixed_commits)
    image = profile_png(report, reps)
    results_image = at_a_glance.results_png(report.summaries, PNG_SOFTWARE)
    rel = os.path.relpath(png, out.parent) if image is not None else None
    results_rel = (
        Path(os.path.relpath(results_png, out.parent)).as_posix()
        if results_image is not None
        else None
    )
    page = claims_markdown(report, rel, dirs, results_rel, out.name).encode()
    new_readme = None
    if readme_text is not None:
        details = results_table(report, Path(os.path.relpath(out, Path(readme).parent)).as_posix())
        block = _results_block(
            report.summaries, details, results_png if results_image is not None else None, readme
        )
        new_readme = replace_block(readme_text, block, str(readme)).encode()
    data_bytes = _summaries_json(report.summaries)
    written = []
    with ResultsFolder(out.parent, staged=False):  # one taskvar command at a time
        if image is not None:
            written.append(atomic_write(png, lambda f: f.write(image)))
        if results_image is not None:
            written.append(atomic_write(results_png, lambda f: f.write(results_image)))
        written.append(atomic_write(data, lambda f: f.write(data_bytes)))
        written.append(atomic_write(out, lambda f: f.write(page)))
        if new_readme is not None:
            Path(readme).parent.mkdir(parents=True, exist_ok=True)
            written.append(atomic_write(Path(readme), lambda f: f.write(new_readme)))
    report.notes += [note] if note else []
    return written, report


def _refuse_inside_results(dirs: Sequence[str], path: str | os.PathLike, flag: str) -> None:
    """A one-line :class:`ReportError` when ``path`` (a file the report writes) lies in one of
    the results folders ``dirs`` it reads."""
    target = Path(path).resolve()
    for d in dirs:
        if Path(d).resolve() in target.parents:
            raise ReportError(
                f"{flag} {str(path)!r} lies in the results folder {d!r} that taskvar report reads; "
                f"choose another {flag}"
            )


__all__ = [
    "drop_rows",
    "GENERATED",
    "PNG_SOFTWARE",
    "README_END",
    "README_START",
    "RESULTS_PAGE",
    "add_rows",
    "default_claims",
    "own_page",
    "target_page",
    "claims_markdown",
    "merge_rows",
    "replace_block",
    "results_files",
    "results_table",
    "write_report",
]
