"""A user's code is a guest: every call the Gymnasium adapter makes into it goes through
:func:`guest`, so a failure there is one line naming the family, the function and where
(docs/reliability.md#your-codes-failures); ``taskvar`` prints it with exit status 2.
"""

from __future__ import annotations

import re
import signal
from collections.abc import Callable
from typing import Any

import numpy as np


class UserCodeError(ValueError):
    """A failure in a user's code (a Gymnasium family's env, options, instance distributions,
    encoder, ``state_info``, given policies), or a value it returned that its declaration
    refuses: one line naming the family, the function and where (docs/reliability.md)."""


class SignalInterrupt(KeyboardInterrupt):
    """The ``KeyboardInterrupt`` a taskvar signal handler raises (it carries the signal's number),
    which :func:`guest` tells apart from one a user's code raises itself."""

    def __init__(self, signum: int, *args: Any):
        super().__init__(*args)
        self.signum = int(signum)


def _from_a_signal(e: KeyboardInterrupt) -> bool:
    """Whether ``e`` is a signal's: it carries ``signum`` (taskvar's handlers), or Python's default
    SIGINT handler is in place (a program using the package: no telling, so it stays a Ctrl-C)."""
    return (
        getattr(e, "signum", None) is not None
        or signal.getsignal(signal.SIGINT) is signal.default_int_handler
    )


SUFFIX = "this is in your code, not in taskvar_torch (docs/gymnasium.md)"
"""How every :class:`UserCodeError` line ends."""


def short(value: Any, width: int = 72) -> str:
    """``value`` on one line of at most ``width`` characters (an observation in a message)."""
    if isinstance(value, np.ndarray):
        text = np.array2string(value, threshold=8, edgeitems=3, precision=4, separator=", ")
    elif isinstance(value, dict):
        text = "{" + ", ".join(f"{k!r}: {short(v, width)}" for k, v in value.items()) + "}"
    else:
        text = repr(value)
    text = re.sub(r"\s+([,\]])", r"\1", re.sub(r"\[\s+", "[", " ".join(text.split())))
    return text if len(text) <= width else text[: width - 3] + "..."


def user_error(family: str, what: str, problem: str, where: str = "") -> UserCodeError:
    """``family 'F': WHAT PROBLEM (WHERE): this is in your code, ...`` as a :class:`UserCodeError`."""
    at = f" ({where})" if where else ""
    return UserCodeError(f"family {family!r}: {what} {problem}{at}: {SUFFIX}")


def guest(
    family: str,
    what: str,
    fn: Callable[..., Any],
    *args: Any,
    where: str | Callable[[], str] = "",
    **kwargs: Any,
) -> Any:
    """``fn(*args, **kwargs)``, a call into a user's code: any exception (``SystemExit`` and its own
    ``KeyboardInterrupt`` included; a signal's passes through) becomes a one-line
    :class:`UserCodeError` ``family 'F': WHAT raised TYPE: MESSAGE (WHERE): this is in your code,
    ...``.

    Args:
        family: the family's name. what: the function as the user knows it (``env.step``).
        fn, args, kwargs: the call.
        where: where it was called, or a function that says it (called on a failure only).
    """
    try:
        return fn(*args, **kwargs)
    except UserCodeError:
        raise
    except (Exception, SystemExit, KeyboardInterrupt) as e:
        if isinstance(e, KeyboardInterrupt) and _from_a_signal(e):
            raise
        text = " ".join(str(e).split())
        detail = f": {text if len(text) <= 160 else text[:157] + '...'}" if text else ""
        if isinstance(e, SystemExit):
            detail = f" (sys.exit({e.code!r}))"
        at = where() if callable(where) else where
        raise user_error(family, what, f"raised {type(e).__name__}{detail}", at) from e


__all__ = ["SUFFIX", "SignalInterrupt", "UserCodeError", "guest", "short", "user_error"]
