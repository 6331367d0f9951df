"""Experience collection for :func:`~taskvar_torch.training.train`: the training env and the
collector of ``cfg.collector`` (one process, W processes or W Ray actors, the same ``(N, T)`` batch;
docs/design.md#many-processes-and-ray-actors).
"""

from __future__ import annotations

import copy
import functools
import os

import torch
from torchrl.collectors import BaseCollector, Collector, MultiSyncCollector
from torchrl.envs import Compose, EnvBase, InitTracker, RewardSum, TransformedEnv
from torchrl.weight_update import SharedMemWeightSyncScheme

from taskvar_torch import rng
from taskvar_torch.config import Config
from taskvar_torch.factory import check_family_installed, make_env
from taskvar_torch.heads.behaviour import BehaviourPolicy


def make_training_env(
    cfg: Config, num_envs: int | None = None, index_offset: int = 0
) -> TransformedEnv:
    """The family env with ``InitTracker`` (new-episode flags) and ``RewardSum`` (episode returns)."""
    env = make_env(cfg, num_envs=num_envs, index_offset=index_offset)
    return TransformedEnv(env, Compose(InitTracker(), RewardSum()))


def make_worker_env(cfg: Config, worker: int) -> TransformedEnv:
    """Collector process ``worker``'s training env, sub-envs ``[worker * n, (worker + 1) * n)``;
    also seeds the worker's global torch RNG.
    """
    n = cfg.env.num_envs // cfg.collector.num_workers
    torch.manual_seed(rng.hash32(rng.hash32(cfg.seed & rng.MASK32) + worker + 1))
    return make_training_env(cfg, num_envs=n, index_offset=worker * n)


def collects_in_workers(cfg: Config) -> bool:
    """Whether the envs run outside the trainer's process (then weights are synced after every
    update phase and no exact resume).
    """
    return cfg.collector.num_workers > 1 or cfg.collector.backend == "ray"


def make_collector(
    cfg: Config, env: EnvBase, behaviour: BehaviourPolicy, total_frames: int, seeds: int = 1
) -> BaseCollector:
    """The experience collector of ``cfg.collector``: TorchRL's ``Collector`` on ``env``, or a
    ``MultiSyncCollector`` over :func:`make_worker_env` slices with shared-memory weights.
    ``seeds``: ``train.frames_per_batch`` frames per seed (one process only).
    """
    t = cfg.train
    workers = cfg.collector.num_workers
    ray = cfg.collector.backend == "ray"
    if workers > 1 or ray:  # new processes: they must find the family by its name
        check_family_installed(
            cfg, "collector.backend=ray" if ray else f"collector.num_workers={workers}"
        )
    if ray:
        return make_ray_collector(cfg, behaviour, total_frames)
    if workers == 1:
        return Collector(
            env,
            behaviour,
            frames_per_batch=t.frames_per_batch * seeds,
            total_frames=total_frames,
            track_traj_ids=False,
        )
    return MultiSyncCollector(
        [functools.partial(make_worker_env, cfg, w) for w in range(workers)],
        copy.deepcopy(behaviour),  # the acting copy: the learner's weights stay private
        frames_per_batch=t.frames_per_batch,
        total_frames=total_frames,
        device=cfg.device,
        cat_results=0,  # (N, T): worker w's rows are sub-envs [w * n, (w + 1) * n)
        use_buffers=True,
        weight_sync_schemes={"policy": SharedMemWeightSyncScheme()},
        num_threads=torch.get_num_threads(),
        num_sub_threads=torch.get_num_threads(),
    )


def make_ray_collector(cfg: Config, behaviour: BehaviourPolicy, total_frames: int) -> BaseCollector:
    """``collector.backend = ray``: TorchRL's ``Collector(backend="ray")``, one actor per
    :func:`make_worker_env` slice; Ray starts locally unless ``collector.ray_address`` names a
    cluster (every node needs this package).
    """
    try:
        import ray  # noqa: F401
    except ImportError:
        raise ValueError(
            'collector.backend=ray needs Ray: pip install "taskvar-torch[distributed]"'
        ) from None
    workers = cfg.collector.num_workers
    address = cfg.collector.ray_address
    init = {"address": "local", "num_cpus": max(workers, os.cpu_count() or 1)}
    if address is not None:
        init = {"address": address}
    remote = {"num_cpus": 1}
    if torch.device(cfg.device).type == "cuda":
        remote["num_gpus"] = 1.0 / workers
    collector = Collector(
        [functools.partial(make_worker_env, cfg, w) for w in range(workers)],
        copy.deepcopy(behaviour),  # the acting copy, sent to the actors
        backend="ray",
        num_collectors=workers,
        sync=True,
        frames_per_batch=cfg.train.frames_per_batch,
        total_frames=total_frames if total_frames >= 0 else 2**62,  # RayCollector: no -1 (endless)
        device=cfg.device,
        backend_options={
            "ray_init_config": {**init, "include_dashboard": False, "log_to_driver": False},
            "remote_configs": remote,
            "collector_kwargs": {"track_traj_ids": False},
        },
    )
    collector.update_policy_weights_(behaviour)  # the actors start from the learner's weights
    return collector


__all__ = [
    "collects_in_workers",
    "make_collector",
    "make_ray_collector",
    "make_training_env",
    "make_worker_env",
]
