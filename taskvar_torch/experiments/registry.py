"""The experiment registry: name -> where its run, plot and default config live.

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
        loader: ``loader(path, overrides, quick=...) -> config`` in its module, for a schema
            other than ``Config`` (``Config``: :func:`taskvar_torch.config.load_config`).
        description: one line for ``--help``.
        refusals: why the experiment does not take an option of ``taskvar experiment`` (option
            -> the one-line reason); an option it neither takes nor names here is refused with
            a generic line.
    """

    name: str
    module: str
    run: str
    plot: str = "plot_results"
    default_config: str = "default_config_path"
    schema: str = "Config"
    loader: str | None = None
    description: str = ""
    refusals: tuple[tuple[str, str], ...] = ()

    def load(self) -> ModuleType:
        """The experiment's module (imported now)."""
        return importlib.import_module(self.module)

    def function(self, attr: str) -> Callable[..., Any]:
        """``run``, ``plot`` or ``default_config`` as a callable."""
        return getattr(self.load(), getattr(self, attr))

    def takes(self, option: str) -> bool:
        """Whether ``run`` takes the keyword ``option`` (e.g. ``workers``: wargus-fig4 only)."""
        return option in inspect.signature(self.function("run")).parameters

    def refuse(self, option: str, flag: str | None = None) -> None:
        """A one-line ``ValueError`` unless ``run`` takes ``option`` (named ``flag`` to the
        user, e.g. ``--workers``): the experiment's own reason where it gives one."""
        if self.takes(option):
            return
        reason = dict(self.refusals).get(option)
        raise ValueError(reason or f"{flag or option} is not an option of {self.name}")

    def call(self, cfg: Any, out_dir: str | os.PathLike, **options: Any) -> dict[str, Any]:
        """Run the experiment with ``options``; one it does not take is a one-line
        ``ValueError`` (:meth:`refuse`), never dropped."""
        for k in options:
            self.refuse(k)
        return self.function("run")(cfg, out_dir, **options)

    def load_config(self, path: str | os.PathLike, overrides: Any = (), quick: bool = False) -> Any:
        """The experiment's config from ``path`` and ``overrides`` (its own ``loader`` where its
        schema is not ``Config``)."""
        if self.loader is None:
            from taskvar_torch.config import load_config

            return load_config(path, overrides, quick=quick)
        return getattr(self.load(), self.loader)(path, overrides, quick=quick)

    def default_config_path(self) -> Path:
        return self.function("default_config")()

    def plot_results(self, out_dir: str | os.PathLike) -> list[Path]:
        return self.function("plot")(out_dir)


EXPERIMENTS: dict[str, Experiment] = {
    "windy-fig2": Experiment(
        "windy-fig2",
        "taskvar_torch.families.windy.fig2",
        run="windy_fig2",
        description="paired rollouts of interruption vs averaging on windy grids (paper Figure 2)",
    ),
    "wargus-fig4": Experiment(
        "wargus-fig4",
        "taskvar_torch.families.wargus.fig4",
        run="wargus_fig4",
        description="lifelong learning curves of the four methods on Wargus (paper Figure 4)",
        refusals=(
            (
                "checkpoint",
                "wargus-fig4 learns from scratch (lifelong protocol); --checkpoint is not used",
            ),
            (
                "threads",
                "--threads: wargus-fig4 runs one thread per process (small batches; 2 threads "
                "under contention ran 10x slower); use --workers N to use more cores",
            ),
        ),
    ),
    "scale": Experiment(
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
