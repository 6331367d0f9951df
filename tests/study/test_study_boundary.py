"""The study beside the library (issue 45): ``taskvar_torch/study/`` (scale, report, sweep),
``benchmarks/`` and ``scripts/`` read ``taskvar_torch`` only through its public names; the library
imports nothing from the study; no import circle. Read from the import statements (AST), lazy ones
inside functions too.

A name ``N`` taken from module ``M`` is *public* when no part of ``M`` and not ``N`` starts with an
underscore and ``M`` declares ``N`` in its ``__all__``, or, where ``M`` has no ``__all__``, defines
``N`` itself (PEP 8: a name ``M`` merely imports is its implementation detail).
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "taskvar_torch"
STUDY = PACKAGE / "study"
DISPATCH = set((PACKAGE / "cli").glob("*.py"))
"""Library modules allowed to import the study: the command line, which runs its commands."""


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in PACKAGE.rglob("*.py")}


def _public_names(module: str) -> set[str]:
    """``module``'s ``__all__``, or the names it defines where it declares none."""
    tree = ast.parse(MODULES[module].read_text())
    defined: set[str] = set()
    for node in tree.body:
        inner = node.body + node.orelse if isinstance(node, (ast.If, ast.Try)) else []
        for n in [node, *inner]:
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                defined.add(n.name)
            elif isinstance(n, (ast.Assign, ast.AnnAssign)):
                targets = n.targets if isinstance(n, ast.Assign) else [n.target]
                if any(isinstance(t, ast.Name) and t.id == "__all__" for t in targets):
                    return set(ast.literal_eval(n.value))
                defined |= {x.id for t in targets for x in ast.walk(t) if isinstance(x, ast.Name)}
    return {n for n in defined if not n.startswith("_")}


def _private_uses(path: Path) -> list[str]:
    """Every non-public name of ``taskvar_torch`` that ``path`` imports or reads off a module."""
    tree = ast.parse(path.read_text())
    modules: dict[str, str] = {}  # local name -> module it stands for
    taken: list[tuple[int, str, str]] = []  # (line, module, name)
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == "taskvar_torch":
                    taken.append((node.lineno, a.name, ""))
                    if a.asname or "." not in a.name:
                        modules[a.asname or a.name] = a.name
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module.split(".")[0] != "taskvar_torch":
                continue
            for a in node.names:
                sub = f"{node.module}.{a.name}"
                if sub in MODULES:
                    modules[a.asname or a.name] = sub
                    taken.append((node.lineno, sub, ""))
                else:
                    taken.append((node.lineno, node.module, a.name))
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            module = modules.get(node.value.id)
            if module and f"{module}.{node.attr}" not in MODULES:
                taken.append((node.lineno, module, node.attr))
    hits = []
    for line, module, name in taken:
        shown = path.relative_to(ROOT) if ROOT in path.parents else path
        where = f"{shown}:{line}: {module}{'.' + name if name else ''}"
        if any(p.startswith("_") for p in module.split(".")) or name.startswith("_"):
            hits.append(f"{where} is private")
        elif module not in MODULES:
            hits.append(f"{where}: no such module")
        elif name and name not in _public_names(module):
            hits.append(f"{where} is not in its __all__ (or not defined there)")
    return hits


def _imports(path: Path) -> list[tuple[int, str]]:
    """``(line, module)`` of every module of ``taskvar_torch`` that ``path`` imports (``from P
    import m`` counts as ``P.m`` where ``m`` is a module, else as ``P``)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names if a.name in MODULES]
        elif isinstance(node, ast.ImportFrom) and node.module in MODULES and node.level == 0:
            for a in node.names:
                sub = f"{node.module}.{a.name}"
                found.append((node.lineno, sub if sub in MODULES else node.module))
    return found


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
        for line, module in _imports(p)
        if module.startswith("taskvar_torch.study")
    ]
    assert not hits, hits


def test_no_import_circle():
    """The package's modules import one another without a circle (lazy imports counted)."""
    graph = {m: {n for _, n in _imports(p) if n != m} for m, p in MODULES.items()}
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
