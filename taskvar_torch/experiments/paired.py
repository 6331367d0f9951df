"""Paired episodes of a bundle's methods (``taskvar eval``, docs/evaluation.md): which methods,
which episode seed, the play loop every method runs on the same episodes, and the exact regret
where the family's oracle can afford it. :mod:`~taskvar_torch.experiments.bundle_eval` and
:mod:`~taskvar_torch.experiments.regret_frames` both play through it."""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torchrl.envs import TransformedEnv
from torchrl.modules import RandomPolicy

from taskvar_torch import keys, rng
from taskvar_torch.config import METHODS, Config
from taskvar_torch.contract import family, sealed_episode_seed
from taskvar_torch.controllers import Controller
from taskvar_torch.experiments.baselines import (
    missing_baseline_error,
)
from taskvar_torch.experiments.evaluation import mean_ci95, run_episodes
from taskvar_torch.experiments.shift import EvalPoint
from taskvar_torch.factory import (
    make_env,
)
from taskvar_torch.heads.bundle import Heads
from taskvar_torch.heads.informed import informed_features
from taskvar_torch.heads.recurrent import BASELINES
from taskvar_torch.oracle.episodes import exact_episode_returns, optimal_episode_returns
from taskvar_torch.subtasks.base import Subtasks


def parse_methods(
    spec: str,
    subtasks: Subtasks,
    heads: Heads,
    baselines: Sequence[str] = (),
    checkpoint: str | os.PathLike = "final.pt",
) -> list[str]:
    """``all``, one method or a comma list -> the methods, in the paper's order, then the
    ``baselines`` (docs/memory.md) whose files sit beside ``checkpoint``. ``all`` is every method
    the bundle supports (the hierarchy needs a composition hierarchy and robustness critics);
    naming an unsupported or unknown one is a one-line error."""
    can_compose = subtasks.hierarchy is not None and heads.has("robustness")
    paper = [m for m in METHODS if m != "hierarchy" or can_compose]
    if spec == "all":
        return paper + [m for m in BASELINES if m in baselines]
    names = [m.strip() for m in spec.split(",") if m.strip()]
    for m in names:
        if m not in METHODS and m not in BASELINES:
            raise ValueError(
                f"--method must be 'all' or among {list(METHODS) + list(BASELINES)}, got {m!r}"
            )
        if m in BASELINES and m not in baselines:
            supported = paper + [b for b in BASELINES if b in baselines]
            raise missing_baseline_error(checkpoint, m, supported)
    if "hierarchy" in names and not can_compose:
        raise ValueError(
            "method 'hierarchy' needs robustness heads and a composition hierarchy, which this "
            "bundle does not have; use averaging, options or interruption"
        )
    return [m for m in (*METHODS, *BASELINES) if m in names]


def episode_seed(cfg: Config, test: str, seed: int | None) -> int:
    """The seed of the test episodes (docs/evaluation.md): ``seed``, by default the bundle's ``seed
    + 1``; a held-out distribution plays only its sealed seed, drawn apart per training seed
    (another ``seed`` is a one-line error).
    """
    if seed is not None:
        seed = rng.check_seed(seed, "--seed")  # 32-bit keys: a larger seed is refused, not wrapped
    sealed = family(cfg).tests[test].seed
    if sealed is None:
        return int(cfg.seed) + 1 if seed is None else int(seed)
    own = sealed_episode_seed(sealed, int(cfg.seed))
    if seed is not None and int(seed) != own:
        raise ValueError(
            f"--test {test} plays its sealed held-out seed (drawn for the bundle's training seed "
            f"{int(cfg.seed)}); drop --seed {seed}"
        )
    return own


def check_fits(point: EvalPoint, heads: Heads, subtasks: Subtasks, env: Any) -> None:
    """The shifted env must keep the bundle's observation, actions and options."""
    obs = int(env.observation_spec[keys.OBSERVATION].shape[-1])
    spec = getattr(heads, "spec", None)
    want = None if spec is None else (spec.obs_dim, spec.num_actions)
    got = (obs, int(env.action_spec.space.n))
    where = point.label or "the test distribution"
    if want is not None and got != want:
        raise ValueError(
            f"{where} gives observations of {got[0]} values and {got[1]} actions; the bundle "
            f"was trained on {want[0]} and {want[1]}"
        )
    if tuple(subtasks.names) != tuple(heads.option_names):
        raise ValueError(
            f"{where} has options {list(subtasks.names)}; the bundle's are "
            f"{list(heads.option_names)}"
        )


def check_baseline_fits(point: EvalPoint, ctrl: Any, env: Any) -> None:
    """A baseline's network must fit the test point's observations, actions and (``informed``)
    instance features; ``env`` is a probe of the point."""
    where = point.label or "the test distribution"
    got = (int(env.observation_spec[keys.OBSERVATION].shape[-1]), int(env.action_spec.space.n))
    want = (ctrl.spec.obs_dim, ctrl.spec.num_actions)
    if got != want:
        raise ValueError(
            f"{where} gives observations of {got[0]} values and "
            f"{got[1]} actions; the {ctrl.name} baseline was trained on {want[0]} and {want[1]}"
        )
    if ctrl.spec.instance_dim:  # informed: e.g. a Wargus shift in the number of items
        dim, _ = informed_features(point.cfg)
        if dim != ctrl.spec.instance_dim:
            raise ValueError(
                f"{where} gives {dim} instance features; the {ctrl.name} baseline was trained "
                f"on {ctrl.spec.instance_dim}"
            )


