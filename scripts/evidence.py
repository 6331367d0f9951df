"""Every method beside memory and the ceiling, over many training seeds (docs/memory.md).

For one family config: ``taskvar train CONFIG --seeds N`` (one batched learner, docs/seeds.md),
``taskvar train-baselines`` in each ``seed<k>/`` (the recurrent, informed and blind baselines), then
``taskvar eval --method all`` of each seed's bundle on each named test distribution (one seed's
methods share paired episodes; eval's default test seed is each bundle's own ``seed + 1``, so
the seeds play different episodes; a held-out test, its sealed seed drawn apart per seed), each into
``OUT/eval-<test>/seed<k>/``: the layout ``taskvar report`` reads. Steps already done are skipped,
so an interrupted run continues. Finally one table per test: each method's mean return, exact
value and regret against the exact per-instance optimum (where the family has an oracle), as the
mean over seeds with rliable's stratified-bootstrap 95% CI (``study/aggregate.py``).

Usage::

    python scripts/evidence.py configs/windy.yaml --seeds 5 --tests train,south,heldout \\
        --out results/evidence/windy
    python scripts/evidence.py configs/taxi.yaml --seeds 5 --tests train,fickle,heldout \\
        --out results/evidence/taxi --baselines none    # the paper's methods only
    python scripts/evidence.py --bundles DIR/rep0 DIR/rep1 ... --tests nominal,heldout \\
        --baselines none --out OUT                      # bundles already trained, e.g. the
                                                        # Figure 4 protocol's (with its recurrent.pt)

``--bundles`` takes bundle folders (``final.pt`` and ``config.yaml``, or a Figure 4 repetition's
``rep{r}/``) in place of training: seed ``k`` is the ``k``-th folder, evaluated where it lies.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from taskvar_torch.heads.recurrent import BASELINES
from taskvar_torch.study.aggregate import interval_estimates

COLUMNS = (("mean_return", "return"), ("exact_mean_return", "exact"), ("regret_mean", "regret"))


def taskvar(*args: str) -> None:
    """Run one ``taskvar`` command in a child process (its output passes through)."""
    cmd = [sys.executable, "-m", "taskvar_torch.cli", *args]
    print("+ taskvar " + " ".join(args), flush=True)
    subprocess.run(cmd, check=True)


def run(args: argparse.Namespace) -> Path:
    """Train, train the baselines, evaluate: whatever is not on disk yet."""
    out = Path(args.out)
    if args.bundles:
        seeds = [Path(b) for b in args.bundles]
        lost = [str(s) for s in seeds if not (s / "final.pt").is_file()]
        if lost:
            raise SystemExit(f"--bundles: no final.pt in {', '.join(lost)}")
    else:
        train_dir = out / "train"
        seeds = [train_dir / f"seed{k}" for k in range(args.seeds)]
        if not all((s / "final.pt").exists() for s in seeds):
            overrides = list(args.overrides)
            taskvar(
                "train",
                args.config,
                *overrides,
                "--seeds",
                str(args.seeds),
                "--out",
                str(train_dir),
            )
    wanted = {"all": BASELINES, "none": ()}.get(args.baselines, (args.baselines,))
    for s in seeds:
        missing = [m for m in wanted if not (s / f"{m}.pt").exists()]
        config = [str(s / "config.yaml")] if (s / "config.yaml").is_file() else []
        for method in ["all"] if len(missing) == len(BASELINES) else missing:
            taskvar(
                "train-baselines",
                *config,
                "--out",
                str(s),
                "--method",
                method,
                "--no-progress",
                *(f"baseline.{kv}" for kv in args.baseline_settings),
            )
    for test in args.tests:
        for k, s in enumerate(seeds):
            dest = out / f"eval-{test}" / f"seed{k}"
            if (dest / "metrics.json").exists():
                continue
            taskvar(
                "eval",
                "--checkpoint",
                str(s / "final.pt"),
                "--method",
                "all",
                "--test",
                test,
                "--episodes",
                str(args.episodes),
                "--out",
                str(dest),
                "--no-progress",
                *(["--exact"] if args.exact else []),
            )
    return out


def table(out: Path, tests: list[str], reps: int) -> str:
    """Per test, each method's mean over seeds (rliable 95% CI) of return, exact value, regret."""
    lines = []
    for test in tests:
        folders = sorted((out / f"eval-{test}").glob("seed*/metrics.json"))
        if not folders:
            continue
        per_seed = [json.loads(f.read_text())["points"][0]["methods"] for f in folders]
        methods = [m for m in per_seed[0] if all(m in p for p in per_seed)]
        lines.append(f"test {test}: {len(folders)} training seeds (mean over seeds, 95% CI)")
        lines.append(f"  {'method':<13}" + "".join(f"{name:>26}" for _, name in COLUMNS))
        for m in methods:
            cells = []
            for key, _ in COLUMNS:
                vals = [p[m].get(key) for p in per_seed]
                if any(v is None for v in vals):
                    cells.append(f"{'':>26}")
                    continue
                est = interval_estimates({m: np.array(vals)}, reps=reps)[m]
                lo, hi = est["mean_ci95"]
                cells.append(f"{est['mean']:>10.3f} [{lo:7.3f}, {hi:7.3f}]")
            lines.append(f"  {m:<13}" + "".join(cells))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("config", nargs="?", help="the family config to train (not with --bundles)")
    p.add_argument("overrides", nargs="*", help="key.sub=value config overrides")
    p.add_argument("--bundles", nargs="+", help="bundle folders to evaluate instead of training")
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--tests", default="train,heldout", help="comma list of test distributions")
    p.add_argument("--episodes", type=int, default=2000)
    p.add_argument("--out", required=True)
    p.add_argument(
        "--baselines",
        default="all",
        choices=("all", *BASELINES, "none"),
        help="the baselines each bundle trains where its file is missing (default all)",
    )
    p.add_argument(
        "--no-baselines",
        dest="baselines",
        action="store_const",
        const="none",
        help="deprecated: --baselines none",
    )
    p.add_argument("--reps", type=int, default=2000, help="bootstrap resamples")
    p.add_argument(
        "--baseline-settings",
        nargs="*",
        default=[],
        metavar="KEY=V",
        help="settings of the baselines trained here (taskvar train-baselines baseline.KEY=V)",
    )
    p.add_argument(
        "--exact",
        action="store_true",
        help="exact values and regret on every test, however many distinct instances (eval --exact)",
    )
    args = p.parse_args(argv)
    if bool(args.config) == bool(args.bundles):
        p.error("give a config to train or --bundles to evaluate, not both or neither")
    args.tests = args.tests.split(",")
    out = run(args)
    text = table(out, args.tests, args.reps)
    (out / "table.txt").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
