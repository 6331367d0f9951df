"""Exact expected returns of every Taxi method, per test distribution (docs/taxi.md).

For each named test distribution of the Taxi family: the exact expected 200-step return (Taxi-v4
starts) of the averaging, options and interruption controllers on the oracle's own tables and, with
``--checkpoint``, on a trained bundle's heads; the expected interruptions per episode; and the
per-instance optimum (an agent that knows the rain and the passenger's fickleness). Everything is
exact (``families/taxi/oracle.py``): no episode is sampled.

Usage:
    python scripts/taxi_exact.py [--checkpoint runs/taxi/final.pt] [--tests train fickle ...]
"""

from __future__ import annotations

import argparse

import torch

from taskvar_torch.factory import load_heads, make_method_controller
from taskvar_torch.families.taxi.family import TESTS
from taskvar_torch.families.taxi.oracle import TaxiOracle
from taskvar_torch.families.taxi.subtasks import TaxiSubtasks

METHODS = ("averaging", "options", "interruption")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", help="a Taxi bundle (taskvar train's final.pt)")
    p.add_argument("--tests", nargs="+", default=list(TESTS), help="test distributions")
    args = p.parse_args()
    torch.set_num_threads(1)
    heads = cfg = None
    encoding = "onehot"
    if args.checkpoint:
        heads, cfg = load_heads(args.checkpoint, device="cpu")
        encoding = cfg.env.taxi.obs_encoding
    oracle = TaxiOracle(
        gamma=0.99 if cfg is None else cfg.train.gamma,
        train_instances="train" if cfg is None else cfg.env.instances,
        obs_encoding=encoding,
    )
    learnt = {}
    if heads is not None:
        learnt = {m: make_method_controller(cfg, m, heads, TaxiSubtasks()) for m in METHODS}
    cols = ["oracle " + m for m in METHODS] + ["learnt " + m for m in learnt]
    print(f"{'test':<11}" + "".join(f"{c:>22}" for c in cols) + f"{'fires/ep':>10}{'optimum':>9}")
    for test in args.tests:
        dist = TESTS[test].instances
        row = [float(oracle.controller_expected_return(m, dist)) for m in METHODS]
        row += [float(oracle.controller_expected_return(c, dist)) for c in learnt.values()]
        ctrl = learnt.get("interruption", "interruption")
        fires = float(oracle.controller_expected_return(ctrl, dist, count_fires=True))
        best = float(oracle.expected_optimal_return(dist))
        print(f"{test:<11}" + "".join(f"{v:22.3f}" for v in row) + f"{fires:10.3f}{best:9.3f}")


if __name__ == "__main__":
    main()
