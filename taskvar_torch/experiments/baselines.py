"""The memory baselines in ``taskvar eval`` (docs/memory.md): which ones a bundle folder has
(``DIR/recurrent.pt``, ``DIR/informed.pt``, ...), loading them beside ``final.pt`` and the one-line
refusals. Their regret is the exact optimum minus the *sampled* return (``regret_sampled``).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from pathlib import Path

from taskvar_torch.config import Config
from taskvar_torch.heads.recurrent import (
    BASELINES,
    BaselineController,
    baseline_path,
    load_baseline,
)


def available_baselines(checkpoint: str | os.PathLike) -> list[str]:
    """The baselines whose bundle files sit beside ``checkpoint``, in :data:`BASELINES` order."""
    return [m for m in BASELINES if baseline_path(checkpoint, m).is_file()]


def train_command(checkpoint: str | os.PathLike, method: str) -> str:
    """The command that trains ``method`` beside ``checkpoint``."""
    folder = Path(checkpoint).parent
    config = folder / "config.yaml"
    cfg = str(config) if config.is_file() else "CONFIG"
    return f"taskvar train-baselines {cfg} --out {folder} --method {method}"


def missing_baseline_error(
    checkpoint: str | os.PathLike, method: str, supported: Sequence[str]
) -> ValueError:
    """The one-line refusal of ``--method recurrent`` (or informed) on a bundle without it."""
    return ValueError(
        f"method {method!r} needs {str(baseline_path(checkpoint, method))!r}, which this bundle "
        f"does not have; it supports {list(supported)}; train it with: "
        f"{train_command(checkpoint, method)}"
    )


def load_baselines(
    checkpoint: str | os.PathLike, methods: Sequence[str], cfg: Config
) -> dict[str, BaselineController]:
    """The greedy controllers of ``methods`` (baselines only) beside ``checkpoint``; a baseline
    trained on another family or layout than the bundle is a one-line ``ValueError``."""
    out = {}
    for m in methods:
        if m not in BASELINES:
            continue
        path = baseline_path(checkpoint, m)
        ctrl, bcfg = load_baseline(path, device=cfg.device)
        trained_on = (bcfg.family, dataclasses.replace(bcfg.env, num_envs=cfg.env.num_envs))
        if trained_on != (cfg.family, cfg.env):
            raise ValueError(
                f"{str(path)!r} was trained on another env than the bundle ({bcfg.family}, "
                f"env differs); train it again with: {train_command(checkpoint, m)}"
            )
        out[m] = ctrl
    return out


__all__ = [
    "available_baselines",
    "load_baselines",
    "missing_baseline_error",
    "train_command",
]
