"""Experience collection for :func:`~taskvar_torch.training.train` (docs/design.md, "Many processes
and Ray actors"): the training env and the collector of ``cfg.collector``.

* one process (``collector.num_workers = 1``): TorchRL's ``Collector`` on the whole batched env,
  acting with the learner's own behaviour policy;
* ``W > 1`` processes: TorchRL's ``MultiSyncCollector``, worker ``w`` stepping sub-envs
  ``[w N/W, (w+1) N/W)`` of the keyed streams (:func:`make_worker_env`), so the W workers draw
  exactly the one-process env's instances, starts and gusts; their batches are concatenated in
  worker order into the same ``(N, T)`` batch, and the learner's weights reach the workers through
  ``SharedMemWeightSyncScheme``;
* ``collector.backend = ray``: the same W slices as Ray actors (TorchRL ``Collector(backend="ray")``,
  ``RayWeightSyncScheme``).
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
    """Collector process ``worker``'s training env: sub-envs ``[worker * n, (worker + 1) * n)``.

    Runs inside the worker (a picklable ``functools.partial`` of this function): it also seeds
    the worker's global torch RNG, which the behaviour policy's exploration draws from.
    """
    n = cfg.env.num_envs // cfg.collector.num_workers
    torch.manual_seed(rng.hash32(rng.hash32(cfg.seed & rng.MASK32) + worker + 1))
    return make_training_env(cfg, num_envs=n, index_offset=worker * n)


def collects_in_workers(cfg: Config) -> bool:
    """Whether the envs run outside the trainer's process (worker processes or Ray actors): then
    the trainer syncs weights to them after every update phase, and their env and RNG states are
    not in the checkpoint (no exact resume)."""
    return cfg.collector.num_workers > 1 or cfg.collector.backend == "ray"


def make_collector(
    cfg: Config, env: EnvBase, behaviour: BehaviourPolicy, total_frames: int, seeds: int = 1
) -> BaseCollector:
    """The experience collector of ``cfg.collector``.

    One process: TorchRL's ``Collector`` on ``env`` with ``behaviour`` itself. Several: a
    ``MultiSyncCollector`` over :func:`make_worker_env` slices, acting with a copy of
    ``behaviour`` whose weights live in shared memory; the trainer refreshes them with
    ``collector.update_policy_weights_(behaviour)``. Worker processes use as many threads as
    this one. ``seeds`` (``train.seeds``): ``env`` holds every seed's sub-envs, and a batch is
    ``train.frames_per_batch`` frames per seed (one process only).
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
    """``collector.backend = ray``: TorchRL's ``Collector(backend="ray")`` (a ``RayCollector``).

    Worker w is a Ray actor (1 CPU; a share of a GPU when ``device`` is CUDA) running a TorchRL
    ``Collector`` over :func:`make_worker_env` slice w with a copy of ``behaviour``; ``sync=True``
    gathers one ``(n, T)`` batch per actor each iteration (the trainer flattens them to ``(N, T)``,
    worker order) and ``collector.update_policy_weights_(behaviour)`` sends the learner's weights
    and epsilon (``RayWeightSyncScheme``). Ray starts locally (``address="local"``, never a
    cluster found in ``RAY_ADDRESS``) unless ``collector.ray_address`` names one; a Ray already
    running in the process is reused. On a cluster every node needs this package installed.
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
