"""The public interface (docs/design.md, Public interface): the code a reader copies -- the README's
and docs' Python blocks, the notebooks and examples/ -- takes from ``taskvar_torch`` only the public
modules below, and from each only its public names (tests/public_names.py); every other module is
internal, free to change. Read from the import statements (AST)."""

from __future__ import annotations

import ast
import json
import re

import pytest
from public_names import MODULES, ROOT, private_uses, taken_names

PUBLIC_MODULES = (
    "taskvar_torch",  # the front door: import taskvar_torch as tv
    "taskvar_torch.contract",  # the family contract and registry
    "taskvar_torch.families",  # the same names, handed on: the built-in families' package
    "taskvar_torch.families.*",  # a built-in family's package and its modules
    "taskvar_torch.family_check",
    "taskvar_torch.envs.batched",  # the base of a family's batched env
    "taskvar_torch.subtasks.base",  # the base of a family's subtasks
    "taskvar_torch.keys",  # the tensordict keys an env writes
    "taskvar_torch.rng",  # per-instance seeding
    "taskvar_torch.oracle.*",  # the exact oracles: value iteration, episode values
    "taskvar_torch.factory",  # a method's controller as a config sets it
    "taskvar_torch.experiments.evaluation",  # episodes and confidence intervals
    "taskvar_torch.experiments.bundle_eval",  # tv.evaluate and its table
)
"""The public modules; docs/design.md names each."""


def is_public_module(module: str) -> bool:
    for entry in PUBLIC_MODULES:
        if entry.endswith(".*"):
            base = entry[:-2]
            if module == base or module.startswith(base + "."):
                return True
        elif module == entry:
            return True
    return False


def _doc_blocks() -> list[tuple[str, str]]:
    """``(where, code)`` of every fenced Python block of the README and docs/ (the change log,
    history, aside)."""
    blocks = []
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]:
        if path.name == "changelog.md":
            continue
        text = path.read_text()
        for m in re.finditer(r"^```python\n(.*?)^```", text, re.M | re.S):
            line = text[: m.start()].count("\n") + 2
            blocks.append((f"{path.relative_to(ROOT)}:{line}", m.group(1)))
    return blocks


def _notebooks() -> list[tuple[str, str]]:
    """``(where, code)`` of every notebook: its code cells joined in order (a module imported in
    one cell is read in the next; IPython's ``%`` and ``!`` lines left out)."""
    found = []
    for path in sorted((ROOT / "notebooks").glob("*.ipynb")):
        cells = json.loads(path.read_text())["cells"]
        src = "\n".join("".join(c["source"]) for c in cells if c["cell_type"] == "code")
        src = "\n".join("" if ln.lstrip().startswith(("%", "!")) else ln for ln in src.splitlines())
        found.append((f"{path.relative_to(ROOT)} (code cells joined)", src))
    return found


def _examples() -> list[tuple[str, str]]:
    return [
        (str(p.relative_to(ROOT)), p.read_text()) for p in sorted((ROOT / "examples").rglob("*.py"))
    ]


def _copied_code() -> list[tuple[str, str]]:
    return [*_doc_blocks(), *_notebooks(), *_examples()]


def test_the_code_a_reader_copies_takes_only_public_modules_and_names():
    code = _copied_code()
    assert len(code) >= 10  # the README's and docs' blocks, 4 notebooks, the example
    hits = []
    for where, src in code:
        ast.parse(src)  # a block that does not parse is an error of its own: fix the block
        for line, module, _ in taken_names(src):
            if not is_public_module(module):
                hits.append(f"{where}:{line}: {module} is internal (not in PUBLIC_MODULES)")
        hits += private_uses(src, where)
    assert not hits, hits


def test_every_public_module_exists_and_docs_design_names_it():
    design = (ROOT / "docs" / "design.md").read_text()
    for entry in PUBLIC_MODULES:
        base = entry.removesuffix(".*")
        assert base in MODULES, entry
        assert f"`{entry}`" in design, f"docs/design.md does not name {entry}"


def test_the_rule_catches_an_internal_module_and_a_name_outside_all():
    src = (
        "import taskvar_torch as tv\n"
        "from taskvar_torch.families.windy import WindyGridEnv\n"
        "from taskvar_torch.training import train\n"
        "from taskvar_torch.factory import load_heads, torch\n"
    )
    internal = [m for _, m, _ in taken_names(src) if not is_public_module(m)]
    assert internal == ["taskvar_torch.training"]
    assert [h.split(": ", 1)[1] for h in private_uses(src, "probe")] == [
        "taskvar_torch.factory.torch is not in its __all__ (or not defined there)"
    ]


def test_every_name_in_every_modules_all_exists_and_star_imports_work():
    """A name in a module's ``__all__`` that the module does not define makes ``from M import *``
    raise (``taskvar_torch.families`` listed windy's ``GENERATED``; issue 57): every package
    module's ``__all__`` is checked, and the front door and the family contract star-imported."""
    import importlib
    import pkgutil

    import taskvar_torch

    missing = []
    for info in pkgutil.walk_packages(taskvar_torch.__path__, "taskvar_torch."):
        if info.name.endswith("__main__") or "._" in info.name:
            continue
        mod = importlib.import_module(info.name)
        missing += [f"{info.name}.{n}" for n in getattr(mod, "__all__", ()) if not hasattr(mod, n)]
    assert not missing, missing
    for name in ("taskvar_torch", "taskvar_torch.families"):
        exec(f"from {name} import *", {})


@pytest.mark.slow  # a real process or several agents trained: make test only
def test_import_taskvar_torch_reads_the_declarations_not_the_oracles():
    """``import taskvar_torch`` registers every built-in family's Gymnasium ids, which needs the
    families' declarations (env, instances, options), not their oracles, the controllers or the
    configs (it loaded 80 modules, windy's oracle and every controller among them, through the
    windy package's eager ``__init__``; issue 57)."""
    import subprocess
    import sys

    code = (
        "import sys, taskvar_torch\n"
        "print(' '.join(m for m in sys.modules if m.startswith('taskvar_torch')))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT
    ).stdout.split()
    heavy = [m for m in out if m.split(".")[-1] in ("oracle", "learnt") or ".controllers" in m]
    assert not heavy, heavy
    assert "taskvar_torch.families.windy.family" in out  # the declaration is read
    assert len(out) <= 50, len(out)
