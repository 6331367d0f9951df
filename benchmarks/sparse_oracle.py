"""The sparse oracle's expectation step at the head report's shapes: gather + sum vs per outcome.

Every exact solve of :class:`~taskvar_torch.families.windy.sparse_oracle.SparseWindyOracle` is a loop of one
expectation ``E[V(s')]`` over successor tables; the head report's slowest part
(:meth:`SparseWindyOracle.controller_returns`: ``horizon`` backward-induction steps over the
(cell, option) chains of 32 instances at a time) spends nearly all of its time there. Before, a
step gathered every outcome into ``(B, n, K)`` and summed over the last dim (the *gather + sum*
reference below, the formula as it was); now it gathers one contiguous plane per outcome and adds
them (:func:`~taskvar_torch.families.windy.sparse_oracle.expect_planes`): the same bits for ``K <= 2`` (checked
here on every step, and in ``tests/families/windy/test_oracle_sparse.py``). The chains are the real ones: the
layout of ``--config``, the options controller's chains with its exact option policies (no
interruption), one quadrature chunk of instances.
Runs alternate and the medians are compared. Single-threaded by default; ``--report`` also times
the whole head report of an untrained bundle (new path only).

    python benchmarks/sparse_oracle.py [--config configs/windy_xxl.yaml] [--steps 50] [--report]
        [--quick]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from taskvar_torch.config import load_config
from taskvar_torch.factory import build_heads, make_env, make_subtasks
from taskvar_torch.families.windy.family import windy_sparse_oracle as sparse_oracle
from taskvar_torch.families.windy.head_report import head_report
from taskvar_torch.families.windy.sparse_oracle import expect_planes, outcome_planes


def sync(device: torch.device | str) -> None:
    """Wait for ``device``'s queued kernels before a timer is read (CUDA runs asynchronously)."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def gather_sum(V: torch.Tensor, flat: torch.Tensor, prob: torch.Tensor) -> torch.Tensor:
    """The chain step as it was: every outcome gathered at once, then ``sum(-1)``."""
    B, n, K = prob.shape
    return (V.gather(1, flat).view(B, n, K) * prob).sum(-1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="configs/windy_xxl.yaml")
    ap.add_argument("--steps", type=int, default=50, help="chain steps per timed pass")
    ap.add_argument("--repeats", type=int, default=5, help="alternating timed passes")
    ap.add_argument(
        "--chunk", type=int, default=32, help="instances per chain batch (as the report)"
    )
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--report", action="store_true", help="also time the whole head report")
    ap.add_argument(
        "--quick", action="store_true", help="5x5 windy.yaml, 5 steps, 1 pass (smoke run)"
    )
    ap.add_argument("overrides", nargs="*", help="config overrides (e.g. device=cuda)")
    args = ap.parse_args()
    if args.quick:
        args.config, args.steps, args.repeats = "configs/windy.yaml", 5, 1
    torch.set_num_threads(args.threads)
    cfg = load_config(args.config, args.overrides)
    oracle = sparse_oracle(cfg)
    S, O = oracle.S, oracle.O  # noqa: E741
    # the options controller's chains on (cell, option), as controller_returns builds them
    pol = oracle.option_policies()  # (O, S)
    keep = torch.arange(O, device=oracle.device).expand(S, O)
    act = pol.gather(0, keep.T.contiguous()).T  # (S, O)
    p, d, _ = oracle.quadrature()
    k = oracle.kernel(p[: args.chunk], d[: args.chunk])
    B, K = k.B, k.K
    idx = act.view(1, S, O, 1).expand(B, S, O, K)
    succ, prob = k.succ.gather(2, idx), k.prob.gather(2, idx)
    chain = succ * O + keep.view(1, S, O, 1)
    flat, prob_k = chain.reshape(B, -1), prob.reshape(B, S * O, K)
    planes = outcome_planes(chain, prob)
    V0 = -torch.rand(B, S * O, dtype=torch.float64, device=oracle.device) * 100
    times: dict[str, list[float]] = {"gather + sum": [], "per outcome": []}
    for _ in range(args.repeats):
        for name in times:
            V, outs = V0, []
            sync(oracle.device)
            start = time.perf_counter()
            for _ in range(args.steps):
                if name == "gather + sum":
                    V = gather_sum(V, flat, prob_k).sub_(1.0)
                else:
                    V = expect_planes(V, *planes).sub_(1.0)
                outs.append(V)
            sync(oracle.device)
            times[name].append((time.perf_counter() - start) / args.steps)
            if name == "gather + sum":
                ref = outs
        assert all(torch.equal(a, b) for a, b in zip(outs, ref)), "the two paths differ"
    old, new = (statistics.median(times[n]) for n in times)
    print(
        f"sparse oracle chain step, {args.config} ({S} cells x {O} options, {B} instances, K={K}; "
        f"{args.threads} thread(s); the same bits on every step)"
    )
    print(f"  gather + sum(-1) (as it was)      {old * 1e3:8.2f} ms per step")
    print(f"  one gather per outcome (now)      {new * 1e3:8.2f} ms per step")
    print(f"  ratio {old / new:.1f}x")
    if args.report:
        env = make_env(cfg, num_envs=1, seed=cfg.seed)
        heads = build_heads(cfg, env, make_subtasks(cfg, env))
        sync(oracle.device)
        start = time.perf_counter()
        head_report(heads, oracle, cfg.env.windy.obs_encoding, cfg.env.windy.patch_radius)
        sync(oracle.device)
        print(f"  head report of an untrained bundle: {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    main()
