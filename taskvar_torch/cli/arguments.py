"""What the ``taskvar`` commands share: the :class:`Command` entry, the ``CONFIG key.sub=value``
items, and the ``--overwrite`` and ``--threads`` options."""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class Command:
    """A subcommand: ``help`` line, ``add_arguments(parser)``, ``run(args) -> exit status``."""

    help: str
    description: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    epilog: Callable[[], str] | None = None


def split_config_and_overrides(items: Sequence[str]) -> tuple[str | None, list[str]]:
    """``CONFIG`` is the first item without ``=``; the rest are ``key.sub=value`` overrides."""
    config, overrides = None, []
    for item in items:
        if "=" not in item and config is None:
            config = item
        elif "=" not in item:
            raise ValueError(f"expected key.sub=value overrides after the config, got {item!r}")
        else:
            overrides.append(item)
    return config, overrides


def overwrite_argument(p: argparse.ArgumentParser, where: str) -> None:
    p.add_argument(
        "--overwrite",
        action="store_true",
        help=f"replace the run already in {where} (its config, checkpoints and logs are removed "
        "first); without it a folder holding a run is refused",
    )


def threads_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--threads",
        type=int,
        default=1,
        metavar="N",
        help="torch CPU threads (default 1: the heads are small MLPs, and more threads only "
        "contend on a shared CPU; raise it for large networks)",
    )


def set_threads(args: argparse.Namespace) -> None:
    import torch

    cores = os.cpu_count() or 1
    if not 1 <= args.threads <= cores:
        raise ValueError(
            f"--threads must be in [1, {cores}] (this machine's cores), got {args.threads}"
        )
    torch.set_num_threads(args.threads)
