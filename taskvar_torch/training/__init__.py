"""Offline training of every head from one stream of experience (paper §3.1-3.4;
docs/design.md#training-the-heads).

The loop (:func:`train`)::

    env (batched family, instances redrawn at every reset) + InitTracker + RewardSum
    --Collector(BehaviourPolicy)--> raw transitions --ReplayBuffer(LazyTensorStorage)--> one shared
    sample --MultiHeadLearner--> every head (averaging, options, switching, max-value, robustness)
    --> CSV logs, periodic checkpoints, DIR/final.pt

The loop is :func:`~taskvar_torch.training.learning.collect_and_learn`; the run it drives is
:mod:`~taskvar_torch.training.run_state`, built or restored by
:mod:`~taskvar_torch.training.run_setup`, collected by :mod:`~taskvar_torch.training.collection`. A
checkpoint holds everything the run draws from, so ``train(..., resume=ckpt)`` continues bit for bit
on CPU (one collector process).
"""

from __future__ import annotations

import os
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from taskvar_torch.checkpoint import (
    CheckpointError,
    load_checkpoint,
    require_entries,
    require_finite_heads,
)
from taskvar_torch.config import Config, apply_overrides, config_from_dict, save_config_yaml
from taskvar_torch.config.memory import check_memory
from taskvar_torch.config.memory import estimate as estimate_memory
from taskvar_torch.contract import family
from taskvar_torch.factory import HEADS_NAME, check_device, write_heads
from taskvar_torch.progress import progress_bar
from taskvar_torch.run_folder import (
    RUN_FILES,
    ResultsFolder,
    StopSignals,
    check_output_folder,
    last_checkpoint_note,
)
from taskvar_torch.training.collection import collects_in_workers, make_collector
from taskvar_torch.training.learning import collect_and_learn
from taskvar_torch.training.run_logs import RunLoggers, check_logger
from taskvar_torch.training.run_setup import build_run, check_runtime_only, restore_collection


def train(
    cfg: Config | None,
    out_dir: str | os.PathLike,
    resume: str | os.PathLike | None = None,
    overrides: Sequence[str] = (),
    progress: bool = True,
    overwrite: bool = False,
    keep_replay: bool = True,
) -> dict[str, Any]:
    """Train every head of ``cfg``'s family; write logs, checkpoints and ``out_dir/final.pt``.

    Args:
        cfg: the run's config; with ``resume`` it may be ``None`` (the checkpoint's config is used)
            or must equal the checkpoint's up to runtime keys such as ``train.total_frames``.
        out_dir: results folder (docs/reliability.md#results-folders-locked-staged-swapped-whole).
        resume: a checkpoint written by this function inside ``out_dir`` to continue from, exactly.
        overrides: ``key.sub=value`` applied to the checkpoint's config when ``cfg`` is ``None``.
        progress: show a progress bar (plain lines when stderr is not a terminal).
        overwrite: remove the run already in ``out_dir`` first.
        keep_replay: ``False``: ``final.pt`` holds no replay buffer (it evaluates but cannot be
            resumed); periodic checkpoints always hold it.

    Returns: ``{"final": path, "frames": int, "updates": int, "seconds": float, "last_log": dict}``.

    Raises:
        ValueError: an unusable ``out_dir`` or device, or a run already there; nothing is written.
        CheckpointError: an unreadable, foreign or non-finite ``resume`` checkpoint, or one of a
            family declared ``resumable=False``.
        TrainingDiverged: a loss or a weight became NaN or infinite; the last checkpoint is intact.
        TrainingInterrupted: SIGINT or SIGTERM; the run wrote a checkpoint after its current batch.
    """
    # written in place (its checkpoints resume there), never over another run unless overwrite
    folder = ResultsFolder(out_dir, overwrite, markers=RUN_FILES, staged=False, resume=resume)
    out = folder.out  # not '': it would be the current folder
    check_output_folder(out)  # inputs first: a refused run writes nothing
    bundle = None
    if resume is not None:
        bundle = load_checkpoint(resume, expected_config=cfg)
        member = bundle.get("batch_member")
        if isinstance(member, dict):
            raise CheckpointError(
                f"{str(resume)!r} is seed index {member.get('seed_index')} of a "
                f"{member.get('seeds')}-seed batch: it evaluates, it does not resume alone; "
                f"resume the batch from {str(Path(resume).resolve().parent.parent)!r}'s "
                "checkpoint_*.pt or final.pt"
            )
        require_finite_heads(bundle, resume)
        if cfg is None:
            cfg = apply_overrides(
                config_from_dict(bundle["config"], f"checkpoint {resume}"), overrides
            )
            check_runtime_only(bundle, cfg, resume)
    if cfg is None:
        raise ValueError("train needs a config (or a checkpoint to resume)")
    if resume is not None and not family(cfg).resumable:
        raise CheckpointError(
            f"cannot resume {str(resume)!r}: family {cfg.family!r} is not resumable (its envs' "
            "state is not in a checkpoint); start a new run, or evaluate this checkpoint"
        )
    check_device(cfg.device)
    check_memory(estimate_memory(cfg))  # before anything is allocated or written
    check_logger(cfg.train.logger)
    workers = cfg.collector.num_workers
    remote = collects_in_workers(cfg)
    if bundle is not None and "replay" not in bundle:
        raise CheckpointError(
            f"cannot resume {str(resume)!r}: it holds no replay buffer (written with "
            "keep_replay=False); it can be evaluated, not continued"
        )
    if bundle is not None:
        require_entries(bundle, resume)  # a damaged or edited bundle: one line, not a KeyError
    if bundle is not None and remote:
        raise CheckpointError(
            f"cannot resume {str(resume)!r}: exact resume needs collector.num_workers=1 and "
            f"collector.backend=process, got {workers} and {cfg.collector.backend!r} (the "
            "workers' env and RNG states are not checkpointed)"
        )
    if resume is not None and overwrite and Path(resume).resolve().parent == out.resolve():
        raise ValueError(
            f"--overwrite would delete {str(resume)!r}, the checkpoint being resumed; drop "
            "--overwrite to continue the run in its folder"
        )
    folder.acquire()
    started = False

    def on_start() -> None:
        nonlocal started
        started = True

    try:
        return _train_loop(cfg, out, bundle, resume, progress, on_start, keep_replay)
    except BaseException:
        if not started:
            folder.abandon()  # a run that never started leaves nothing behind
        raise
    finally:
        folder.commit()  # unlock: the run's files stay (an interrupted run resumes from them)