def point_oracle(cfg: Config, point: EvalPoint) -> Any:
    """The exact oracle of a test point, where the family brings one (``Family.oracle``) and it
    covers the point's env (windy: small one-hot layouts)."""
    fam = family(cfg)
    return None if fam.oracle is None else fam.oracle(point.cfg)


def affordable(oracle: Any, instance: dict[str, np.ndarray]) -> bool:
    """Whether the oracle's exact returns of these episodes are cheap: the distinct instances it
    would solve (``oracle.exact_solves(*fields)``, else the distinct field tuples) within its
    ``max_exact_solves`` (no such attribute: always)."""
    limit = getattr(oracle, "max_exact_solves", None)
    if limit is None:
        return True
    fields = [np.asarray(instance[k]) for k in oracle.instance_keys]
    count = getattr(oracle, "exact_solves", None)
    n = count(*fields) if count is not None else len(np.unique(np.stack(fields, 1), axis=0))
    return n <= limit


def exact_regret(
    oracle: Any,
    ctrl: Controller,
    cfg: Config,
    instance: dict[str, np.ndarray],
    start: np.ndarray,
    optimum: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray | None, dict[str, float] | None]:
    """A memoryless controller's exact expected return per episode and its regret against the exact
    per-instance optimum (paper §3.3.1), ``optimum`` reused where already known.

    Returns the exact returns, the optimum and ``regret_mean`` with ``regret_ci95`` (``None``
    without an optimum).
    """
    exact_r = exact_episode_returns(oracle, ctrl, cfg, instance, start)
    if optimum is None and hasattr(oracle, "optimal_return"):
        optimum = optimal_episode_returns(oracle, instance, start)
    if optimum is None:
        return exact_r, None, None
    mean, ci = mean_ci95(torch.as_tensor(optimum - exact_r, dtype=torch.float64))
    return exact_r, optimum, {"regret_mean": float(mean), "regret_ci95": ci}


def play(
    policy: Any,
    point: EvalPoint,
    episodes: int,
    seed: int,
    batch_size: int,
    noise_seed: int | None = None,
    progress: Any = None,
    steps: Sequence[str] = (),
) -> dict[str, np.ndarray]:
    """Play ``episodes`` episodes (global indices ``0..episodes-1``) of ``point`` with ``policy``:
    the one episode player of ``taskvar eval``, Figure 2, the scale experiment and the baselines.

    Sub-env ``i`` of a batch is global episode ``lo + i`` of envs seeded ``seed``, so every policy
    meets the same instance, start and noise per episode whatever ``batch_size``
    (docs/evaluation.md). Returns per-episode ``return``, ``length``, ``interruptions``,
    ``instance_<field>``, ``start`` and ``steps_<o>``; ``steps``: keys also traced per step as
    ``step_<key> (episodes, horizon)`` beside ``step_alive``.
    """
    parts: dict[str, list[np.ndarray]] = {}
    option_level = isinstance(policy, Controller) and policy.name != "averaging"
    O = len(policy.heads.option_names) if option_level else 0  # noqa: E741
    trace = ((keys.OPTION,) if option_level else ()) + tuple(k for k in steps if k != keys.OPTION)
    for lo in range(0, int(episodes), batch_size):
        n = min(batch_size, int(episodes) - lo)
        base = make_env(
            point.cfg,
            n,
            seed=seed,
            index_offset=lo,
            instances=point.instances,
            noise_seed=noise_seed,
            validate_actions=False,
        )
        if isinstance(policy, RandomPolicy):
            policy = RandomPolicy(base.action_spec)
        env = TransformedEnv(base, policy.primer()) if hasattr(policy, "primer") else base
        out = run_episodes(env, policy, max_steps=int(base.horizon), trace_keys=trace)
        got = {k: out[k] for k in ("return", "length", "interruptions")}
        for k, v in out[keys.INSTANCE].items():
            if v.dim() == 1:  # scalar instance fields (windy p, direction; Wargus seed)
                got[f"instance_{k}"] = v
        if "start" in out.keys():
            got["start"] = out["start"]
        tr = out["trace"] if trace else None
        if option_level:
            opt = torch.where(tr["alive"], tr[keys.OPTION], torch.full_like(tr[keys.OPTION], -1))
            for o in range(O):
                got[f"steps_{o}"] = (opt == o).sum(-1)
        if steps:  # padded to the horizon: batches end at different steps
            pad = int(base.horizon) - tr["alive"].shape[-1]
            got["step_alive"] = torch.nn.functional.pad(tr["alive"], (0, pad), value=False)
            for k in steps:
                got[f"step_{k}"] = torch.nn.functional.pad(tr[k], (0, pad))
        for k, v in got.items():
            parts.setdefault(k, []).append(v.detach().cpu().numpy())
        if progress is not None:
            progress.update(n)
    return {k: np.concatenate(v) for k, v in parts.items()}
