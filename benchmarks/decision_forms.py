"""The kept second forms of Algorithms 1 and 2 against the one implementation, side by side,
single-threaded CPU (docs/benchmarks.md, "Decision rules: one implementation, two fast forms").

Each kept form is tested equal to the one implementation on random inputs
(tests/test_controllers.py); this measures what it buys, from head outputs to a decision
(heads excluded):

- **Algorithm 2, table vs walk**: :func:`hierarchy_decide_table_of` (one table lookup) against
  :func:`hierarchy_decide_of` (the recursion, walking the levels), option-first inputs, with the
  termination-aware inputs the Wargus controller passes (``terminated``, ``startable``), at
  ``B = 16384`` and ``B = 1``, on Wargus's 3-node tree and a 5-node 3-level tree;
- **scalar vs batched at B = 1** (one environment in real time, ``Controller.act_one``'s rule):
  ``decide_scalar`` on Python floats, including the one host transfer (``tolist``), against
  the batched ``decide`` on ``(1, ...)`` tensors, for Algorithm 1 (interruption, greedy and
  softmax mu_bar) and Algorithm 2 (hierarchy).

Timing: best of ``--repeats`` runs of ``--iters`` calls, thread CPU time (``time.thread_time``:
robust to other processes on a loaded machine) and wall clock. Prints each ratio.

Usage::

    python benchmarks/decision_forms.py [--batch 16384] [--repeats 5] [--quick]
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable

import torch

from taskvar_torch import keys
from taskvar_torch.controllers import make_controller
from taskvar_torch.controllers.hierarchy import (
    TreeTables,
    hierarchy_decide_of,
    hierarchy_decide_table_of,
)
from taskvar_torch.oracle import table_heads
from taskvar_torch.subtasks import Hierarchy

A = 4
RUNNING = torch.tensor([0])  # the running option at B = 1
TREES = {
    "wargus (3 nodes)": (
        Hierarchy(root="TG+FE", children={"TG+FE": ("TG", "FE")}),
        ("TG", "FE", "TG+FE"),
    ),
    "3 levels (5 nodes)": (
        Hierarchy(root="root", children={"root": ("A", "B"), "A": ("A1", "A2")}),
        ("root", "A", "B", "A1", "A2"),
    ),
}


def timeit(fn: Callable[[], object], iters: int, repeats: int) -> tuple[float, float]:
    """Best-of-``repeats`` seconds per call: ``(thread CPU, wall)``."""
    for _ in range(max(3, iters // 10)):
        fn()
    cpu = wall = float("inf")
    for _ in range(repeats):
        c0, w0 = time.thread_time(), time.perf_counter()
        for _ in range(iters):
            fn()
        cpu = min(cpu, (time.thread_time() - c0) / iters)
        wall = min(wall, (time.perf_counter() - w0) / iters)
    return cpu, wall


def inputs(O: int, B: int, g: torch.Generator) -> dict:  # noqa: E741
    """Random option-first head outputs and termination-aware inputs for ``B`` states."""
    return {
        "q_opt": torch.randn(O, A, B, generator=g),
        "robustness": torch.randn(O, A, B, generator=g),
        "running": torch.randint(-1, O, (B,), generator=g),
        "terminated": torch.rand(B, generator=g) < 0.1,
        "startable": torch.rand(O, B, generator=g) < 0.8,
    }


def table_vs_walk(B: int, iters: int, repeats: int) -> list[tuple]:
    rows = []
    g = torch.Generator().manual_seed(0)
    for name, (tree, names) in TREES.items():
        tt = TreeTables.build(tree, names)
        x = inputs(len(names), B, g)
        args = (x["q_opt"], x["robustness"], x["running"], tt, 0.0, x["terminated"], x["startable"])
        walk = timeit(lambda: hierarchy_decide_of(*args), iters, repeats)  # noqa: B023
        table = timeit(lambda: hierarchy_decide_table_of(*args), iters, repeats)  # noqa: B023
        rows.append((name, B, walk, table))
    return rows


def scalar_vs_batched(iters: int, repeats: int) -> list[tuple]:
    """``decide_scalar`` (with the host transfer) vs ``decide`` at B = 1, from head outputs."""
    rows = []
    g = torch.Generator().manual_seed(1)
    tree, names = TREES["wargus (3 nodes)"]
    O = len(names)  # noqa: E741
    S = 8
    t = {
        "averaging": torch.randn(S, A, generator=g),
        "options": torch.randn(S, O, A, generator=g),
        "switching": torch.randn(S, O, generator=g),
        "max_value": torch.randn(S, O, generator=g),
        "robustness": torch.randn(S, O, A, generator=g),
    }
    cases = [
        ("interruption, greedy mu_bar", "interruption", None),
        ("interruption, softmax mu_bar", "interruption", 0.5),
        ("hierarchy", "hierarchy", None),
    ]
    for label, name, temperature in cases:
        heads = table_heads(names, softmax_temperature=temperature, **t)
        ctrl = make_controller(name, heads, hierarchy=tree, tau=0.0)
        values = ctrl.head_values({keys.CELL: torch.tensor([3])})  # {out_key: (1, ...)}

        def scalar(values=values, ctrl=ctrl) -> object:
            one = {k: v[0].tolist() for k, v in values.items()}  # the one host transfer
            return ctrl.decide_scalar(one, 0, False)

        def batched(values=values, ctrl=ctrl, running=RUNNING) -> object:
            return ctrl.decide(values, running, None)

        rows.append((label, timeit(batched, iters, repeats), timeit(scalar, iters, repeats)))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--batch", type=int, default=16384)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--iters1", type=int, default=2000, help="calls per repeat at B=1")
    parser.add_argument("--itersB", type=int, default=100, help="calls per repeat at large B")
    parser.add_argument("--quick", action="store_true", help="B=256, 1 repeat, few calls")
    args = parser.parse_args()
    if args.quick:
        args.batch, args.repeats, args.iters1, args.itersB = 256, 1, 20, 5
    torch.set_num_threads(1)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"torch {torch.__version__}, threads 1, load average {load:.1f}")
    us = 1e6
    print("\nAlgorithm 2: table lookup vs level walk (us per call, thread CPU / wall)")
    print(f"{'tree':20s} {'B':>6s} {'walk':>17s} {'table':>17s} {'walk / table (CPU)':>19s}")
    for B, iters in ((args.batch, args.itersB), (1, args.iters1)):
        for name, b, walk, table in table_vs_walk(B, iters, args.repeats):
            f = lambda t: f"{t[0] * us:7.1f} / {t[1] * us:7.1f}"  # noqa: E731
            print(f"{name:20s} {b:6d} {f(walk):>17s} {f(table):>17s} {walk[0] / table[0]:18.2f}x")
    print("\nB = 1, from head outputs: batched decide vs decide_scalar (us, thread CPU / wall)")
    print(f"{'rule':30s} {'batched':>17s} {'scalar':>17s} {'batched / scalar (CPU)':>23s}")
    for label, batched, scalar in scalar_vs_batched(args.iters1, args.repeats):
        f = lambda t: f"{t[0] * us:7.1f} / {t[1] * us:7.1f}"  # noqa: E731
        print(f"{label:30s} {f(batched):>17s} {f(scalar):>17s} {batched[0] / scalar[0]:22.2f}x")


if __name__ == "__main__":
    main()
