"""The Taxi family: Gymnasium's Taxi-v4 as a family of MDPs (docs/taxi.md), registered through the
public door only: the entry point ``taskvar_torch.families`` names :func:`family`
(docs/families.md). Own config keys: ``env.taxi`` (:class:`TaxiConfig`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase

from taskvar_torch import keys, rng
from taskvar_torch.contract import HELDOUT_SEED, Family, TestDistribution
from taskvar_torch.families.taxi.dynamics import TaxiInstances, taxi_instances
from taskvar_torch.families.taxi.env import OBS_ENCODINGS, TaxiEnv

NAME = "taxi"
MAX_HORIZON = rng.RESET_COUNTER - 1
"""Largest ``env.taxi.horizon``: step ``t`` draws from counters below ``rng.RESET_COUNTER``."""
INSTANCE_DIM = 3
"""Features of a Taxi instance: ``(1 - rainy_probability, fickle_probability, armed)``."""


@dataclass(frozen=True)
class TaxiConfig:
    """The Taxi family's own env keys (``env.taxi.*``)."""

    obs_encoding: str = "onehot"
    """Observation: onehot (one-hot of Taxi-v4's 500 states) or factored (one-hot row, column,
    passenger and destination: 19 values)."""
    horizon: int = 200
    """Steps before truncation (Taxi-v4: 200)."""

    def __post_init__(self):
        if self.obs_encoding not in OBS_ENCODINGS:
            raise ValueError(
                f"obs_encoding must be one of {list(OBS_ENCODINGS)}, got {self.obs_encoding!r}"
            )
        if not 1 <= self.horizon <= MAX_HORIZON:
            raise ValueError(f"horizon must be in [1, {MAX_HORIZON}], got {self.horizon}")


def _section(cfg: Any) -> TaxiConfig:
    section = getattr(cfg.env, NAME, None)
    return TaxiConfig() if section is None else section


def _env_kwargs(cfg: Any) -> dict[str, Any]:
    t = _section(cfg)
    return {
        "num_envs": cfg.env.num_envs,
        "instances": cfg.env.instances,
        "horizon": t.horizon,
        "obs_encoding": t.obs_encoding,
        "seed": cfg.seed,
        "device": cfg.device,
    }


def _subtasks(cfg: Any, env: Any) -> Any:
    from taskvar_torch.families.taxi.subtasks import TaxiSubtasks

    return TaxiSubtasks()


def instance_features(td: TensorDictBase) -> torch.Tensor:
    """``(B, 3)``: how rainy (``1 - q``), how fickle (``f``) and whether the passenger will still
    change their mind (``armed``), from the transitions' ``("instance", ...)`` entries."""
    inst = td.get(keys.INSTANCE)
    q = inst.get("rainy_probability").reshape(-1, 1).to(torch.float32)
    f = inst.get("fickle_probability").reshape(-1, 1).to(torch.float32)
    armed = inst.get("armed").reshape(-1, 1).to(torch.float32)
    return torch.cat([1.0 - q, f, armed], dim=-1)


INFORMED_DIM = 2


def informed_features(td: TensorDictBase) -> torch.Tensor:
    """``(B, 2)``: how rainy (``1 - q``) and how fickle (``f``) the instance is, what the
    ``informed`` baseline reads (docs/memory.md); not the episode's ``armed`` draw (docs/taxi.md).
    """
    inst = td.get(keys.INSTANCE)
    q = inst.get("rainy_probability").reshape(-1, 1).to(torch.float32)
    f = inst.get("fickle_probability").reshape(-1, 1).to(torch.float32)
    return torch.cat([1.0 - q, f], dim=-1)


def _informed(cfg: Any) -> tuple[int, Any]:
    """The ``Family.informed_features`` hook: ``(2, informed_features)``."""
    return INFORMED_DIM, informed_features


def _fields(spec: Any) -> dict[str, Any]:
    inst = taxi_instances(spec)
    return {
        "rain_share": inst.rain_share,
        "q_low": inst.q_low,
        "q_high": inst.q_high,
        "fickle_share": inst.fickle_share,
        "f_low": inst.f_low,
        "f_high": inst.f_high,
        "points": None if inst.points is None else [list(p) for p in inst.points],
    }


def _make_instances(fields: dict[str, Any]) -> TaxiInstances:
    """Fields -> :class:`TaxiInstances`; ``rainy_probability=q`` pins the rain (always, at q;
    1.0: dry) and ``fickle_probability=f`` the passenger (always fickle at f; 0.0: never)."""
    fields = dict(fields)
    if "rainy_probability" in fields:
        q = float(fields.pop("rainy_probability"))
        fields.update(rain_share=1.0 if q < 1.0 else 0.0, q_low=q, q_high=q)
    if "fickle_probability" in fields:
        f = float(fields.pop("fickle_probability"))
        fields.update(fickle_share=1.0 if f > 0.0 else 0.0, f_low=f, f_high=f)
    return taxi_instances(fields)


def _oracle(cfg: Any) -> Any:
    """The exact oracle (``families/taxi/oracle.py``): 500 states, any encoding (learnt heads are read at
    every state through their observation)."""
    from taskvar_torch.families.taxi.oracle import TaxiOracle

    return TaxiOracle(
        gamma=cfg.train.gamma,
        horizon=_section(cfg).horizon,
        train_instances=cfg.env.instances,
        mu_temperature=cfg.train.mu_bar_temperature if cfg.train.mu_bar == "softmax" else None,
        obs_encoding=_section(cfg).obs_encoding,
    )


