"""The first thing ``import taskvar_torch`` runs: when the process is the ``taskvar`` command, a
handler that turns Ctrl-C or SIGTERM during the start-up imports into the documented line
``taskvar COMMAND: interrupted by SIGNAL`` and exit status 128 + N (docs/reliability.md#outcomes).
"""

from __future__ import annotations

import os
import re
import signal
import sys
import threading

_MODULES = ("taskvar_torch.cli", "taskvar_torch.cli.__main__")
_SCRIPTS = ("taskvar", "taskvar.exe", "taskvar-script.py")


def _started_as_command() -> bool:
    """Whether this process is the ``taskvar`` command (read from its command line)."""
    if sys.argv and os.path.basename(sys.argv[0]) in _SCRIPTS:
        return True
    orig = list(getattr(sys, "orig_argv", ()))
    skip = False
    for i, arg in enumerate(orig[1:], start=1):
        if skip:  # the value of -X or -W
            skip = False
            continue
        if arg in ("-X", "-W"):
            skip = True
            continue
        if arg == "-m":
            return i + 1 < len(orig) and orig[i + 1] in _MODULES
        if arg.startswith("-m"):
            return arg[2:] in _MODULES
        if not arg.startswith("-") or arg == "-c":  # a script or -c: not the command
            return False
    return False


AS_COMMAND = _started_as_command()
"""Whether this process is the ``taskvar`` command: the registry then loads an installed
family's entry point only when the family is asked for by name (``envs/registration.py``)."""


def _command_name() -> str:
    """``taskvar COMMAND`` as far as the command line says (argv may not be parsed yet)."""
    args = sys.argv[1:]
    if args and re.fullmatch(r"[a-z][a-z-]*", args[0]):
        return f"taskvar {args[0]}"
    return "taskvar"


def _interrupted_at_start(signum: int, frame: object) -> None:
    """A signal before the command's handling is in place: its one line, status 128 + N."""
    line = f"{_command_name()}: interrupted by {signal.Signals(signum).name}\n"
    try:
        os.write(2, line.encode("ascii", "replace"))
    finally:
        os._exit(128 + signum)


_EARLY: dict[int, object] = {}
"""Signal -> the handler it had before :func:`_install` (restored by :func:`hand_over`)."""


def _install() -> None:
    if threading.current_thread() is not threading.main_thread():
        return
    defaults = ((signal.SIGTERM, signal.SIG_DFL), (signal.SIGINT, signal.default_int_handler))
    for sig, default in defaults:
        if signal.getsignal(sig) is default:
            _EARLY[sig] = signal.signal(sig, _interrupted_at_start)


def hand_over() -> None:
    """The command's own handling takes over: the handlers from before start-up come back."""
    for sig, old in list(_EARLY.items()):
        if signal.getsignal(sig) is _interrupted_at_start:
            signal.signal(sig, old)
        del _EARLY[sig]


if AS_COMMAND:
    _install()
