"""Building a training run of the heads from its config, or restoring it from a checkpoint for exact
resume, each entry checked first (:func:`_check_resume_state`; docs/reliability.md).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase

from taskvar_torch import keys
from taskvar_torch.checkpoint import (
    RUNTIME_KEYS,
    CheckpointError,
    config_differences,
    set_rng_state,
)
from taskvar_torch.checkpoint.checks import (
    check_counter,
    check_counters,
    check_like,
    check_optimizer_state,
    check_rng_state,
    load_state_dicts,
)
from taskvar_torch.config import Config
from taskvar_torch.factory import build_heads, make_learner, make_subtasks
from taskvar_torch.heads.behaviour import BEHAVIOUR, BehaviourPolicy
from taskvar_torch.heads.first_visit import FirstVisitFilter
from taskvar_torch.heads.nstep import nstep_returns
from taskvar_torch.heads.seeds import stack_seeds
from taskvar_torch.run_folder import restore_logs
from taskvar_torch.training.collection import make_training_env
from taskvar_torch.training.learning import epsilon_at
from taskvar_torch.training.replay import check_replay_state, load_replay_state, make_replay_buffer
from taskvar_torch.training.run_state import (
    TrainingRun,
    collector_carrier,
    replay_rngs,
    replay_rows,
    run_models,
    seed_config,
)


def check_runtime_only(bundle: dict[str, Any], cfg: Config, path: Any) -> None:
    """Overrides on a resumed run may change only runtime keys (e.g. ``train.total_frames``)."""
    diffs = config_differences(bundle["config"], cfg)
    if diffs:
        key, saved, wanted = diffs[0]
        raise CheckpointError(
            f"cannot resume {str(path)!r} with {key}={wanted!r}: it was trained with {saved!r}; "
            f"only {list(RUNTIME_KEYS)} may change on resume"
        )


def build_run(
    cfg: Config,
    out: Path,
    bundle: dict[str, Any] | None,
    resume: str | os.PathLike | None = None,
) -> TrainingRun:
    """Everything from the config, seeded, then (resuming) overwritten with ``bundle``'s checked
    state.
    """
    t = cfg.train
    S = t.seeds
    torch.manual_seed(cfg.seed)
    replay_generators = [
        torch.Generator(device="cpu").manual_seed(cfg.seed + k + 1) for k in range(S)
    ]
    workers = cfg.collector.num_workers
    env = make_training_env(cfg, num_envs=cfg.env.num_envs * S // workers)  # workers > 1: specs
    subtasks = make_subtasks(cfg, env.base_env)
    if S == 1:
        heads = build_heads(cfg, env, subtasks)
    else:  # seed k's networks initialised as its one-seed run's, then stacked (heads/seeds.py)
        if not hasattr(env.base_env, "set_seed_blocks"):
            raise ValueError(
                f"train.seeds={S} needs a family env with set_seed_blocks (envs/batched.py "
                f"BatchedFamilyEnv); {type(env.base_env).__name__} has none"
            )
        env.base_env.set_seed_blocks([cfg.seed + k for k in range(S)])
        runs = []
        for k in range(S):
            cfg_k = seed_config(cfg, k)
            torch.manual_seed(cfg_k.seed)
            one_env = make_training_env(cfg_k)
            runs.append(build_heads(cfg_k, one_env, make_subtasks(cfg_k, one_env.base_env)))
        heads = stack_seeds(runs)
        heads.spec = runs[0].spec
        torch.manual_seed(cfg.seed)  # exploration: one stream for the batch
    learner = make_learner(cfg, heads, subtasks)
    behaviour = BehaviourPolicy(
        heads,
        subtasks,
        env.action_spec,
        option_prob=t.option_behaviour_prob,
        root_policy=t.hierarchy_root_policy,
        option_coverage=t.option_coverage,
    )
    buffers = [make_replay_buffer(cfg, g) for g in replay_generators]
    obs_dim = env.observation_spec[keys.OBSERVATION].shape[-1]
    first_visit = FirstVisitFilter(cfg.env.num_envs * S, obs_dim, device=cfg.device)
    stats = {
        "return_sum": torch.zeros((), device=cfg.device),
        "episodes": torch.zeros((), device=cfg.device),
        "return_sum_options": torch.zeros((), device=cfg.device),
        "episodes_options": torch.zeros((), device=cfg.device),
    }
    if S > 1:
        stats["seed_return_sum"] = torch.zeros(S, device=cfg.device)
        stats["seed_episodes"] = torch.zeros(S, device=cfg.device)
    run = TrainingRun(
        cfg=cfg,
        out=out,
        env=env,
        learner=learner,
        behaviour=behaviour,
        buffers=buffers,
        first_visit=first_visit,
        replay_generators=replay_generators,
        counters={"frames": 0, "updates": 0, "batches": 0, "stored": 0},
        stats=stats,
    )
    if bundle is not None:
        _check_resume_state(run, bundle, resume)  # every entry, before any is loaded
        load_state_dicts(bundle, models=run_models(learner), optimizers={"adam": learner.optimizer})
        learner.load_state_dict(
            {
                **bundle["learner"],
                "targets": bundle["models"]["targets"],
                "optimizer": bundle["optimizers"]["adam"],
            }
        )
        replays = bundle["replay"]["seeds"] if S > 1 else [bundle["replay"]]
        for buffer, state in zip(buffers, replays):
            load_replay_state(buffer, state)
        first_visit.load_state_dict(bundle["first_visit"])
        run.counters.update(bundle["counters"])
        run.stats = {k: v.to(cfg.device) for k, v in bundle["stats"].items()}
    behaviour.set_epsilon(epsilon_at(run.counters["frames"], t))
    return run


def _check_resume_state(
    run: TrainingRun, bundle: dict[str, Any], resume: str | os.PathLike
) -> None:
    """:class:`CheckpointError` naming the entry unless every entry a resume loads fits what the
    config built.
    """
    learner, t = run.learner, run.cfg.train
    live_learner = {
        k: v for k, v in learner.state_dict().items() if k not in ("targets", "optimizer")
    }
    live_learner["loss_sum"] = None  # None, or each loss's running sum (checked below)
    try:
        check_like(
            bundle["models"], {k: m.state_dict() for k, m in run_models(learner).items()}, "models"
        )
        check_like(bundle["optimizers"], {"adam": None}, "optimizers")
        check_optimizer_state(bundle["optimizers"]["adam"], learner.optimizer, "optimizers['adam']")
        check_like(bundle["learner"], live_learner, "learner")
        for k in ("num_updates", "loss_count"):
            check_counter(bundle["learner"][k], f"learner[{k!r}]")
        params = sum(len(g["params"]) for g in learner.optimizer.param_groups)
        states = len(bundle["optimizers"]["adam"]["state"])
        want = params if bundle["learner"]["num_updates"] > 0 else 0  # every update steps all
        if states != want:
            raise CheckpointError(
                f"optimizers['adam']['state'] holds {states} parameters' state, expected {want} "
                f"after {bundle['learner']['num_updates']} updates"
            )
        loss_sum = bundle["learner"]["loss_sum"]
        if loss_sum is not None and not (
            isinstance(loss_sum, dict)
            and all(isinstance(v, torch.Tensor) and v.numel() == 1 for v in loss_sum.values())
        ):
            raise CheckpointError("learner['loss_sum'] is not a dict of scalar losses")
        check_counters(bundle["counters"], run.counters)
        check_rng_state(bundle["rng"], replay_rngs(run.replay_generators))
        batch = _probe_batch(run)  # (N, 2), as the collector gives it
        stored = batch.copy()
        if t.n_step > 1:  # the n-step keys, as TrainingRun.store adds them
            subtasks = learner.loss.subtasks
            stored = nstep_returns(stored, subtasks, t.gamma, t.n_step, BEHAVIOUR)
        rows = replay_rows(run.cfg, stored)
        if run.seeds == 1:
            check_replay_state(bundle["replay"], rows, t.buffer_size)
        else:
            check_like(bundle["replay"], {"seeds": [None] * run.seeds}, "replay")
            for k, state in enumerate(bundle["replay"]["seeds"]):
                check_replay_state(state, rows, t.buffer_size, f"replay['seeds'][{k}]")
        check_like(bundle["first_visit"], run.first_visit.state_dict(), "first_visit")
        check_like(bundle["stats"], run.stats, "stats")
        check_like(bundle["carrier"], batch[:, -1].exclude(keys.NEXT).to_dict(), "carrier")
    except CheckpointError as e:
        raise CheckpointError(
            f"checkpoint {str(resume)!r} does not fit the run its config builds: {e}"
        ) from None


def _probe_batch(run: TrainingRun) -> TensorDictBase:
    """A collector batch ``(N, 2)`` as this run collects them (two steps of a fresh env)."""
    probe = make_training_env(run.cfg, num_envs=run.env.batch_size[0])
    return probe.rollout(2, policy=run.behaviour, break_when_any_done=False)


def restore_collection(run: TrainingRun, bundle: dict[str, Any], resume: str | os.PathLike) -> None:
    """The checkpoint's env state, collector carrier and replay RNG, and the logs cut back to the
    checkpoint.
    """
    carrier = collector_carrier(run.collector)
    try:
        check_like(bundle["env"], run.env.base_env.state_dict(), "env")
        run.env.base_env.load_state_dict(bundle["env"])  # its values' ranges: one line
    except (CheckpointError, ValueError) as e:
        raise CheckpointError(
            f"checkpoint {str(resume)!r} does not fit the run its config builds: {e}"
        ) from None
    carrier.update(TensorDict(bundle["carrier"], batch_size=run.env.batch_size))
    set_rng_state(bundle["rng"], replay_rngs(run.replay_generators))
    restore_logs(Path(resume).parent, run.out, run.counters["frames"])
    if Path(resume).parent.resolve() == run.out.resolve() and Path(resume).name.startswith(
        "checkpoint_"
    ):
        run.last_checkpoint = Path(resume)


__all__ = ["build_run", "check_runtime_only", "restore_collection"]
