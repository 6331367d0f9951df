"""The study beside the library (issue 45): ``taskvar_torch/study/`` (scale, report, sweep),
``benchmarks/`` and ``scripts/`` read ``taskvar_torch`` only through its public names; the library
imports nothing from the study; no import circle. Read from the import statements (AST), lazy ones
inside functions too (what a public name is: tests/public_names.py).
"""

from __future__ import annotations

from pathlib import Path

from public_names import MODULES, PACKAGE, ROOT, imported_modules, private_uses

STUDY = PACKAGE / "study"
DISPATCH = set((PACKAGE / "cli").glob("*.py"))
"""Library modules allowed to import the study: the command line, which runs its commands."""


def _private_uses(path: Path) -> list[str]:
    shown = path.relative_to(ROOT) if ROOT in path.parents else path
    return private_uses(path.read_text(), str(shown))


def test_the_study_benchmarks_and_scripts_read_only_public_names():
    paths = [
        *STUDY.rglob("*.py"),
        *(ROOT / "benchmarks").glob("*.py"),
        *(ROOT / "scripts").glob("*.py"),
    ]
    assert len(paths) > 20
    hits = [h for p in sorted(paths) for h in _private_uses(p)]
    assert not hits, hits


def test_the_library_imports_nothing_from_the_study():
    hits = [
        f"{p.relative_to(ROOT)}:{line} imports {module}"
        for p in PACKAGE.rglob("*.py")
        if STUDY not in p.parents and p not in DISPATCH
        for line, module in imported_modules(p)
        if module.startswith("taskvar_torch.study")
    ]
    assert not hits, hits


def test_no_import_circle():
    """The package's modules import one another without a circle (lazy imports counted)."""
    graph = {m: {n for _, n in imported_modules(p) if n != m} for m, p in MODULES.items()}
    done: set[str] = set()
    path: list[str] = []

    def visit(m: str) -> list[str] | None:
        if m in path:
            return path[path.index(m) :] + [m]
        if m in done:
            return None
        path.append(m)
        for n in sorted(graph[m]):
            circle = visit(n)
            if circle:
                return circle
        path.pop()
        done.add(m)
        return None

    for m in sorted(graph):
        circle = visit(m)
        assert circle is None, " -> ".join(circle)


def test_the_public_name_rule_catches_each_kind_of_violation(tmp_path):
    """A private name, a name outside its module's ``__all__`` and a private attribute of an
    imported module are caught; public names pass."""
    probe = tmp_path / "probe.py"
    probe.write_text(
        "from taskvar_torch.experiments.plots import pyplot, save_figure\n"
        "from taskvar_torch.training import train, _resume_state\n"
        "from taskvar_torch.run_folder import ResultsFolder, remove_path\n"
        "from taskvar_torch import rng\n"
        "rng.MAX_SEED, rng._nope\n"
    )
    hits = [h.split(": ", 1)[1] for h in _private_uses(probe)]
    assert hits == [
        "taskvar_torch.training._resume_state is private",
        "taskvar_torch.run_folder.remove_path is not in its __all__ (or not defined there)",
        "taskvar_torch.rng._nope is private",
    ]