def _train_loop(
    cfg: Config,
    out: Path,
    bundle: dict[str, Any] | None,
    resume: str | os.PathLike | None,
    progress: bool,
    on_start: Any,
    keep_replay: bool = True,
) -> dict[str, Any]:
    """:func:`train` once its inputs are checked and ``out`` is held: build (or restore) the run,
    then :func:`~taskvar_torch.training.learning.collect_and_learn` until ``train.total_frames``.
    """
    t = cfg.train
    save_config_yaml(cfg, out / "config.yaml")
    run = build_run(cfg, out, bundle, resume)
    threads = torch.get_num_threads()
    with warnings.catch_warnings():  # TorchRL's note that the last batch may pass total_frames
        warnings.filterwarnings("ignore", message=r"total_frames \(\d+\) is not exactly divisible")
        run.collector = make_collector(
            cfg,
            run.env,
            run.behaviour,
            max(t.total_frames - run.counters["frames"], 0) * t.seeds,
            seeds=t.seeds,
        )
    pbar = loggers = None
    try:  # shut the worker processes down on any exit
        if bundle is not None:  # after the collector's own reset and policy probe
            restore_collection(run, bundle, resume)
        loggers = RunLoggers(t.logger, out)
        pbar = progress_bar(
            total=t.total_frames,
            initial=run.counters["frames"],
            disable=not progress,
            desc="train",
            unit="frame",
        )
        start_time = time.perf_counter()
        on_start()
        with StopSignals() as stop:
            try:
                last_log = collect_and_learn(
                    run,
                    run.collector,
                    pbar,
                    lambda before: run.report(before, stop, loggers, pbar, start_time),
                )
                final = out / "final.pt"  # a first signal from here on: the run ends normally
                run.save(final, replay=keep_replay)
                if t.seeds == 1:
                    write_heads(out / HEADS_NAME, run.learner.eval_heads, cfg, run.counters)
                else:  # the batch's final.pt resumes; each seed<k>/ evaluates
                    seed_finals = run.write_seed_bundles()
            except KeyboardInterrupt:
                raise KeyboardInterrupt(
                    f"aborted by a second signal; nothing written, "
                    f"{last_checkpoint_note(run.last_checkpoint)}"
                ) from None
    finally:
        if pbar is not None:
            pbar.close()  # before any message: the bar's last line does not run into it
        if loggers is not None:
            loggers.close()  # TensorBoard, W&B and MLflow write their last rows here
        run.collector.shutdown()
        torch.set_num_threads(threads)  # MultiSyncCollector.shutdown adds num_workers threads
    result = {
        "final": final,
        "frames": run.counters["frames"],
        "updates": run.counters["updates"],
        "seconds": time.perf_counter() - start_time,
        "last_log": last_log,
    }
    if t.seeds > 1:
        result["seeds"] = seed_finals
    return result


__all__ = ["train"]
