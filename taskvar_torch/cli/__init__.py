"""Command line: ``taskvar COMMAND ...`` (train, eval, train-baselines, experiment, sweep, export,
plot, report).

Each command is one entry of :data:`COMMANDS` (a help line, its arguments, its function); commands
parse intermixed arguments, so ``key.sub=value`` overrides may come before or after the options.
Input errors print one line and exit 2; signals and bugs as docs/reliability.md says. One module per
command group (``train``, ``evaluate``, ``study``), each importing its machinery inside its
function, so ``taskvar --help`` loads no experiment.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

from taskvar_torch._startup import hand_over
from taskvar_torch.cli import evaluate, study, train
from taskvar_torch.cli.arguments import Command
from taskvar_torch.cli.failures import (
    TerminateAsInterrupt,
    locale_safe_output,
    quiet_third_party,
    run_command,
)

COMMANDS: dict[str, Command] = {
    "train": train.TRAIN,
    "eval": evaluate.EVAL,
    "train-baselines": train.TRAIN_BASELINES,
    "experiment": study.EXPERIMENT,
    "sweep": study.SWEEP,
    "export": train.EXPORT,
    "plot": study.PLOT,
    "report": study.REPORT,
}
"""Subcommands by name, in ``taskvar --help``'s order (each defined beside its arguments and run
function); add an entry to add a command."""


class _OneLineParser(argparse.ArgumentParser):
    """``argparse`` whose input errors are one line ``PROG: error: ...`` (status 2) and whose epilog
    may be computed only when the help is printed (``lazy_epilog``).
    """

    lazy_epilog: Callable[[], str] | None = None

    def error(self, message: str):  # argparse API
        self.exit(2, f"{self.prog}: error: {message}\n")

    def format_help(self) -> str:  # argparse API
        if self.lazy_epilog is not None:
            self.epilog, self.lazy_epilog = self.lazy_epilog(), None
        return super().format_help()


def build_parser() -> tuple[argparse.ArgumentParser, dict[str, argparse.ArgumentParser]]:
    """The ``taskvar`` parser and one parser per subcommand."""
    parser = _OneLineParser(
        prog="taskvar",
        description="Offline learning across task variations for online performance "
        "(averaging policy, offline options, offline interruption, composition hierarchies).",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    parsers = {}
    for name, cmd in COMMANDS.items():
        parsers[name] = sub.add_parser(
            name,
            help=cmd.help,
            description=cmd.description,
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        parsers[name].lazy_epilog = cmd.epilog
        cmd.add_arguments(parsers[name])
    return parser, parsers


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``taskvar`` console script; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser, parsers = build_parser()
    if not argv or argv[0] not in parsers:
        parser.parse_args(argv)  # --help, or an error naming the valid commands
        return 2
    name = argv[0]
    args = parsers[name].parse_intermixed_args(argv[1:])
    quiet_third_party()
    locale_safe_output()
    with TerminateAsInterrupt():
        hand_over()  # Ctrl-C raises KeyboardInterrupt again; SIGTERM is TerminateAsInterrupt's
        return run_command(name, COMMANDS[name].run, args)
