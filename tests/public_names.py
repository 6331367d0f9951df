"""Which names of ``taskvar_torch`` a piece of code takes, read from its import statements (AST):
what tests/test_public_interface.py and tests/study/test_study_boundary.py check.

A name ``N`` taken from module ``M`` is *public* when no part of ``M`` and not ``N`` starts with an
underscore and ``M`` declares ``N`` in its ``__all__``, or, where ``M`` has no ``__all__``, defines
``N`` itself (PEP 8: a name ``M`` merely imports is its implementation detail).
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "taskvar_torch"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
"""Every module of the package: dotted name -> file."""


def public_names(module: str) -> set[str]:
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


def taken_names(source: str) -> list[tuple[int, str, str]]:
    """``(line, module, name)`` of every module (name ``""``) and name of ``taskvar_torch`` that
    ``source`` imports or reads off an imported module."""
    tree = ast.parse(source)
    modules: dict[str, str] = {}  # local name -> module it stands for
    taken: list[tuple[int, str, str]] = []
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
    return taken


def private_uses(source: str, where: str) -> list[str]:
    """Every non-public name of ``taskvar_torch`` that ``source`` (shown as ``where``) takes."""
    hits = []
    for line, module, name in taken_names(source):
        at = f"{where}:{line}: {module}{'.' + name if name else ''}"
        if any(p.startswith("_") for p in module.split(".")) or name.startswith("_"):
            hits.append(f"{at} is private")
        elif module not in MODULES:
            hits.append(f"{at}: no such module")
        elif name and name not in public_names(module):
            hits.append(f"{at} is not in its __all__ (or not defined there)")
    return hits


def imported_modules(path: Path) -> list[tuple[int, str]]:
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
