"""The experiment registry: name -> where its run, plot and default config live.

``taskvar experiment NAME``, ``taskvar plot DIR`` and ``taskvar sweep`` read :data:`EXPERIMENTS`;
a results folder names its experiment in ``metrics.json`` (``"experiment"``), so plotting reads that
key instead of guessing from the folder's files. Modules are imported when an experiment is used,
so ``taskvar --help`` and one-line errors do not load every experiment.

Examples:
    >>> sorted(EXPERIMENTS)
    ['scale', 'wargus-fig4', 'windy-fig2']
    >>> EXPERIMENTS["wargus-fig4"].module
    'taskvar_torch.experiments.wargus_fig4'
"""

from __future__ import annotations

import importlib
import inspect
import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

METRICS_NAME = "metrics.json"


@dataclass(frozen=True)
class Experiment:
    """One experiment: its module and the names of its entry points there.

    Attributes:
        name: ``taskvar experiment NAME`` and ``metrics.json``'s ``"experiment"``.
        module: dotted module holding the functions below.
        run: the function running it (``run(cfg, out_dir, ...) -> metrics``).
        plot: ``plot(out_dir) -> [png paths]`` (redraws from the results folder alone).
        default_config: ``default_config() -> Path`` of its YAML config.
        schema: the config dataclass its YAML follows (``Config`` or ``ScaleConfig``).
        description: one line for ``--help``.
    """

    name: str
    module: str
    run: str
    plot: str = "plot_results"
    default_config: str = "default_config_path"
    schema: str = "Config"
    description: str = ""

    def load(self) -> ModuleType:
        """The experiment's module (imported now)."""
        return importlib.import_module(self.module)

    def function(self, attr: str) -> Callable[..., Any]:
        """``run``, ``plot`` or ``default_config`` as a callable."""
        return getattr(self.load(), getattr(self, attr))

    def call(self, cfg: Any, out_dir: str | os.PathLike, **options: Any) -> dict[str, Any]:
        """Run the experiment with the ``options`` its ``run`` function takes (others are
        dropped: e.g. ``workers`` reaches wargus-fig4 only, ``quick`` windy-fig2 and scale)."""
        run = self.function("run")
        accepted = inspect.signature(run).parameters
        return run(cfg, out_dir, **{k: v for k, v in options.items() if k in accepted})

    def default_config_path(self) -> Path:
        return self.function("default_config")()

    def plot_results(self, out_dir: str | os.PathLike) -> list[Path]:
        return self.function("plot")(out_dir)


EXPERIMENTS: dict[str, Experiment] = {
    "windy-fig2": Experiment(
        "windy-fig2",
        "taskvar_torch.experiments.windy_fig2",
        run="windy_fig2",
        description="paired rollouts of interruption vs averaging on windy grids (paper Figure 2)",
    ),
    "wargus-fig4": Experiment(
        "wargus-fig4",
        "taskvar_torch.experiments.wargus_fig4",
        run="wargus_fig4",
        description="lifelong learning curves of the four methods on Wargus (paper Figure 4)",
    ),
    "scale": Experiment(
        "scale",
        "taskvar_torch.experiments.scale",
        run="scale",
        schema="ScaleConfig",
        description="every method on large grids and many environments, against references",
    ),
}
"""Every experiment, by name."""


def experiment(name: str) -> Experiment:
    """The registry entry ``name``; a one-line ``ValueError`` naming the experiments otherwise."""
    if name not in EXPERIMENTS:
        raise ValueError(f"experiment must be one of {sorted(EXPERIMENTS)}, got {name!r}")
    return EXPERIMENTS[name]


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


__all__ = ["EXPERIMENTS", "Experiment", "experiment", "experiment_of_folder"]
