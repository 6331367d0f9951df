"""Checking a loaded bundle's entries against what the config and the networks build, and loading
the state dicts that fit (docs/reliability.md#checkpoints-every-entry-checked-before-it-is-loaded).

Each check raises a one-line :class:`~taskvar_torch.checkpoint.CheckpointError` naming the entry.
"""

from __future__ import annotations

import random
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from torch import nn

from taskvar_torch.checkpoint import CheckpointError, first_line, kind_of, rng_state


def load_state_dicts(
    bundle: Mapping[str, Any],
    models: Mapping[str, nn.Module],
    optimizers: Mapping[str, torch.optim.Optimizer] | None = None,
) -> None:
    """Load a bundle's state dicts into live modules and optimizers (strict, clear errors).

    Raises:
        CheckpointError: a name is missing from the bundle or a state dict does not fit.
    """
    for group, targets in (("models", models), ("optimizers", optimizers or {})):
        saved = bundle.get(group, {})
        if not isinstance(saved, Mapping):
            raise CheckpointError(f"checkpoint {group} is {kind_of(saved)}, expected a dict")
        for name, obj in targets.items():
            if name not in saved:
                raise CheckpointError(
                    f"checkpoint has no {group}[{name!r}]; it has {sorted(saved)}"
                )
            try:  # every tensor's name, shape and dtype first: the message names the one at fault
                if isinstance(obj, torch.optim.Optimizer):
                    check_optimizer_state(saved[name], obj, f"{group}[{name!r}]")
                else:
                    check_like(saved[name], obj.state_dict(), f"{group}[{name!r}]")
            except CheckpointError as e:
                raise CheckpointError(
                    f"checkpoint does not fit the network built from the config: {e}"
                ) from None
            try:
                obj.load_state_dict(saved[name])
            except (RuntimeError, ValueError, KeyError) as e:
                first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
                raise CheckpointError(
                    f"checkpoint {group}[{name!r}] does not fit the network built from the "
                    f"config: {first}"
                ) from None


def check_like(saved: Any, expected: Any, where: str) -> None:
    """:class:`CheckpointError` naming the first part of ``saved`` whose type, keys, length, shape
    or dtype differ from ``expected`` (``None`` accepts anything); the caller adds the path.
    """
    if isinstance(expected, torch.Tensor):
        if not isinstance(saved, torch.Tensor):
            raise CheckpointError(f"{where} is {kind_of(saved)}, expected {kind_of(expected)}")
        if saved.shape != expected.shape:
            raise CheckpointError(
                f"{where} has shape {list(saved.shape)}, expected {list(expected.shape)}"
            )
        if saved.dtype != expected.dtype:
            raise CheckpointError(f"{where} has dtype {saved.dtype}, expected {expected.dtype}")
        return
    if isinstance(expected, Mapping):
        if not isinstance(saved, Mapping):
            raise CheckpointError(f"{where} is {kind_of(saved)}, expected a dict")
        missing = [k for k in expected if k not in saved]
        if missing:
            raise CheckpointError(f"{where} has no entry {missing[0]!r}")
        extra = [k for k in saved if k not in expected]
        if extra:
            raise CheckpointError(f"{where} has an unexpected entry {extra[0]!r}")
        for k, v in expected.items():
            check_like(saved[k], v, f"{where}[{k!r}]")
        return
    if isinstance(expected, (list, tuple)):
        if not isinstance(saved, (list, tuple)):
            raise CheckpointError(f"{where} is {kind_of(saved)}, expected a list")
        if len(saved) != len(expected):
            raise CheckpointError(f"{where} has {len(saved)} items, expected {len(expected)}")
        for i, (a, b) in enumerate(zip(saved, expected)):
            check_like(a, b, f"{where}[{i}]")
        return
    if expected is None:
        return
    kinds = {bool: (bool,), int: (int,), float: (int, float), str: (str,)}
    allowed = next((v for k, v in kinds.items() if type(expected) is k), (type(expected),))
    if type(saved) not in allowed:
        raise CheckpointError(f"{where} is {kind_of(saved)}, expected {kind_of(expected)}")


def check_counter(value: Any, where: str, high: int = 2**62) -> int:
    """A counter: an integer (not a bool) in ``[0, high]``, else :class:`CheckpointError`."""
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= high:
        raise CheckpointError(f"{where} must be an integer in [0, {high}], got {value!r}")
    return value


def check_counters(saved: Any, expected: Mapping[str, int], where: str = "counters") -> None:
    """``saved`` has exactly ``expected``'s counters, each a non-negative integer."""
    check_like(saved, dict(expected), where)
    for k in expected:
        check_counter(saved[k], f"{where}[{k!r}]")


