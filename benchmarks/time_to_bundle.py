"""Time to a learnt bundle (docs/scale.md, "The shipped settings and time to a learnt bundle").

For each variant of a windy family config (``NAME=key.sub=value,...``; the first is the baseline)
and each seed: the real :func:`~taskvar_torch.training.train` to the config's budget, then
:func:`~taskvar_torch.families.windy.head_report.head_report` against the exact oracle. Prints, per run,
the training seconds and their ratio to the baseline's (same seed), each head's relative gap to
its exact optimum (``*``: within 2%), how many heads are within 2%, mu_bar's agreement at the
start cells, the exact return of the learnt options controller and the learnt interruption
condition's agreement with the exact one (``--no-max-value`` skips it); then, per variant, the share
of heads within 2% over the seeds. ``--snapshots K`` also saves the heads K times during training
(``train.heads_every``) and reports each snapshot's heads (without the interruption condition): the
first snapshot with every head within 2% is the time to a learnt bundle. Runs one after the other
in this process (``--threads`` torch threads), so their seconds are comparable when nothing else
runs.

Usage::

    python benchmarks/time_to_bundle.py --config configs/windy_xl.yaml --seeds 0,1,2
    python benchmarks/time_to_bundle.py --config configs/windy_xl.yaml \\
        --variant shipped= --variant lr-decay=train.lr_end=0.0001,train.lr_decay_start_frames=2000000
    python benchmarks/time_to_bundle.py --config configs/windy_xl.yaml --snapshots 6 \
        --variant uniform= --variant per-option=train.replay_sampling=per_option
    python benchmarks/time_to_bundle.py --quick      # a smoke run: 5x5 layout, 3k frames
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from pathlib import Path

import torch

from taskvar_torch.checkpoint import load_checkpoint
from taskvar_torch.config import load_config
from taskvar_torch.factory import load_heads
from taskvar_torch.families.windy.family import windy_sparse_oracle as sparse_oracle
from taskvar_torch.families.windy.head_report import head_report
from taskvar_torch.training import train
from taskvar_torch.training.run_state import HEADS_SNAPSHOTS

QUICK = ["train.total_frames=3000", "train.init_random_frames=500", "train.eps_decay_frames=1500"]


def parse_variant(text: str) -> tuple[str, list[str]]:
    """``NAME=key.sub=value,key.sub=value`` (or ``NAME=``) -> ``(NAME, [overrides])``."""
    name, sep, rest = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(
            f"--variant must be NAME=key.sub=value,... (or NAME= for none), got {text!r}"
        )
    return name, [o for o in rest.split(",") if o]


def run_once(
    config: str, overrides: list[str], seed: int, max_value: bool = True, snapshots: int = 0
) -> dict:
    """Train one variant and seed in a scratch folder; its training seconds and head report, and
    with ``snapshots > 0`` the reports of that many snapshots of the heads along the way."""
    cfg = load_config(config, [*overrides, f"seed={seed}", "train.checkpoint_every=0"])
    if snapshots > 0:
        every = max(cfg.train.total_frames // snapshots, 1)
        cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, heads_every=every))
    if cfg.family != "windy":
        raise SystemExit(f"--config must be a windy config (exact oracle), got family {cfg.family}")
    oracle = sparse_oracle(cfg)
    along = []
    with tempfile.TemporaryDirectory() as tmp:
        result = train(cfg, Path(tmp) / "run", progress=False, keep_replay=False)
        heads, _ = load_heads(result["final"], device=cfg.device)
        for path in sorted((Path(tmp) / "run" / HEADS_SNAPSHOTS).glob("heads_*.pt")):
            snap, _ = load_heads(path, device=cfg.device)
            r = measure(snap, cfg, oracle, False)
            counters = load_checkpoint(path)["counters"]
            r["frames"], r["seconds"] = int(counters["frames"]), float(counters["seconds"])
            along.append(r)
    final = measure(heads, cfg, oracle, max_value)
    final.update(seconds=float(result["seconds"]), frames=int(result["frames"]), snapshots=along)
    return final


def measure(heads, cfg, oracle, max_value: bool) -> dict:
    """Each head's gap to its exact optimum, the heads within 2%, mu_bar's agreement, the options
    controller's exact return and (``max_value``) the interruption condition's agreement."""
    report = head_report(
        heads, oracle, cfg.env.windy.obs_encoding, cfg.env.windy.patch_radius, max_value
    )
    gaps = {"averaging": report["averaging"]}
    gaps.update(report.get("options", {}))
    return {
        "gaps": gaps,
        "within": sum(g["within_2pct"] for g in gaps.values()),
        "mu_bar": report["mu_bar"]["start_agreement"] if "mu_bar" in report else float("nan"),
        "controller": report.get("options_controller", {}).get("expected_return", float("nan")),
        "optimum": report["averaging"]["optimal_return"],
        "condition": report.get("interruption_condition", {}).get("agreement", float("nan")),
    }


def gap_line(gaps: dict) -> str:
    """``head gap`` for each head, ``*`` where within 2%."""
    return ", ".join(
        f"{h} {g['rel_gap']:.3f}" + ("*" if g["within_2pct"] else "") for h, g in gaps.items()
    )


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="configs/windy_xl.yaml", help="a windy family config")
    ap.add_argument(
        "--variant",
        action="append",
        type=parse_variant,
        help="NAME=key.sub=value,... (repeatable; the first is the baseline; default shipped=)",
    )
    ap.add_argument("--seeds", default="0", help="comma-separated seeds (default 0)")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    ap.add_argument(
        "--snapshots",
        type=int,
        default=0,
        help="also report the heads saved this many times during training (default 0: none)",
    )
    ap.add_argument("--quick", action="store_true", help="5x5 windy.yaml, 3k frames: a smoke run")
    ap.add_argument(
        "--no-max-value",
        action="store_true",
        help="skip the interruption condition's agreement with the exact one (the slowest solve)",
    )
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    variants = args.variant or [("shipped", [])]
    config = "configs/windy.yaml" if args.quick else args.config
    extra = QUICK if args.quick else []
    seeds = [int(s) for s in args.seeds.split(",") if s]
    print(f"{config}, seeds {seeds}, {args.threads} torch thread(s)")
    base_seconds: dict[int, float] = {}
    share: dict[str, list[int]] = {}
    for name, overrides in variants:
        for seed in seeds:
            r = run_once(config, [*extra, *overrides], seed, not args.no_max_value, args.snapshots)
            for snap in r["snapshots"]:
                print(
                    f"{name:<12} seed {seed}, {snap['frames']} frames ({snap['seconds']:.0f} s): "
                    f"{gap_line(snap['gaps'])}; {snap['within']}/{len(snap['gaps'])} within 2%; "
                    f"mu_bar {snap['mu_bar']:.2f}; options controller {snap['controller']:.2f}",
                    flush=True,
                )
            base_seconds.setdefault(seed, r["seconds"])
            share.setdefault(name, []).append(r["within"])
            heads = gap_line(r["gaps"])
            print(
                f"{name:<12} seed {seed}: {r['frames']} frames in {r['seconds']:.1f} s "
                f"(x{r['seconds'] / base_seconds[seed]:.2f} of {variants[0][0]}); {heads}; "
                f"{r['within']}/{len(r['gaps'])} heads within 2%; mu_bar {r['mu_bar']:.2f}; "
                f"options controller {r['controller']:.2f} (optimum {r['optimum']:.2f}); "
                f"interruption condition {r['condition']:.3f}",
                flush=True,
            )
    n_heads = len(r["gaps"])
    for name, counts in share.items():
        every = sum(c == n_heads for c in counts)
        print(
            f"{name}: {sum(counts)}/{n_heads * len(counts)} heads within 2% over {len(counts)} "
            f"seed(s); every head within 2% in {every} of {len(counts)}"
        )


if __name__ == "__main__":
    main()
