"""The scale experiment's evaluation on fresh test instances (docs/scale.md): each method on paired
test episodes (:func:`evaluate`), the references (:func:`references`), :func:`gap_closed`, the
held-out test (:func:`heldout_test`) and :func:`isolated_rng`.
"""

from __future__ import annotations

import contextlib
import random
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import RandomPolicy

from taskvar_torch import keys
from taskvar_torch.config import (
    Config,
)
from taskvar_torch.contract import family
from taskvar_torch.experiments.evaluation import mean_ci95
from taskvar_torch.experiments.paired import play
from taskvar_torch.experiments.shift import EvalPoint, shift_points
from taskvar_torch.factory import make_env, make_method_controller, make_subtasks
from taskvar_torch.heads.recurrent import (
    BASELINES,
    BaselineController,
)
from taskvar_torch.study.scale_config import TEST_SEED_OFFSET

HELDOUT_TEST = "heldout"
"""The family test distribution (``Family.tests``) the held-out block plays: the sealed instances
(``families.HELDOUT_SEED``, docs/claims.md)."""


# --------------------------------------------------------------------------------------------
# evaluation on fresh test instances


def family_figure(cfg: Config, name: str) -> Any:
    """A family's table figure (``grid_side``, ``cells``, ``observation``), ``None`` if it has
    none."""
    f = getattr(family(cfg), name)
    return None if f is None else f(cfg)


def grid_side(cfg: Config) -> int:
    """The grid's side length (windy: max of height and width; Wargus: ``size``)."""
    return family_figure(cfg, "grid_side")


@dataclass(frozen=True)
class HeldoutTest:
    """The family's sealed held-out test distribution (``Family.tests["heldout"]``) for a cell's
    config: the env config, the instances and the sealed env seed its episodes play
    (docs/scale.md#held-out-instances)."""

    cfg: Config
    instances: Any
    seed: int
    description: str


def heldout_test(cfg: Config) -> HeldoutTest | None:
    """The held-out test of ``cfg``'s family (``taskvar eval --test heldout``'s) under the sealed
    seed, the same episodes for every training seed; ``None`` where the family has none.
    """
    dist = family(cfg).tests.get(HELDOUT_TEST)
    if dist is None or dist.seed is None:
        return None
    (point,) = shift_points(cfg, HELDOUT_TEST)
    return HeldoutTest(point.cfg, point.instances, int(dist.seed), dist.description)


@contextlib.contextmanager
def isolated_rng(device: str | torch.device) -> Iterator[None]:
    """Run a block without touching the global random streams the nominal protocol draws from:
    torch's (CPU and the device's), NumPy's and Python's states are restored on exit."""
    dev = torch.device(device)
    devices = []
    if dev.type == "cuda":
        devices = [dev.index if dev.index is not None else torch.cuda.current_device()]
    np_state, py_state = np.random.get_state(), random.getstate()
    try:
        with torch.random.fork_rng(devices=devices):
            yield
    finally:
        np.random.set_state(np_state)
        random.setstate(py_state)


class TablePolicy(nn.Module):
    """``action = table[cell]``: a tabular deterministic policy (the oracle's averaging optimum)."""

    def __init__(self, table: torch.Tensor):
        super().__init__()
        self.register_buffer("table", table.to(torch.int64))

    def forward(self, cell: torch.Tensor) -> torch.Tensor:
        return self.table[cell]


def make_policy(name: str, cfg: Config, heads: Any = None, subtasks: Any = None, env: Any = None):
    """A TorchRL policy: a method's controller on ``heads``, ``random`` or ``oracle_averaging``;
    for a baseline (``recurrent``, ``informed``) ``heads`` is its trained
    :class:`~taskvar_torch.heads.recurrent.BaselineController`, played as it is."""

    if name in BASELINES:
        if not isinstance(heads, BaselineController):
            raise ValueError(f"the {name} baseline plays its trained controller, got {heads!r}")
        return heads
    if name == "random":
        return RandomPolicy(env.action_spec)
    if name == "oracle_averaging":  # the family's exact mean-MDP averaging policy over cell
        table = family(cfg).needs("averaging_optimum", "the oracle_averaging reference")(cfg)
        return TensorDictModule(TablePolicy(table.to(cfg.device)), [keys.CELL], [keys.ACTION])
    return make_method_controller(cfg, name, heads, subtasks)


def evaluate(
    cfg: Config,
    policy_name: str,
    episodes: int,
    batch_size: int,
    heads: Any = None,
    test: HeldoutTest | None = None,
) -> dict[str, float] | None:
    """Mean return (95% CI), length and interruptions of ``policy_name`` over ``episodes`` paired
    test episodes (``test``: the held-out test's); ``None`` where the method does not apply.
    """

    instances: Any = "test"
    if test is None:
        seed = cfg.seed + TEST_SEED_OFFSET
    else:
        cfg, instances, seed = test.cfg, test.instances, test.seed
    probe = make_env(cfg, 1, seed=seed, instances=instances, validate_actions=False)
    subtasks = make_subtasks(cfg, probe)
    if policy_name == "hierarchy" and subtasks.hierarchy is None:
        return None
    torch.manual_seed(seed)  # the random policy's action stream
    policy = make_policy(policy_name, cfg, heads, subtasks, probe)
    point = EvalPoint("", None, cfg, instances)
    played = play(policy, point, int(episodes), seed, int(batch_size))
    r = torch.as_tensor(played["return"]).double()
    mean, ci = mean_ci95(r)
    result = {
        "mean_return": mean,
        "ci95": ci,
        "mean_length": float(torch.as_tensor(played["length"]).double().mean()),
        "episodes": int(r.numel()),
    }
    if policy_name in ("options", "interruption", "hierarchy"):
        result["interruptions_per_episode"] = float(
            torch.as_tensor(played["interruptions"]).double().mean()
        )
    return result


def references(
    cfg: Config, episodes: int, batch_size: int, test: HeldoutTest | None = None
) -> dict[str, Any]:
    """The random policy and, where the family brings one (``Family.averaging_optimum``), the
    exact mean-MDP averaging optimum on the same test episodes (``test``: the held-out ones)."""
    t0 = time.perf_counter()
    refs: dict[str, Any] = {"random": evaluate(cfg, "random", episodes, batch_size, test=test)}
    if family(cfg).averaging_optimum is not None:
        refs["oracle_averaging"] = evaluate(
            cfg, "oracle_averaging", episodes, batch_size, test=test
        )
        refs["oracle_note"] = (
            "mean-MDP optimal averaging policy (exact value iteration, paper "
            "§3.1), rolled out on the same test episodes"
        )
    else:
        refs["oracle_averaging"] = None
        refs["oracle_note"] = f"no exact oracle for the {cfg.family} family"
    refs["seconds"] = time.perf_counter() - t0
    return refs


def gap_closed(ret: float, random_ret: float, oracle_ret: float | None) -> float | None:
    """``(ret - random) / (oracle - random)``; ``None`` without an oracle or a gap."""
    if oracle_ret is None or abs(oracle_ret - random_ret) < 1e-9:
        return None
    return (ret - random_ret) / (oracle_ret - random_ret)


__all__ = [
    "HELDOUT_TEST",
    "HeldoutTest",
    "TablePolicy",
    "evaluate",
    "family_figure",
    "gap_closed",
    "grid_side",
    "heldout_test",
    "isolated_rng",
    "make_policy",
    "references",
]