def check_rng_state(
    saved: Any, generators: Mapping[str, torch.Generator] | None = None, where: str = "rng"
) -> None:
    """``saved`` is a :func:`rng_state` of this machine's generators (CUDA states checked only where
    CUDA is available).
    """
    live = rng_state(generators)
    if isinstance(saved, Mapping) and not torch.cuda.is_available():
        live["cuda"] = saved.get("cuda", [])  # restored only where CUDA is available
    if isinstance(saved, Mapping) and isinstance(saved.get("python"), Mapping):
        live["python"]["gauss_next"] = None  # None or a float
    if isinstance(saved, Mapping) and isinstance(saved.get("generators"), Mapping):
        for k in saved["generators"]:  # generators this run does not restore are ignored
            live["generators"].setdefault(k, live["torch"])
    check_like(saved, live, where)
    for i, s in enumerate(saved["cuda"]):
        if not isinstance(s, torch.Tensor) or s.dtype != torch.uint8:
            raise CheckpointError(f"{where}['cuda'][{i}] is {kind_of(s)}, expected a uint8 tensor")
    n, p = saved["numpy"], saved["python"]
    if n["bit_generator"] != "MT19937" or not (
        bool(((n["keys"] >= 0) & (n["keys"] <= 0xFFFFFFFF)).all()) and 0 <= n["pos"] <= 624
    ):
        raise CheckpointError(f"{where}['numpy'] is not an MT19937 state (keys, pos)")
    gauss = p["gauss_next"]
    if gauss is not None and type(gauss) is not float:
        raise CheckpointError(
            f"{where}['python']['gauss_next'] is {kind_of(gauss)}, expected a float"
        )
    try:
        random.Random().setstate((p["version"], tuple(p["state"]), gauss))
        np.random.RandomState().set_state(
            (n["bit_generator"], n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"],
             n["cached_gaussian"])
        )  # fmt: skip
    except (TypeError, ValueError, OverflowError) as e:
        raise CheckpointError(
            f"{where} holds an unusable Python or numpy state: {first_line(e)}"
        ) from None
    for k in generators or {}:
        try:
            torch.Generator().set_state(saved["generators"][k])
        except RuntimeError as e:
            raise CheckpointError(f"{where}['generators'][{k!r}]: {first_line(e)}") from None
    try:
        torch.Generator().set_state(saved["torch"])
    except RuntimeError as e:
        raise CheckpointError(f"{where}['torch']: {first_line(e)}") from None


def check_optimizer_state(saved: Any, optimizer: torch.optim.Optimizer, where: str) -> None:
    """``saved`` is a state dict of ``optimizer``: the same parameter groups, each parameter's state
    exactly as one step creates it, of the parameter's shape and dtype, ``step`` finite and >= 0.
    """
    live = optimizer.state_dict()
    check_like(saved, {"state": None, "param_groups": None}, where)
    groups, states = saved["param_groups"], saved["state"]
    check_like(groups, [None] * len(live["param_groups"]), f"{where}['param_groups']")
    params = [p for g in optimizer.param_groups for p in g["params"]]
    by_id: dict[int, torch.Tensor] = {}
    for i, (g, lg) in enumerate(zip(groups, live["param_groups"])):
        gw = f"{where}['param_groups'][{i}]"
        check_like(g, lg, gw)  # every setting of this optimizer, of its type (betas a pair...)
        for k, v in lg.items():
            if v is None and g[k] is not None:  # unset here (foreach): unset there too
                raise CheckpointError(f"{gw}[{k!r}] must be None, got {g[k]!r}")
        for k, v in g.items():
            if isinstance(lg[k], float) and not (
                type(v) in (int, float) and np.isfinite(v) and v >= 0
            ):
                raise CheckpointError(f"{gw}[{k!r}] must be a finite number >= 0, got {v!r}")
        for pid, lpid in zip(g["params"], lg["params"]):
            by_id[pid] = params[lpid]
    if len(by_id) != len(params):
        raise CheckpointError(f"{where}['param_groups'] names a parameter twice")
    if not isinstance(states, Mapping):
        raise CheckpointError(f"{where}['state'] is {kind_of(states)}, expected a dict")
    probe = _one_step_state(optimizer)
    for pid, st in states.items():
        sw = f"{where}['state'][{pid!r}]"
        if pid not in by_id:
            raise CheckpointError(f"{sw} is the state of no parameter (ids {sorted(by_id)})")
        param = by_id[pid]
        expected = {
            k: (v if k == "step" else torch.empty(param.shape, dtype=param.dtype))
            if isinstance(v, torch.Tensor)
            else v
            for k, v in probe.items()
        }
        check_like(st, expected, sw)
        step = st.get("step")
        if isinstance(step, torch.Tensor) and not (
            bool(torch.isfinite(step).all()) and float(step) >= 0
        ):
            raise CheckpointError(f"{sw}['step'] must be finite and >= 0, got {float(step)}")


def _one_step_state(optimizer: torch.optim.Optimizer) -> dict[str, Any]:
    """The state one step of ``optimizer``'s class and settings gives a one-element parameter:
    which entries a parameter's state holds, and their dtypes."""
    p = nn.Parameter(torch.zeros(1, dtype=optimizer.param_groups[0]["params"][0].dtype))
    probe = type(optimizer)([p], **optimizer.defaults)
    p.grad = torch.zeros_like(p)
    probe.step()
    return dict(probe.state[p])
