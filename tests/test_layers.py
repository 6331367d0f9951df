"""The import direction (docs/design.md, Layout): the package's top-level parts stand in layers,
and a module imports only from its own part or from a lower layer (lazy imports inside functions
and type-only imports counted; read from the import statements, AST). A new arrow that runs back
up fails here, naming the module, the line and both layers (issue 57)."""

from __future__ import annotations

from public_names import MODULES, imported_modules

LAYERS = (
    ("rng", "keys", "io", "progress", "guest", "_startup", "_lazy", "compiling", "subtasks"),
    ("contract",),  # the family contract and registry: every layer reads it
    ("config",),
    ("envs",),
    ("",),  # the front door, taskvar_torch/__init__.py (its heavier names load lazily)
    ("checkpoint", "run_folder"),
    ("heads",),
    ("controllers",),
    ("oracle",),
    ("factory",),
    ("training",),
    ("experiments",),
    ("families", "family_check"),
    ("study",),
    ("cli",),
)
"""The top-level parts, bottom first (``""``: the package's ``__init__``)."""


def _part(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


LEVEL = {part: i for i, layer in enumerate(LAYERS) for part in layer}


def test_every_top_level_part_has_a_layer():
    parts = {_part(m) for m in MODULES}
    assert parts <= set(LEVEL), sorted(parts - set(LEVEL))


def _back_up(module: str, path) -> list[str]:
    """The imports of ``module`` (read from ``path``) that do not run down the layers."""
    here, hits = _part(module), []
    for line, target in imported_modules(path):
        there = _part(target)
        if target.startswith("taskvar_torch") and there != here and LEVEL[there] >= LEVEL[here]:
            hits.append(f"{module}:{line} imports {target} ({here!r} is not above {there!r})")
    return hits


def test_imports_run_down_the_layers():
    hits = [h for module, path in MODULES.items() for h in _back_up(module, path)]
    assert not hits, hits


def test_the_rule_catches_an_arrow_back_up(tmp_path):
    """A lazy import of the training loop inside the config package is caught; one of the
    contract is not."""
    path = tmp_path / "fake.py"
    path.write_text(
        "from taskvar_torch.contract import family\n\n\n"
        "def f():\n    from taskvar_torch.training import train\n"
    )
    assert _back_up("taskvar_torch.config.fake", path) == [
        "taskvar_torch.config.fake:5 imports taskvar_torch.training ('config' is not above "
        "'training')"
    ]
