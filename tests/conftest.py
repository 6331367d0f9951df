"""Shared by every test file.

- ``tests/`` is on ``sys.path`` (pytest's rootdir import mode puts a conftest's folder there), so
  a test anywhere below imports :mod:`budgets`, the training budgets the tests share.
- Files holding a slow test run first: ``make test`` hands whole files to two pytest-xdist
  workers in collection order (``--dist loadfile --no-loadscope-reorder``), so the long files
  start early instead of one of them running alone at the end. The order within a file is kept.
- Session fixtures: bundles several files evaluate, trained once.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from budgets import TINY

ROOT = Path(__file__).resolve().parents[1]


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    slow_files = {item.path for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.path not in slow_files)  # stable sort


@pytest.fixture(scope="session")
def windy_tiny_bundle(tmp_path_factory) -> Path:
    """``final.pt`` of ``configs/windy.yaml`` trained on :data:`budgets.TINY` (~2 s), with the
    informed baseline beside it (``informed.pt``, the same budget), once per session (per worker)
    for the tests that only evaluate a bundle; they must not write into its folder."""
    from taskvar_torch.config import load_config
    from taskvar_torch.training import train
    from taskvar_torch.training.baselines import train_baseline

    out = tmp_path_factory.mktemp("windy-tiny")
    cfg = load_config(ROOT / "configs" / "windy.yaml", TINY)
    train(cfg, out, progress=False)
    train_baseline(cfg, "informed", out)
    return out / "final.pt"
