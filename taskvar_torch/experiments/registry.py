"""The experiment registry: name -> where its run, plot and default config live.

Filled by the families that own the experiments (``Family.experiment``: windy's Figure 2, Wargus's
Figure 4, an installed family's own) and the scale experiment of :mod:`taskvar_torch.study`.

``taskvar experiment NAME``, ``taskvar plot DIR`` and ``taskvar sweep`` read :data:`EXPERIMENTS`;
a results folder names its experiment in ``metrics.json`` (``"experiment"``), so plotting reads that
key instead of guessing from the folder's files. Modules are imported when an experiment is used,
so ``taskvar --help`` and one-line errors do not load every experiment.

Examples:
    >>> sorted(EXPERIMENTS)
    ['scale', 'wargus-fig4', 'windy-fig2']
    >>> EXPERIMENTS["wargus-fig4"].module
    'taskvar_torch.families.wargus.fig4'
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from taskvar_torch.config import load_config
from taskvar_torch.contract import FAMILIES, Experiment

METRICS_NAME = "metrics.json"


SCALE = Experiment(
    "scale",
    "taskvar_torch.study.scale",
    run="scale",
    schema="ScaleConfig",
    loader="load_scale_config",
    refusals=(
        (
            "checkpoint",
            "scale trains one bundle per (case, num_envs) cell; --checkpoint is not used",
        ),
    ),
    description="every method on large grids and many environments, against references",
)
"""The scale experiment (:mod:`taskvar_torch.study.scale`): any family with the scale hooks."""


class _Experiments(Mapping):
    """Every experiment by name: each loaded family's (``Family.experiment``; the built-in
    families are loaded, an installed one once asked for) and :data:`SCALE`."""

    def _all(self) -> dict[str, Experiment]:
        out = {
            fam.experiment.name: fam.experiment
            for fam in FAMILIES.loaded().values()
            if fam.experiment is not None
        }
        return {**out, SCALE.name: SCALE}

    def __getitem__(self, name: str) -> Experiment:
        return self._all()[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._all())

    def __len__(self) -> int:
        return len(self._all())


EXPERIMENTS = _Experiments()
"""Every experiment, by name."""


def experiment(name: str) -> Experiment:
    """The registry entry ``name``; a one-line ``ValueError`` naming the experiments otherwise."""
    if name not in EXPERIMENTS:
        raise ValueError(f"experiment must be one of {sorted(EXPERIMENTS)}, got {name!r}")
    return EXPERIMENTS[name]


def load_experiment_config(
    exp: Experiment, path: str | os.PathLike, overrides: Any = (), quick: bool = False
) -> Any:
    """The config of experiment ``exp`` from ``path`` and ``overrides``: its own ``loader``
    where its schema is not ``Config`` (the scale experiment's), else
    :func:`taskvar_torch.config.load_config`."""
    if exp.loader is None:
        return load_config(path, overrides, quick=quick)
    return getattr(exp.load(), exp.loader)(path, overrides, quick=quick)


def experiment_of_folder(out_dir: str | os.PathLike) -> Experiment:
    """The experiment that wrote the results folder ``out_dir`` (its ``metrics.json``'s
    ``"experiment"``); a one-line ``ValueError`` when the folder holds no such results."""
    path = Path(out_dir) / METRICS_NAME
    try:
        name = json.loads(path.read_text()).get("experiment")
    except OSError:
        raise ValueError(
            f"{str(out_dir)!r} is not a results folder of taskvar experiment (no {METRICS_NAME})"
        ) from None
    except (ValueError, AttributeError):
        raise ValueError(f"{str(path)!r} is not a metrics file of taskvar experiment") from None
    if name not in EXPERIMENTS:
        raise ValueError(f"{str(path)!r} names experiment {name!r}; known: {sorted(EXPERIMENTS)}")
    return EXPERIMENTS[name]


__all__ = [
    "EXPERIMENTS",
    "SCALE",
    "Experiment",
    "experiment",
    "experiment_of_folder",
    "load_experiment_config",
]
