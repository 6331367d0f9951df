"""The recurrent baseline's cost beside the averaging head's, measured side by side in one run
(issue 31, item 6; docs/memory.md), single-threaded CPU (``torch.set_num_threads(1)``).

Training frames/s, same config and frame budget for each (default configs/windy.yaml, frames
``--frames``, no checkpoints):

- ``paper heads``: ``taskvar train`` (``taskvar_torch.train.train``): the averaging head is trained
  there, with the option, switching and max-value heads, from one stream (the project's trainer);
- ``feed-forward``: the informed baseline's loop (TorchRL ``Collector``, ``DQNLoss(double_dqn)``,
  uniform replay): a feed-forward DQN like the averaging head, through the same TorchRL pieces as
  the recurrent one, so the ratio isolates what recurrence costs;
- ``recurrent``: the GRU baseline (``SliceSampler`` slices, recurrent-mode loss).

Decision latency, per step including the network forward (the ``controller(td)`` path): the
averaging controller on an averaging head (2 x 64 MLP, as configs/windy.yaml) and the recurrent
controller (GRU 64, MLP 64, the defaults), at B=1 (real-time control) and B=16384. Best of
``--repeats`` runs, wall clock; ratios are recurrent / averaging.

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
from taskvar_torch.config import load_config
from taskvar_torch.controllers import AveragingController
from taskvar_torch.heads.bundle import Heads
from taskvar_torch.heads.networks import make_head
from taskvar_torch.heads.recurrent import (
    PREV_ACTION,
    RECURRENT_STATE,
    BaselineController,
    BaselineSettings,
    BaselineSpec,
    make_recurrent_qnet,
)
from taskvar_torch.train import train
from taskvar_torch.train_recurrent import train_baseline


def best_of(fn, iters: int, repeats: int) -> float:
    """Best-of-``repeats`` seconds per call of ``fn``."""
    for _ in range(max(2, iters // 10)):
        fn()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(iters):
            fn()
        best = min(best, (time.perf_counter() - t0) / iters)
    return best


def training_rates(cfg_path: str, frames: int) -> dict[str, float]:
    """Frames/s of the three trainers on the same config and frame budget."""
    overrides = [
        f"train.total_frames={frames}",
        f"train.init_random_frames={min(frames // 4, 4000)}",
        "train.checkpoint_every=0",
    ]
    cfg = load_config(cfg_path, overrides)
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        r = train(cfg, f"{tmp}/paper", progress=False, overwrite=True)
        out["paper heads"] = r["frames"] / (time.perf_counter() - t0)
        for method, name in (("informed", "feed-forward"), ("recurrent", "recurrent")):
            t0 = time.perf_counter()
            r = train_baseline(cfg, method, f"{tmp}/{method}")
            out[name] = r["frames"] / (time.perf_counter() - t0)
    return out


def latencies(B: int, iters: int, repeats: int) -> dict[str, float]:
    """Seconds per batched decision (forward included) of the averaging and recurrent
    controllers on the 25-cell one-hot windy observation."""
    S, A = 25, 4
    heads = Heads(
        ("exit_north", "exit_south"), averaging=make_head(keys.ACTION_VALUE, S, A, (64, 64))
    )
    avg = AveragingController(heads)
    settings = BaselineSettings()
    net, _ = make_recurrent_qnet(S, A, settings)
    rec = BaselineController(net.eval(), BaselineSpec("recurrent", S, A, settings))
    obs = torch.zeros(B, S)
    obs[:, 3] = 1.0
    td_avg = TensorDict({keys.OBSERVATION: obs}, [B])
    td_rec = TensorDict(
        {
            keys.OBSERVATION: obs,
            PREV_ACTION: torch.zeros(B, A),
            "is_init": torch.zeros(B, 1, dtype=torch.bool),
            RECURRENT_STATE: torch.zeros(B, 1, settings.hidden),
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
    frames = 1024 if args.quick else args.frames
    big = 256 if args.quick else 16384
    iters1, itersB = (50, 3) if args.quick else (2000, 20)
    repeats = 2 if args.quick else args.repeats

    rates = training_rates(args.config, frames)
    print(f"training, {args.config}, {frames} frames each, 1 thread:")
    for name, fps in rates.items():
        print(f"  {name:<14} {fps:10.0f} frames/s")
    print(
        f"  recurrent / paper heads {rates['recurrent'] / rates['paper heads']:.2f}x, "
        f"recurrent / feed-forward {rates['recurrent'] / rates['feed-forward']:.2f}x"
    )
    for B, iters in ((1, iters1), (big, itersB)):
        lat = latencies(B, iters, repeats)
        print(
            f"decision latency B={B}: averaging {lat['averaging'] * 1e6:.1f} us, recurrent "
            f"{lat['recurrent'] * 1e6:.1f} us (recurrent / averaging "
            f"{lat['recurrent'] / lat['averaging']:.2f}x; "
            f"{B / lat['averaging'] / 1e6:.2f}M vs {B / lat['recurrent'] / 1e6:.2f}M decisions/s)"
        )


if __name__ == "__main__":
    main()
