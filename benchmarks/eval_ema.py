"""Which Polyak average of the weights to evaluate (``train.eval_ema_tau``; docs/scale.md).

One real :func:`~taskvar_torch.training.train` run of a windy config per seed, keeping beside the
online heads one exponential moving average of their weights per ``--taus`` value (``ema <- ema +
tau (online - ema)`` after every update, from the initial weights, as ``train.eval_ema_tau`` does;
the averages only read the weights, so the run trains as without them), then
:func:`~taskvar_torch.families.windy.head_report.head_report` of the online heads and of each average
against the exact oracle (the training distribution's exact values). Prints per seed and weights:
how many heads are within 2% of their exact optimum, each head's relative gap (``*``: within 2%),
mu_bar's agreement at the start cells and the exact return of the learnt options controller; then
the share of heads within 2% per weights over the seeds. The config's own ``train.eval_ema_tau``
is switched off (the averages here replace it).

Usage::

    python benchmarks/eval_ema.py --config configs/windy_xl.yaml --seeds 0,1,2 --taus 0.01,0.002
    python benchmarks/eval_ema.py --quick     # a smoke run: 5x5 layout, 3k frames
"""

from __future__ import annotations

import argparse
import copy
import tempfile
from pathlib import Path

import torch

from taskvar_torch.config import load_config
from taskvar_torch.factory import load_heads
from taskvar_torch.families.windy.family import windy_sparse_oracle as sparse_oracle
from taskvar_torch.families.windy.head_report import head_report
from taskvar_torch.heads import learner as learner_module
from taskvar_torch.training import train

QUICK = ["train.total_frames=3000", "train.init_random_frames=500", "train.eps_decay_frames=1500"]


def train_with_averages(config: str, overrides: list[str], seed: int, taus: list[float]):
    """Train one seed; returns the loaded online heads, the config and ``{tau: [weights]}``."""
    cfg = load_config(
        config, [*overrides, f"seed={seed}", "train.checkpoint_every=0", "train.eval_ema_tau=null"]
    )
    if cfg.family != "windy":
        raise SystemExit(f"--config must be a windy config (exact oracle), got family {cfg.family}")
    averages: dict[float, list[torch.Tensor]] = {}
    update = learner_module.MultiHeadLearner.update

    def update_and_average(self, sample):  # the learner's update, then every average's step
        out = update(self, sample)
        online = [p.detach() for p in self.heads.parameters()]
        for tau, ema in averages.items():
            torch._foreach_lerp_(ema, online, tau)
        return out

    init = learner_module.MultiHeadLearner.__init__

    def init_and_copy(self, *a, **kw):  # the averages start at the initial weights
        init(self, *a, **kw)
        for tau in taus:
            averages[tau] = [p.detach().clone() for p in self.heads.parameters()]

    learner_module.MultiHeadLearner.update = update_and_average
    learner_module.MultiHeadLearner.__init__ = init_and_copy
    try:
        with tempfile.TemporaryDirectory() as tmp:
            result = train(cfg, Path(tmp) / "run", progress=False)
            heads, _ = load_heads(result["final"], device=cfg.device)
    finally:
        learner_module.MultiHeadLearner.update = update
        learner_module.MultiHeadLearner.__init__ = init
    return heads, cfg, averages, float(result["seconds"])


def report_line(heads, cfg, oracle) -> dict:
    report = head_report(
        heads, oracle, cfg.env.windy.obs_encoding, cfg.env.windy.patch_radius, False
    )
    gaps = {"averaging": report["averaging"]}
    gaps.update(report.get("options", {}))
    return {
        "gaps": gaps,
        "within": sum(g["within_2pct"] for g in gaps.values()),
        "mu_bar": report["mu_bar"]["start_agreement"] if "mu_bar" in report else float("nan"),
        "controller": report.get("options_controller", {}).get("expected_return", float("nan")),
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="configs/windy_xl.yaml", help="a windy family config")
    ap.add_argument("--seeds", default="0", help="comma-separated training seeds (default 0)")
    ap.add_argument("--taus", default="0.01,0.002", help="comma-separated averaging rates")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--quick", action="store_true", help="5x5 layout, 3k frames: a smoke run")
    ap.add_argument("overrides", nargs="*", help="config overrides for every run")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    config = "configs/windy.yaml" if args.quick else args.config
    overrides = [*(QUICK if args.quick else []), *args.overrides]
    taus = [float(t) for t in args.taus.split(",") if t]
    bad = [t for t in taus if not 0.0 < t <= 1.0]
    if bad:
        raise SystemExit(f"--taus must be in (0, 1], got {bad}")
    seeds = [int(s) for s in args.seeds.split(",") if s]
    totals: dict[str, list[int]] = {}
    for seed in seeds:
        heads, cfg, averages, seconds = train_with_averages(config, overrides, seed, taus)
        oracle = sparse_oracle(cfg)
        print(f"seed {seed}: {seconds:.0f} s training")
        runs = [("online", heads)]
        for tau, ema in averages.items():
            h = copy.deepcopy(heads)
            with torch.no_grad():
                for p, q in zip(h.parameters(), ema):
                    p.copy_(q)
            runs.append((f"ema {tau:g}", h))
        for name, h in runs:
            r = report_line(h, cfg, oracle)
            cells = "  ".join(
                f"{k} {g['rel_gap']:.3f}{'*' if g['within_2pct'] else ' '}"
                for k, g in r["gaps"].items()
            )
            print(
                f"  {name:<12} {r['within']}/{len(r['gaps'])} within 2%   {cells}   "
                f"mu_bar {r['mu_bar']:.2f}   options controller {r['controller']:.2f}",
                flush=True,
            )
            totals.setdefault(name, []).extend([r["within"], len(r["gaps"])])
    print("heads within 2% over the seeds:")
    for name, counts in totals.items():
        print(f"  {name:<12} {sum(counts[0::2])} / {sum(counts[1::2])}")


if __name__ == "__main__":
    main()