def _averaging_optimum(cfg: Any) -> torch.Tensor:
    from taskvar_torch.families.taxi.oracle import TaxiOracle

    return TaxiOracle(gamma=cfg.train.gamma, train_instances=cfg.env.instances).averaging_policy()


def oracle_summary(heads: Any, cfg: Any) -> list[str]:
    """Every learnt controller's exact expected return on the training instances beside the same
    controller on the oracle's own tables and the per-instance optimum (printed after training)."""
    oracle = _oracle(cfg)
    if oracle is None:
        return []
    from taskvar_torch.factory import make_method_controller
    from taskvar_torch.families.taxi.subtasks import TaxiSubtasks

    heads = heads.cpu()
    dist = cfg.env.instances
    lines = [
        f"exact expected returns on the training instances ({dist}), Taxi-v4 starts:",
        f"  {'method':<13} {'learnt':>8} {'oracle':>8} {'fires/ep':>9}",
    ]
    for m in ("averaging", "options", "interruption"):
        ctrl = make_method_controller(cfg, m, heads, TaxiSubtasks())
        learnt = float(oracle.controller_expected_return(ctrl, dist))
        best = float(oracle.controller_expected_return(m, dist))
        fires = (
            ""
            if m != "interruption"
            else f"{float(oracle.controller_expected_return(ctrl, dist, count_fires=True)):9.3f}"
        )
        lines.append(f"  {m:<13} {learnt:8.3f} {best:8.3f} {fires}")
    optimum = float(oracle.expected_optimal_return(dist))
    lines.append(f"  per-instance optimum (knows q and f): {optimum:8.3f}")
    return lines


TESTS = {
    "train": TestDistribution(
        "fresh training instances: rain on half the episodes (q in [0.7, 0.9]), a fickle "
        "passenger on half (f in [0.2, 0.4])"
    ),
    "dry": TestDistribution("classic Taxi: no rain, no fickle passenger", "dry"),
    "heavy_rain": TestDistribution(
        "always rain, heavier than trained (q in [0.5, 0.7]), never fickle", "heavy_rain"
    ),
    "fickle": TestDistribution(
        "dry, a passenger who changes their mind far more often (f in [0.8, 1.0])", "fickle"
    ),
    "storm": TestDistribution("heavy rain and a very fickle passenger together", "storm"),
    "gymnasium": TestDistribution(
        "Taxi-v4's own rainy fickle instance (q = 0.8, f = 0.3)", "gymnasium"
    ),
    "heldout": TestDistribution(
        "sealed held-out episodes: the training distribution under the held-out seed",
        seed=HELDOUT_SEED,
    ),
}
"""Taxi test distributions (docs/taxi.md)."""


FAILED_BELOW = -100.0
"""A Taxi training seed whose mean return per episode is below -100 failed
(``Family.failed_below``, docs/report.md#failed-seeds), chosen from the reward and the dynamics
alone: -1 a step, +20 for the delivery (instead of the step's -1), -10 an illegal pickup or
dropoff (``dynamics.py``); an episode ends only by the delivery or at ``env.taxi.horizon`` (200 in
configs/taxi.yaml). One that never delivers thus returns -200 or less, and -100 is half of it: a
seed below it pays more than 100 an episode in steps (an illegal action counts 10) beyond what its
deliveries earn (21 each), as one that never delivers in half its episodes and breaks even on the
others. Rain alone never brings a seed there: the exact per-instance optimum of the hardest
instance a Taxi test draws (q = 0.5, ``heavy_rain`` and ``storm``) is -11.5 over Taxi-v4's starts
(``TaxiOracle.optimal_return``). A line at 0 (a delivery just paying for its 21 steps) would call
the exact optimum failed on ``heavy_rain`` (-4.42) and ``storm`` (-1.39), so it is not one."""

GYM_IDS = {"taskvar/Taxi-v0": ("taskvar_torch.families.taxi.gym_env:TaxiGymEnv", {})}
"""The Taxi family's Gymnasium id."""


def family() -> Family:
    """The Taxi :class:`Family` (the package's ``taskvar_torch.families`` entry point)."""
    return Family(
        name=NAME,
        description="Gymnasium's Taxi-v4: rain and a fickle passenger hidden (Dietterich's MAXQ)",
        env_class=TaxiEnv,
        env_kwargs=_env_kwargs,
        subtasks=_subtasks,
        instance_names=TaxiInstances.NAMES,
        config_class=TaxiConfig,
        tests=TESTS,
        instance_fields=_fields,
        make_instances=_make_instances,
        shift_aliases=("rainy_probability", "fickle_probability"),
        instance_dim=INSTANCE_DIM,
        instance_features=instance_features,
        informed_features=_informed,
        oracle=_oracle,
        oracle_summary=oracle_summary,
        averaging_optimum=_averaging_optimum,
        grid_side=lambda cfg: 5,
        cells=lambda cfg: 25,
        observation=lambda cfg: _section(cfg).obs_encoding,
        gym_ids=GYM_IDS,
        failed_below=FAILED_BELOW,
    )


__all__ = [
    "INFORMED_DIM",
    "INSTANCE_DIM",
    "NAME",
    "TESTS",
    "TaxiConfig",
    "family",
    "informed_features",
    "instance_features",
    "oracle_summary",
]
