"""Regenerate every Results row (docs/results.md) from scratch at one commit (``make results``;
docs/report.md).

Each row is a list of steps (``taskvar`` commands and ``scripts/evidence.py``), run in order into
``OUT/<row>/``; a step whose output is already there is skipped, so an interrupted run goes on
where it stopped. The commit is written to ``OUT/.commit`` at the start, and a run refuses an
``OUT`` made at another commit (or from a working tree with uncommitted changes to the package or
the configs): every row of the Results then names the same code. Last, ``taskvar report``
rewrites ``docs/claims.md`` and the Results block of ``docs/results.md`` (where ``taskvar report``
writes it since issue 57; the README links it) from these folders only.

Hours of CPU on the project's 2-core machine (measured per row in docs/report.md): run it in the
background, ``nohup make results > results.log &``; ``--list`` prints the plan with no work,
``--only ROW`` (repeatable) runs some rows, ``--no-report`` stops before the report.

Usage::

    python scripts/results.py --out results/regen [--list] [--only windy ...] [--no-report]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

EVIDENCE = [sys.executable, "scripts/evidence.py"]
TASKVAR = [sys.executable, "-m", "taskvar_torch.cli"]
SEEDS = 5
CLAIMS_PAGE = "docs/claims.md"
RESULTS_PAGE = "docs/results.md"
"""The page whose markers hold every Results row (the README links it, issue 57)."""
FIG4_RUNS = 10
"""Figure 4's repetitions: >= 10, so its verdicts do not flip between realisations of 5."""


@dataclass
class Step:
    """One command of a row and the file whose presence says it is done."""

    argv: list[str]
    done: str  # relative to OUT

    def shell(self) -> str:
        return " ".join(a if " " not in a else repr(a) for a in self.argv)


@dataclass
class Row:
    """A Results row group: its steps and the folders ``taskvar report`` reads."""

    name: str
    what: str
    steps: list[Step] = field(default_factory=list)
    reads: list[str] = field(default_factory=list)  # relative to OUT


def _evidence(name: str, config: str, tests: str, out: Path, *extra: str) -> Row:
    """A family's rows by ``scripts/evidence.py``: 5 training seeds, the baselines, every method
    on each named test."""
    d = out / name
    row = Row(name, f"{config}: {SEEDS} seeds, heads and baselines, tests {tests}")
    done = f"{name}/eval-{tests.split(',')[-1]}/seed{SEEDS - 1}/metrics.json"
    argv = [*EVIDENCE, config, "--seeds", str(SEEDS), "--tests", tests, "--out", str(d), *extra]
    row.steps.append(Step(argv, done))
    row.reads = [f"{name}/eval-{t}" for t in tests.split(",")]
    return row


def rows(out: Path) -> list[Row]:
    """Every Results row, in docs/results.md's order."""
    windy = _evidence("windy", "configs/windy.yaml", "train,south,heldout", out)
    for k in range(SEEDS):
        bundle = str(out / "windy" / "train" / f"seed{k}" / "final.pt")
        windy.steps.append(
            Step(
                [*TASKVAR, "experiment", "windy-fig2", "--checkpoint", bundle, "--no-progress"]
                + ["--out", str(out / "windy-fig2" / f"seed{k}")],
                f"windy-fig2/seed{k}/metrics.json",
            )
        )
        windy.steps.append(
            Step(
                [*TASKVAR, "eval", "--checkpoint", bundle, "--method", "all", "--test", "heldout"]
                + ["--shift", "env.instances.p=0.0,0.25,0.5,0.75,1.0", "--no-progress"]
                + ["--out", str(out / "windy-shift" / f"seed{k}")],
                f"windy-shift/seed{k}/metrics.json",
            )
        )
    windy.reads = ["windy-fig2", "windy-shift", *windy.reads]
    fig4 = Row("wargus-fig4", f"Figure 4, {FIG4_RUNS} repetitions x 500 trials")
    fig4.steps.append(
        Step(
            [*TASKVAR, "experiment", "wargus-fig4", f"experiment.runs={FIG4_RUNS}"]
            + ["--workers", "1", "--no-progress", "--out", str(out / "wargus-fig4")],
            "wargus-fig4/metrics.json",
        )
    )
    fig4.reads = ["wargus-fig4"]
    return [
        windy,
        _evidence("windy-whole-column", "configs/windy_whole_column.yaml", "train,south,heldout", out),
        fig4,
        _evidence("wargus-large", "configs/wargus_large.yaml", "train,heldout", out, "--episodes", "300"),
        _evidence("taxi", "configs/taxi.yaml", "train,heldout", out, "--exact"),
        _evidence("minigrid-doorkey", "configs/minigrid_doorkey.yaml", "train,heldout", out, "--episodes", "300"),
    ]  # fmt: skip


def report_steps(out: Path, chosen: list[Row]) -> list[Step]:
    """The report over every row's folders: the claims page and the Results block of
    :data:`RESULTS_PAGE`."""
    folders = [str(out / r) for row in chosen for r in row.reads]
    return [Step([*TASKVAR, "report", *folders, "--out", CLAIMS_PAGE, "--page", RESULTS_PAGE], "")]


def commit() -> tuple[str, bool]:
    """The checkout's commit and whether the package, configs or scripts differ from it."""
    head = subprocess.run(
        ["git", "rev-parse", "--short=7", "HEAD"], capture_output=True, text=True, check=True
    ).stdout.strip()
    dirty = subprocess.run(
        ["git", "status", "--porcelain", "--", "taskvar_torch", "configs", "scripts"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    return head, bool(dirty)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="results/regen", help="where every row's folders go")
    p.add_argument("--only", action="append", default=[], metavar="ROW", help="run these rows")
    p.add_argument("--list", action="store_true", help="print the plan and do nothing")
    p.add_argument("--no-report", action="store_true", help="stop before taskvar report")
    args = p.parse_args(argv)
    out = Path(args.out)
    every = rows(out)
    names = [r.name for r in every]
    bad = [n for n in args.only if n not in names]
    if bad:
        p.error(f"--only {bad[0]!r} is not a row; the rows: {', '.join(names)}")
    chosen = [r for r in every if not args.only or r.name in args.only]
    steps = [(r.name, s) for r in chosen for s in r.steps]
    if not args.no_report:
        steps += [("report", s) for s in report_steps(out, chosen)]
    if args.list:
        for row in chosen:
            print(f"{row.name}: {row.what}")
        for name, s in steps:
            state = "done" if s.done and (out / s.done).exists() else "to run"
            print(f"  [{name}, {state}] {s.shell()}")
        return 0
    head, dirty = commit()
    if dirty:
        raise SystemExit(
            "make results: taskvar_torch/, configs/ or scripts/ differ from the commit: commit "
            "first, so every row names the code it ran"
        )
    mark = out / ".commit"
    if mark.exists() and mark.read_text().strip() != head:
        raise SystemExit(
            f"make results: {out} holds rows of commit {mark.read_text().strip()}, this checkout "
            f"is {head}: give another --out, or remove it to start over"
        )
    out.mkdir(parents=True, exist_ok=True)
    mark.write_text(head + "\n")
    for i, (name, s) in enumerate(steps, 1):
        if s.done and (out / s.done).exists():
            print(f"[{i}/{len(steps)}] {name}: done, skipped", flush=True)
            continue
        print(f"[{i}/{len(steps)}] {name}: {s.shell()}", flush=True)
        subprocess.run(s.argv, check=True)
    print(f"every row at commit {head}: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
