"""Progress bars that stay readable in a log file: tqdm's on a terminal or notebook, else plain
lines (:class:`LineProgress`) every ``every`` (5%) of the total or ``interval`` (30 s), and one
at the end. Both take ``update``, ``set_postfix``, ``set_postfix_str``, ``close``, ``n``,
``total``, iteration and ``with``.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator, Mapping
from typing import IO, Any

from tqdm.auto import tqdm as _auto_tqdm

_IN_NOTEBOOK = any(c.__module__ == "tqdm.notebook" for c in _auto_tqdm.__mro__)
"""tqdm.auto chose its notebook widget: a Jupyter kernel with ipywidgets, where the bar redraws in
place (the kernel's streams are not terminals, yet a widget is what a notebook user expects)."""


def progress_bar(
    iterable: Iterable[Any] | None = None,
    *,
    total: float | None = None,
    desc: str | None = None,
    unit: str = "it",
    initial: float = 0,
    disable: bool = False,
    file: IO[str] | None = None,
    every: float = 0.05,
    interval: float = 30.0,
) -> Any:
    """A progress bar: tqdm's on a terminal or in a notebook, else a :class:`LineProgress`.

    Args:
        iterable: iterate over it, one step per item (``total`` defaults to its length).
        total: steps expected; ``None``: unknown (lines by time only).
        desc, unit: label of each line and what a step is. initial: steps already done.
        disable: no output. file: the stream (default ``sys.stderr``); a terminal decides.
        every, interval: away from a terminal, a line per this share of ``total`` or seconds.
    """
    stream = sys.stderr if file is None else file
    if disable or _IN_NOTEBOOK or _isatty(stream):
        return _auto_tqdm(
            iterable, total=total, desc=desc, unit=unit, initial=initial, disable=disable, file=file
        )
    return LineProgress(iterable, total, desc, unit, initial, stream, every, interval)


def _isatty(stream: Any) -> bool:
    """Whether ``stream`` is an interactive terminal (``False`` for anything without ``isatty``)."""
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


class LineProgress:
    """tqdm's bar as plain lines for non-terminal streams: at most ``1 / every + 1`` lines plus one
    per ``interval`` of wall time, none holding a ``'\\r'``."""

    def __init__(
        self,
        iterable: Iterable[Any] | None,
        total: float | None,
        desc: str | None,
        unit: str,
        initial: float,
        file: IO[str],
        every: float = 0.05,
        interval: float = 30.0,
    ) -> None:
        if total is None and iterable is not None:
            try:
                total = len(iterable)  # type: ignore[arg-type]
            except TypeError:
                total = None
        self.iterable = iterable
        self.total = total
        self.n = initial
        self.desc = desc
        self.unit = unit
        self.file = file
        self.every = every
        self.interval = interval
        self.postfix = ""
        self.start = time.monotonic()
        self._last_time = self.start
        self._last_n = initial
        self._last_step = self._step(initial)
        self._closed = False

    def _step(self, n: float) -> int:
        """Index of the ``every``-sized share of ``total`` that ``n`` has reached (0 if unknown)."""
        if not self.total or self.every <= 0:
            return 0
        return int(n / self.total / self.every + 1e-9)

    def __iter__(self) -> Iterator[Any]:
        if self.iterable is None:
            raise TypeError("this progress bar was made without an iterable")
        try:
            for item in self.iterable:
                yield item
                self.update(1)
        finally:
            self.close()

    def __enter__(self) -> LineProgress:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def update(self, n: float = 1) -> None:
        """Count ``n`` more steps; print a line if another share is done or ``interval`` passed."""
        if self._closed:
            return
        self.n += n
        now = time.monotonic()
        step = self._step(self.n)
        if step > self._last_step or (now - self._last_time >= self.interval):
            self._print(now)
            self._last_step = step

    def set_postfix(self, ordered_dict: Mapping[str, Any] | None = None, **kwargs: Any) -> None:
        """Show ``key=value`` pairs at the end of the next line (tqdm's ``set_postfix``)."""
        items = {**(ordered_dict or {}), **kwargs}
        self.postfix = ", ".join(f"{k}={v}" for k, v in items.items())

    def set_postfix_str(self, s: str = "") -> None:
        """Show ``s`` at the end of the next line (tqdm's ``set_postfix_str``)."""
        self.postfix = str(s)

    def close(self) -> None:
        """Print the last line (if anything changed since the previous one); idempotent."""
        if self._closed:
            return
        self._closed = True
        if self.n != self._last_n:
            self._print(time.monotonic())

    def _print(self, now: float) -> None:
        label = f"{self.desc}: " if self.desc else ""
        done = f"{_count(self.n)} {self.unit}"
        if self.total:
            done = f"{100 * self.n / self.total:3.0f}% {_count(self.n)}/{_count(self.total)}"
            done += f" {self.unit}"
        tail = f", {self.postfix}" if self.postfix else ""
        self.file.write(f"{label}{done}, {now - self.start:.0f} s{tail}\n")
        self.file.flush()
        self._last_time, self._last_n = now, self.n


def _count(x: float) -> str:
    """``x`` as an integer when it is one (``1000000``, not ``1e+06``), else 4 digits."""
    return str(int(x)) if float(x).is_integer() else f"{x:.4g}"


__all__ = ["LineProgress", "progress_bar"]
