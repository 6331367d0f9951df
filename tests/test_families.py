"""The family registry and the factory: one entry per family, no family-name branches elsewhere,
checkpoints that load without building an env (``heads_spec``), old checkpoints still loading."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest
import torch
from budgets import TINY  # tests/budgets.py

from taskvar_torch import factory
from taskvar_torch.checkpoint import load_checkpoint, save_checkpoint
from taskvar_torch.config import load_config
from taskvar_torch.factory import load_heads
from taskvar_torch.families import BUILTIN, family
from taskvar_torch.training import train

torch.set_num_threads(1)
PACKAGE = Path(__file__).resolve().parents[1] / "taskvar_torch"


def test_no_family_name_branches_outside_the_registry():
    """Nothing outside ``families/`` (the families' own packages) and ``contract.py`` (the
    registry, comparing a config's ``family`` with a declaration's ``name``) branches on a
    family's name."""
    pattern = re.compile(r"""\.family\s*(==|!=)|family\s*(==|!=)\s*["']""")
    hits = [
        f"{p.relative_to(PACKAGE)}:{i}"
        for p in PACKAGE.rglob("*.py")
        if p.relative_to(PACKAGE).parts[0] not in ("families", "contract.py")
        for i, line in enumerate(p.read_text().splitlines(), 1)
        if pattern.search(line)
    ]
    assert not hits, hits


def _imported_modules(path):
    """Every module ``path`` imports, at any depth (a function's lazy import too): the module of
    ``import M`` / ``from M import ...`` and ``M.name`` for each name taken from it."""
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.lineno, node.module
            for alias in node.names:
                yield node.lineno, f"{node.module}.{alias.name}"


def test_the_core_imports_no_family():
    """A family's package ``taskvar_torch/families/<name>/`` is imported only by itself: the core,
    the study and the other families reach it through the registry (``family(cfg)``, entry
    points), as they would an outside family's (read from the import statements, lazy ones too)."""
    builtin = set(BUILTIN)
    hits = []
    for p in PACKAGE.rglob("*.py"):
        parts = p.relative_to(PACKAGE).parts
        own = parts[1] if parts[0] == "families" and len(parts) > 2 else None
        for line, module in _imported_modules(p):
            m = module.split(".")
            if m[:2] == ["taskvar_torch", "families"] and len(m) > 2 and m[2] in builtin:
                if m[2] != own:
                    hits.append(f"{'/'.join(parts)}:{line} imports {module}")
    assert not hits, hits
    assert {p.name for p in (PACKAGE / "families").iterdir() if p.is_dir()} >= builtin


def test_unknown_family_is_a_one_line_error():
    with pytest.raises(ValueError, match=r"family must be one of \[.*'taxi', 'wargus', 'windy'"):
        family("mujoco")


def test_checkpoints_load_without_an_env_and_old_ones_still_load(tmp_path, monkeypatch):
    cfg = load_config("configs/wargus.yaml", TINY)
    train(cfg, tmp_path, progress=False)
    bundle = load_checkpoint(tmp_path / "final.pt")
    assert bundle["heads_spec"]["option_names"] == ["TG", "FE", "TG+FE"]
    reference, _ = load_heads(tmp_path / "final.pt")

    def no_env(*args, **kwargs):
        raise AssertionError("load_heads built an env")

    with monkeypatch.context() as m:
        m.setattr(factory, "make_env", no_env)
        heads, _ = load_heads(tmp_path / "final.pt")
    old = {k: v for k, v in bundle.items() if k not in ("heads_spec", "format", "format_version")}
    save_checkpoint(tmp_path / "old.pt", old)
    legacy, _ = load_heads(tmp_path / "old.pt")
    obs = torch.rand(5, 24)
    for h in (heads, legacy):
        for name in ("averaging", "options", "robustness"):
            assert torch.equal(h.heads[name].module(obs), reference.heads[name].module(obs))
