"""The recurrent baseline's cost beside the averaging head's, measured side by side in one run
(issue 31, item 6; docs/memory.md), single-threaded CPU (``torch.set_num_threads(1)``).

Training frames/s, same config and frame budget for each (default configs/windy.yaml, frames
``--frames``, no checkpoints):

- ``paper heads``: ``taskvar train`` (``taskvar_torch.training.train``): the averaging head is trained
  there, with the option, switching and max-value heads, from one stream (the project's trainer);
- ``feed-forward``: the informed baseline's loop (TorchRL ``Collector``, ``DQNLoss(double_dqn)``,
  uniform replay): a feed-forward DQN like the averaging head, through the same TorchRL pieces as
  the recurrent one, so the ratio isolates what recurrence costs;
- ``recurrent``: the GRU baseline (``SliceSampler`` slices, recurrent-mode loss).

Decision latency, per step including the network forward (the ``controller(td)`` path): the
averaging controller on an averaging head (2 x 64 MLP, as configs/windy.yaml) and the recurrent
controller (GRU 64, MLP 64, the defaults), at B=1 (real-time control) and B=16384. Best of
``--repeats`` runs, wall clock and this thread's CPU time (``time.thread_time``: robust to other
jobs on a loaded machine); ratios are recurrent / averaging.

Usage::

    python benchmarks/recurrent.py [--config configs/windy.yaml] [--frames 20480] [--quick]
"""

from __future__ import annotations

import argparse
import tempfile
import time

import torch
from tensordict import TensorDict

from taskvar_torch import keys
from taskvar_torch.config import BaselineConfig, load_config
from taskvar_torch.controllers import AveragingController
from taskvar_torch.heads.bundle import Heads
from taskvar_torch.heads.networks import make_head
from taskvar_torch.heads.recurrent import (
    PREV_ACTION,
    PREV_REWARD,
    RECURRENT_STATE,
    BaselineController,
    BaselineSpec,
    make_recurrent_qnet,
)
from taskvar_torch.training import train
from taskvar_torch.training.baselines import train_baseline


def best_of(fn, iters: int, repeats: int) -> tuple[float, float]:
    """Best-of-``repeats`` seconds per call of ``fn``: ``(wall, this thread's CPU time)``."""
    for _ in range(max(2, iters // 10)):
        fn()
    wall = cpu = float("inf")
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.thread_time()
        for _ in range(iters):
            fn()
        wall = min(wall, (time.perf_counter() - t0) / iters)
        cpu = min(cpu, (time.thread_time() - c0) / iters)
    return wall, cpu


def training_rates(cfg_path: str, frames: int) -> dict[str, tuple[float, float]]:
    """Frames/s of the three trainers on the same config and frame budget: ``(per wall second,
    per CPU second of this thread)`` (the CPU figure is robust to other jobs on the machine)."""
    overrides = [
        f"train.total_frames={frames}",
        f"train.init_random_frames={min(frames // 4, 4000)}",
        "train.checkpoint_every=0",
    ]
    cfg = load_config(cfg_path, overrides)
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        t0, c0 = time.perf_counter(), time.thread_time()
        r = train(cfg, f"{tmp}/paper", progress=False, overwrite=True)
        out["paper heads"] = (
            r["frames"] / (time.perf_counter() - t0),
            r["frames"] / (time.thread_time() - c0),
        )
        for method, name in (("informed", "feed-forward"), ("recurrent", "recurrent")):
            t0, c0 = time.perf_counter(), time.thread_time()
            r = train_baseline(cfg, method, f"{tmp}/{method}")
            out[name] = (
                r["frames"] / (time.perf_counter() - t0),
                r["frames"] / (time.thread_time() - c0),
            )
    return out


def latencies(B: int, iters: int, repeats: int) -> dict[str, tuple[float, float]]:
    """Seconds per batched decision (forward included) of the averaging and recurrent
    controllers on the 25-cell one-hot windy observation."""
    S, A = 25, 4
    heads = Heads(
        ("exit_north", "exit_south"), averaging=make_head(keys.ACTION_VALUE, S, A, (64, 64))
    )
    avg = AveragingController(heads)
    hidden = BaselineConfig().hidden
    net, _ = make_recurrent_qnet(S, A, hidden, (64, 64))
    rec = BaselineController(net.eval(), BaselineSpec("recurrent", S, A, (64, 64), hidden=hidden))
    obs = torch.zeros(B, S)
    obs[:, 3] = 1.0
    td_avg = TensorDict({keys.OBSERVATION: obs}, [B])
    td_rec = TensorDict(
        {
            keys.OBSERVATION: obs,
            PREV_ACTION: torch.zeros(B, A),
            PREV_REWARD: torch.zeros(B, 1),
            "is_init": torch.zeros(B, 1, dtype=torch.bool),
            RECURRENT_STATE: torch.zeros(B, 1, hidden),
        },
        [B],
    )
    with torch.inference_mode():
        return {
            "averaging": best_of(lambda: avg(td_avg.clone(False)), iters, repeats),
            "recurrent": best_of(lambda: rec(td_rec.clone(False)), iters, repeats),
        }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default="configs/windy.yaml")
    p.add_argument("--frames", type=int, default=20480)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--quick", action="store_true", help="tiny sizes: a smoke run")
    args = p.parse_args()
    torch.set_num_threads(1)
    frames = 768 if args.quick else args.frames
    big = 256 if args.quick else 16384
    iters1, itersB = (50, 3) if args.quick else (2000, 20)
    repeats = 2 if args.quick else args.repeats

    rates = training_rates(args.config, frames)
    print(f"training, {args.config}, {frames} frames each, 1 thread (per wall s / per CPU s):")
    for name, (w, c) in rates.items():
        print(f"  {name:<14} {w:10.0f} {c:10.0f} frames/s")
    for i, what in ((0, "wall"), (1, "CPU")):
        print(
            f"  {what}: recurrent / paper heads "
            f"{rates['recurrent'][i] / rates['paper heads'][i]:.2f}x, recurrent / feed-forward "
            f"{rates['recurrent'][i] / rates['feed-forward'][i]:.2f}x"
        )
    for B, iters in ((1, iters1), (big, itersB)):
        lat = latencies(B, iters, repeats)
        (aw, ac), (rw, rc) = lat["averaging"], lat["recurrent"]
        print(
            f"decision latency B={B} (wall / CPU): averaging {aw * 1e6:.1f} / {ac * 1e6:.1f} us, "
            f"recurrent {rw * 1e6:.1f} / {rc * 1e6:.1f} us; recurrent / averaging "
            f"{rw / aw:.2f}x / {rc / ac:.2f}x; {B / ac / 1e6:.3f}M vs {B / rc / 1e6:.3f}M "
            "decisions per CPU s"
        )


if __name__ == "__main__":
    main()
