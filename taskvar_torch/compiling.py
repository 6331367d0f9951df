"""``torch.compile`` with an eager fallback for the hot paths ``train.compile`` turns on (the
learner's losses, the Wargus dynamics step; docs/benchmarks.md).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any

import torch


class Compiled:
    """Pure ``fn`` through ``torch.compile(fn, dynamic=False)`` on first call; if compiling fails,
    one warning naming ``what`` and ``fn`` eager from then on. Attributes: ``eager``, ``compiled``,
    ``failed`` (the exception, or ``None``)."""

    def __init__(self, fn: Callable[..., Any], what: str):
        self.eager = fn
        self.compiled = torch.compile(fn, dynamic=False)
        self.what = what
        self.failed: Exception | None = None

    def __call__(self, *args: Any) -> Any:
        if self.failed is None:
            try:
                return self.compiled(*args)
            except Exception as e:  # noqa: BLE001 - any compile failure: run eager from now on
                self.failed = e
                first = str(e).splitlines()[0] if str(e) else ""
                warnings.warn(
                    f"torch.compile of {self.what} failed, running eager: "
                    f"{type(e).__name__}: {first}",
                    stacklevel=2,
                )
        return self.eager(*args)
