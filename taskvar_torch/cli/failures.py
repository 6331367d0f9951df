"""How a ``taskvar`` command fails: one line on stderr and an exit status (docs/reliability.md).

2 for an input error (a value, a file, a folder, memory), 128 + N for signal N, 1 with the
traceback for a bug in the package; SIGTERM outside the training loop unwinds like Ctrl-C."""

from __future__ import annotations

import argparse
import codecs
import logging
import os
import signal
import sys
import threading
from collections.abc import Callable

from taskvar_torch import _startup
from taskvar_torch.checkpoint import CheckpointError
from taskvar_torch.guest import SignalInterrupt, UserCodeError
from taskvar_torch.run_folder import check_out_path


def run_command(
    name: str, run: Callable[[argparse.Namespace], int], args: argparse.Namespace
) -> int:
    """``run(args)`` of command ``name``; every failure is one line on stderr and an exit status: 2 for input
    (a value, a file, a folder, memory), 128 + N for signal N, 1 with the traceback for a bug."""
    try:
        if getattr(args, "out", None) is not None:  # --out '' would be the current folder
            check_out_path(args.out)
        return run(args)
    except UserCodeError as e:  # a family's own code failed: its line, even behind an interrupt
        line = (str(e).splitlines() or [""])[0]  # TorchRL appends a collector worker's traceback
        print(f"taskvar {name}: error: {line}", file=sys.stderr)
        return 2
    except (ValueError, CheckpointError, RuntimeError) as e:
        if (interrupt := _interrupt_behind(e)) is not None:
            return _interrupted(name, interrupt)
        if type(e).__name__ == "TrainingInterrupted":
            print(f"taskvar {name}: {e}", file=sys.stderr)
            return 128 + int(e.signum)
        if isinstance(e, RuntimeError) and type(e).__name__ != "TrainingDiverged":
            if _out_of_memory(e):
                return _memory_error(name)
            return _bug(name, e)
        print(f"taskvar {name}: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # a folder or file the command cannot write or read
        where = f" {e.filename!r}" if e.filename else ""
        print(f"taskvar {name}: error: cannot use{where}: {e.strerror or e}", file=sys.stderr)
        return 2
    except MemoryError:
        return _memory_error(name)
    except KeyboardInterrupt as e:
        return _interrupted(name, e)
    except Exception as e:  # not the input's fault: a bug, reported as one
        if (interrupt := _interrupt_behind(e)) is not None:
            return _interrupted(name, interrupt)
        return _bug(name, e)


def _interrupt_behind(e: BaseException) -> KeyboardInterrupt | None:
    """The Ctrl-C or SIGTERM that ``e`` was raised while unwinding, if any: a context manager's
    exit can fail on the way out (tensordict's ``to_module`` inside TorchRL's losses returns a
    TensorDict whose truth value raises), and that failure is the interrupt, not a bug."""
    seen = set()
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return e
        seen.add(id(e))
        e = e.__context__
    return None


def _interrupted(name: str, e: KeyboardInterrupt) -> int:
    """The one line of a command stopped by Ctrl-C or SIGTERM; status 128 + N."""
    signum = getattr(e, "signum", signal.SIGINT)
    text = f": {e}" if str(e) else f" by {signal.Signals(signum).name}"
    print(f"taskvar {name}: interrupted{text}", file=sys.stderr)
    return 128 + signum


def _out_of_memory(e: BaseException) -> bool:
    """Whether ``e`` is torch's out-of-memory error (CUDA's, or the CPU allocator's)."""
    import torch

    text = str(e).lower()
    return isinstance(e, torch.OutOfMemoryError) or any(
        marker in text for marker in ("out of memory", "can't allocate memory")
    )


def _memory_error(name: str) -> int:
    """The one line of an allocation that failed although the memory estimate let it pass."""
    print(
        f"taskvar {name}: error: out of memory: lower the sizes (env.num_envs, "
        "train.buffer_size, heads.hidden, eval.batch_size, --episodes)",
        file=sys.stderr,
    )
    return 2


def _bug(name: str, e: BaseException) -> int:
    """A failure that no input explains: the traceback, then one line saying it is a bug."""
    import traceback

    from taskvar_torch import __version__

    traceback.print_exception(e)
    print(
        f"taskvar {name}: internal error ({type(e).__name__}): this is a bug in taskvar_torch "
        f"{__version__}, not in your input; please report it to the taskvar_torch issue tracker "
        "with the command line and the traceback above",
        file=sys.stderr,
    )
    return 1


class _Terminated(KeyboardInterrupt):
    """SIGTERM outside the training loop (which handles its own): unwinds like Ctrl-C, so a run
    folder taken but not yet used is released and removed, and the command prints one line."""

    signum = signal.SIGTERM


class TerminateAsInterrupt:
    """While a command runs in the main thread with the default SIGTERM handler, SIGTERM raises
    :class:`_Terminated`; with the default SIGINT handler, Ctrl-C raises a
    :class:`~taskvar_torch.guest.SignalInterrupt` (a ``KeyboardInterrupt`` that says it is a
    signal's, not one a family's own code raised: :func:`~taskvar_torch.guest.guest`). The
    previous handlers are restored after."""

    def __enter__(self) -> TerminateAsInterrupt:
        self._old: dict[int, object] = {}
        if threading.current_thread() is threading.main_thread():
            early = _startup._interrupted_at_start
            current = signal.getsignal(signal.SIGTERM)
            if current == signal.SIG_DFL or current is early:
                signal.signal(signal.SIGTERM, self._raise)
                self._old[signal.SIGTERM] = signal.SIG_DFL
            current = signal.getsignal(signal.SIGINT)
            if current is signal.default_int_handler or current is early:
                signal.signal(signal.SIGINT, self._interrupt)
                self._old[signal.SIGINT] = signal.default_int_handler
        return self

    @staticmethod
    def _raise(signum: int, frame: object) -> None:
        raise _Terminated

    @staticmethod
    def _interrupt(signum: int, frame: object) -> None:
        raise SignalInterrupt(signum)

    def __exit__(self, *exc: object) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)


def _locale_safe(error: UnicodeEncodeError) -> tuple[str | bytes, int]:
    """A character the output's encoding lacks: a path's undecodable byte as it was
    (``surrogateescape``), anything else as ``\\xe9`` (``backslashreplace``)."""
    try:
        return codecs.lookup_error("surrogateescape")(error)
    except UnicodeEncodeError:
        return codecs.backslashreplace_errors(error)


codecs.register_error("taskvar_locale_safe", _locale_safe)


def locale_safe_output() -> None:
    """stdout and stderr print any text whatever the locale (``LC_ALL=C``,
    ``PYTHONIOENCODING=ascii``): a character the encoding lacks goes through :func:`_locale_safe`."""
    for stream in (sys.stdout, sys.stderr):
        encoding = getattr(stream, "encoding", None)
        try:
            if encoding is None or codecs.lookup(encoding).name == "utf-8":
                continue
            stream.reconfigure(errors="taskvar_locale_safe")
        except (AttributeError, LookupError, ValueError, OSError):
            continue  # a stream that cannot be reconfigured keeps its own errors


def quiet_third_party() -> None:
    """TorchRL's INFO lines (e.g. "Initialized LazyTensorStorage") are not for this CLI's users;
    ``RL_LOGGING_LEVEL`` set in the environment still wins."""
    if "RL_LOGGING_LEVEL" not in os.environ:
        os.environ["RL_LOGGING_LEVEL"] = "WARNING"  # read when torchrl is first imported
        logging.getLogger("torchrl").setLevel(logging.WARNING)  # in case it already was
