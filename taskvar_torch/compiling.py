"""``torch.compile`` with an eager fallback, for the hot paths ``train.compile`` turns on.

:class:`Compiled` wraps a pure function (no side effects, so a failed call can simply be rerun):
the first call compiles it (Dynamo + Inductor, static shapes; a new input shape recompiles), and
if compiling fails (no C++ compiler, an unsupported op) the error is warned once and every later
call runs the eager function. Used for the learner's losses
(:class:`~taskvar_torch.heads.learner.CompiledLosses`) and the Wargus dynamics step
(:meth:`~taskvar_torch.families.wargus.env.WargusEnv.compile_dynamics`); numbers and compile times:
docs/benchmarks.md.

Examples:
    >>> f = Compiled(lambda x: (x * 2).relu(), "doubling")  # doctest: +SKIP
    >>> f(torch.ones(3))  # doctest: +SKIP
    tensor([2., 2., 2.])
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any

import torch


class Compiled:
    """``fn`` through ``torch.compile(fn, dynamic=False)``, falling back to ``fn`` if that fails.

    Args:
        fn: a pure function of tensors (and static Python values).
        what: what ``fn`` computes, for the warning.

    Attributes:
        eager: ``fn``.
        compiled: the compiled ``fn``.
        failed: the exception compiling raised, or ``None``.
    """

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
