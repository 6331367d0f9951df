"""Where a training run's log rows go (:func:`~taskvar_torch.training.train`): the CSV files
always, and TensorBoard, W&B or MLflow with ``train.logger``. The rows themselves (losses, training
returns, epsilon, updates, seconds) are written by
:meth:`~taskvar_torch.training.run_state.TrainingRun.log_row`.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

from torchrl.record.loggers import Logger, get_logger

LOGGER_EXTRAS = ("tensorboard", "wandb", "mlflow")
"""``train.logger`` values beyond ``csv``: each needs the package (and pip extra) of its name."""


def check_logger(kind: str) -> None:
    """Raise a one-line ``ValueError`` naming the extra when ``train.logger``'s package is
    missing (checked before a run writes anything)."""
    if kind in LOGGER_EXTRAS and not _installed(kind):
        raise ValueError(
            f"train.logger={kind} needs the {kind} package: pip install 'taskvar-torch[{kind}]'"
        )


def _installed(package: str) -> bool:
    """Whether ``package`` can be imported (found, not imported)."""
    return importlib.util.find_spec(package) is not None


class RunLoggers:
    """Where a run's log rows go, via TorchRL's ``get_logger``: always CSV files
    ``out/logs/scalars/<name>.csv``, and with ``train.logger`` TensorBoard, W&B or MLflow under
    ``out/logs``.
    """

    def __init__(self, kind: str, out: Path) -> None:
        check_logger(kind)
        logs = out / "logs"
        self.loggers: list[Logger] = [get_logger("csv", str(out), "logs")]
        if kind == "tensorboard":
            self.loggers.append(get_logger("tensorboard", str(logs), "tensorboard"))
        elif kind == "wandb":
            self.loggers.append(get_logger("wandb", str(logs), out.resolve().name))
        elif kind == "mlflow":
            self.loggers.append(get_logger("mlflow", str(logs / "mlruns"), out.resolve().name))

    def log_scalar(self, name: str, value: float, step: int) -> None:
        """Log ``value`` of scalar ``name`` at frame ``step`` to every logger."""
        for logger in self.loggers:
            logger.log_scalar(name, value, step=step)

    def close(self) -> None:
        """Flush and close every logger (TensorBoard, W&B and MLflow write their last rows)."""
        for logger in self.loggers:
            logger.close()


__all__ = ["LOGGER_EXTRAS", "RunLoggers", "check_logger"]
