"""Controller latency and throughput (docs/benchmarks.md), single-threaded CPU.

Per controller (averaging, options, interruption, hierarchy):

- **B = 1, per decision, including the head forward** (real-time control), three ways:
  ``td``: the TensorDictModule path (``controller(td)``, as in ``env.rollout``);
  ``act``: batched kernels on plain tensors (no TensorDict);
  ``act_one``: heads fused into one MLP, one host transfer, the rule on Python floats.
- **B = 16384, decisions/s excluding the forward**: the batched decision kernels on precomputed
  head outputs, in the bundle layout ``(B, O, A)`` (permuted views, no copy) and option-first
  ``(O, A, B)`` (what a head emitting option-first would hand over).

Heads: a realistic small bundle, one MLP per head with 2 x 64 hidden units over the 25-cell
one-hot observation of the default windy grid (2 exit options; the hierarchy adds a root node).
Timing: best of ``--repeats`` runs of ``--iters`` calls, wall clock and this thread's CPU time
(``time.thread_time``: robust to other processes on a loaded machine), under
``torch.inference_mode``. Targets: <= 50 us at B=1 incl. forward, >= 50M decisions/s at
B=16384.

Usage::

    python benchmarks/controller_latency.py [--batch 16384] [--repeats 7] [--quick]
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from collections.abc import Callable

import torch
from tensordict import TensorDict

from taskvar_torch import keys
from taskvar_torch.controllers import make_controller, option_first
from taskvar_torch.heads.bundle import Heads
from taskvar_torch.heads.networks import make_head
from taskvar_torch.subtasks import Hierarchy

S, A = 25, 4
NAMES = ("averaging", "options", "interruption", "hierarchy")


def timeit(fn: Callable[[], object], iters: int, repeats: int) -> tuple[float, float]:
    """Best-of-``repeats`` seconds per call: ``(wall, thread CPU)``."""
    for _ in range(max(3, iters // 10)):
        fn()
    wall = cpu = float("inf")
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.thread_time()
        for _ in range(iters):
            fn()
        wall = min(wall, (time.perf_counter() - w0) / iters)
        cpu = min(cpu, (time.thread_time() - c0) / iters)
    return wall, cpu


def make_heads(num_options: int, hidden: tuple[int, ...] = (64, 64)) -> Heads:
    names = ("root", "exit_north", "exit_south")[-num_options:]
    k = num_options
    return Heads(
        names,
        averaging=make_head(keys.ACTION_VALUE, S, A, hidden),
        options=make_head(keys.OPTION_ACTION_VALUE, S, (k, A), hidden),
        switching=make_head(keys.OPTION_VALUE, S, k, hidden),
        max_value=make_head(keys.MAX_VALUE, S, k, hidden),
        robustness=make_head(keys.ROBUSTNESS, S, (k, A), hidden),
    )


def measure(name: str, tree: Hierarchy, B: int, args: argparse.Namespace) -> tuple:
    """Timings of one controller: B=1 paths incl. forward, large-B kernels excl. forward."""
    heads = make_heads(3 if name == "hierarchy" else 2)
    ctrl = make_controller(name, heads, hierarchy=tree, tau=0.0)
    it1, itB, rep = args.iters1, args.itersB, args.repeats
    with torch.inference_mode():
        obs1 = torch.zeros(1, S)
        obs1[0, 3] = 1.0
        run1 = torch.tensor([0])
        inp1 = {keys.OBSERVATION: obs1}
        td1 = TensorDict({keys.OBSERVATION: obs1, keys.RUNNING_OPTION: run1}, [1])
        r1 = run1 if ctrl.stateful else None
        t_td = timeit(lambda: ctrl(td1), it1, rep)
        t_act = timeit(lambda: ctrl.act(inp1, r1), it1, rep)
        fused = ctrl.fuse() is not None
        t_one = timeit(lambda: ctrl.act_one(inp1, 0), it1, rep)
        t_fwd1 = timeit(lambda: ctrl.head_values(inp1), it1, rep)
        t_ffwd1 = timeit(lambda: ctrl._fused(obs1), it1, rep) if fused else (float("nan"),) * 2

        obsB = torch.zeros(B, S)
        obsB[torch.arange(B), torch.randint(0, S, (B,))] = 1.0
        vals = ctrl.head_values({keys.OBSERVATION: obsB})  # (B, O, A) / (B, O) layout
        vals_of = {k: option_first(v).contiguous() for k, v in vals.items()}
        runB = torch.randint(-1, ctrl.num_options, (B,)) if ctrl.stateful else None
        t_bundle = timeit(lambda: ctrl.decide(vals, runB, None), itB, rep)
        t_of = timeit(lambda: ctrl.decide_of(vals_of, runB, None), itB, rep)
        t_fwdB = timeit(lambda: ctrl.head_values({keys.OBSERVATION: obsB}), max(10, itB // 10), rep)
    return name, t_td, t_act, t_one, fused, t_fwd1, t_ffwd1, t_bundle, t_of, t_fwdB


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--batch", type=int, default=16384)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--iters1", type=int, default=2000, help="calls per repeat at B=1")
    parser.add_argument("--itersB", type=int, default=200, help="calls per repeat at large B")
    parser.add_argument(
        "--quick", action="store_true", help="B=256, 1 repeat, few calls (smoke run)"
    )
    args = parser.parse_args()
    if args.quick:
        args.batch, args.repeats, args.iters1, args.itersB = 256, 1, 20, 5
    torch.set_num_threads(1)
    torch.manual_seed(0)
    B = args.batch
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(
        f"torch {torch.__version__}, threads {torch.get_num_threads()}, {platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} cpus, load average {load:.1f}"
    )
    tree = Hierarchy(root="root", children={"root": ("exit_north", "exit_south")})
    rows = [measure(name, tree, B, args) for name in NAMES]

    us = 1e6
    print("\nB = 1: microseconds per decision including the head forward (wall / thread CPU)")
    print(
        f"{'controller':13s} {'td path':>15s} {'act (kernels)':>15s} {'act_one (fused)':>16s}"
        f" {'heads forward':>15s} {'fused forward':>15s}"
    )
    for name, t_td, t_act, t_one, fused, t_fwd1, t_ffwd1, *_ in rows:
        f = lambda t: f"{t[0] * us:6.1f} / {t[1] * us:6.1f}"  # noqa: E731
        print(
            f"{name:13s} {f(t_td):>15s} {f(t_act):>15s} {f(t_one):>16s} {f(t_fwd1):>15s}"
            f" {f(t_ffwd1):>15s}" + ("" if fused else "  (not fused)")
        )
    print(f"\nB = {B}: million decisions/s excluding the forward (wall / thread CPU)")
    print(f"{'controller':13s} {'bundle (B,O,A)':>17s} {'option-first':>17s} {'forward (ms)':>14s}")
    for name, *_, t_bundle, t_of, t_fwdB in rows:
        m = lambda t: f"{B / t[0] / 1e6:6.1f} / {B / t[1] / 1e6:6.1f}"  # noqa: E731
        print(f"{name:13s} {m(t_bundle):>17s} {m(t_of):>17s} {t_fwdB[1] * 1e3:14.2f}")
    print("\ntargets: <= 50 us at B=1 including the forward; >= 50M decisions/s at B=16384")


if __name__ == "__main__":
    main()
