"""Seeds as a batch dimension: ``taskvar train --seeds N`` against one seed, side by side.

For each case (a config and a frame budget) and each N in ``--seeds`` (default 1, 5, 10), one
child process runs the real :func:`~taskvar_torch.training.train` with ``train.seeds=N`` (one torch
thread) and reports its wall time, its CPU time and its peak resident memory; the cases and Ns are
interleaved over ``--repeats`` rounds so that load on the machine hits them alike, and the medians
are printed with the ratios that matter: N seeds' wall over one seed's (the goal: 5 seeds in <= 2x
one seed's wall) and wall, CPU and memory per seed.

Replay buffers are the memory: each seed has its own ``train.buffer_size`` rows, allocated at
full size on the first write (TorchRL ``LazyTensorStorage``), so peak RSS grows by one buffer per
seed (printed as ``MB/seed``, the increase over one seed divided by N - 1).

Usage::

    python benchmarks/seeds.py                # windy 5x5 (50k frames), windy 51x51 and Wargus
                                              # 32x32 training (shorter budgets), and Figure 4's
                                              # repetitions batched, N = 1, 5, 10
    python benchmarks/seeds.py --cases windy5 --seeds 1,5 --repeats 3
    python benchmarks/seeds.py --cases windy5,wargus32 --seeds 1,5 train.total_frames=20000
    python benchmarks/seeds.py --quick        # a smoke run: windy 5x5, 768 frames, N = 1, 2
    python benchmarks/seeds.py --cases fig4 --seeds 1,5   # Figure 4: 30 paper-scale trials of
                                              # 1 repetition against 5 batched (N = seeds)
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# eager throughout (configs/wargus.yaml compiles by default): a compile, once per child process,
# would blur the N-seed ratios; add train.compile=true on the command line to measure that path
CASES = {
    "windy5": ("configs/windy.yaml", []),  # the shipped 50k-frame budget
    "windy51": ("configs/windy_xl.yaml", ["train.total_frames=60000"]),
    "wargus32": ("configs/wargus.yaml", ["train.total_frames=40000", "train.compile=false"]),
    # Figure 4: N repetitions batched in one loop (wargus_fig4.run_repetitions_batched), the
    # paper-scale trial (30 learning episodes, 5 x 4 test episodes, 2 x with the held-out ones)
    "fig4": ("configs/wargus.yaml", ["experiment.trials=30", "train.compile=false"]),
}
FIG4 = {"fig4"}  # cases that run Figure 4 repetitions rather than taskvar train
QUICK = [
    "train.total_frames=768",
    "train.init_random_frames=256",
    "train.frames_per_batch=128",
    "train.updates_per_batch=4",
    "env.num_envs=4",
]


def child(config: str, overrides: list[str], seeds: int, fig4: bool = False) -> dict:
    """One training run (``fig4``: ``seeds`` Figure 4 repetitions batched) in this process; its
    wall and CPU seconds and peak RSS (MB)."""
    import torch

    from taskvar_torch.config import load_config
    from taskvar_torch.families.wargus.fig4_repetition import run_repetitions_batched
    from taskvar_torch.training import train

    torch.set_num_threads(1)
    extra = [] if fig4 else [f"train.seeds={seeds}"]
    cfg = load_config(str(ROOT / config), [*overrides, *extra])
    with tempfile.TemporaryDirectory() as tmp:
        wall0, cpu0 = time.perf_counter(), time.process_time()
        phases = {}
        if fig4:  # CPU seconds per repetition and trial, per phase (wargus_fig4.PHASES)
            done = run_repetitions_batched(cfg, list(range(seeds)), Path(tmp))
            per = seeds * cfg.experiment.trials
            phases = {
                k: sum(r["cpu_seconds"][k] for r in done) / per for k in done[0]["cpu_seconds"]
            }
        else:
            train(cfg, Path(tmp) / "run", progress=False, keep_replay=False)
        wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KB -> MB (Linux)
    return {"wall": wall, "cpu": cpu, "rss": rss, "phases": phases}


def measure(config: str, overrides: list[str], seeds: int, fig4: bool = False) -> dict:
    """:func:`child` in a fresh process (its own peak RSS)."""
    here = str(Path(__file__).parent)
    code = (
        f"import json, sys; sys.path.insert(0, {here!r}); from seeds import child; "
        f"print('RESULT', json.dumps(child({config!r}, {overrides!r}, {seeds}, {fig4})))"
    )
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=env
    )
    if out.returncode != 0:
        raise RuntimeError(f"seeds={seeds} {config} failed:\n{out.stderr[-2000:]}")
    line = next(x for x in out.stdout.splitlines() if x.startswith("RESULT "))
    return json.loads(line[len("RESULT ") :])


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", default=",".join(CASES), help=f"comma list of {list(CASES)}")
    p.add_argument("--seeds", default="1,5,10", help="comma list of seed counts (1 first)")
    p.add_argument("--repeats", type=int, default=1, help="interleaved rounds (medians)")
    p.add_argument("--quick", action="store_true", help="smoke run: windy 5x5, 768 frames, N=1,2")
    p.add_argument("--device", default="cpu", help="device key of every run (e.g. cuda)")
    p.add_argument(
        "overrides", nargs="*", help="key.sub=value for every case (e.g. train.total_frames=20000)"
    )
    args = p.parse_args(argv)
    cases = {k: (c, [*o, f"device={args.device}"]) for k, (c, o) in CASES.items()}
    cases = {k: cases[k] for k in args.cases.split(",")}
    counts = [int(n) for n in args.seeds.split(",")]
    if args.quick:
        cases = {"windy5-quick": ("configs/windy.yaml", [*QUICK, f"device={args.device}"])}
        counts = [1, 2]
    if counts[0] != 1:
        raise SystemExit("--seeds must start with 1 (the baseline)")
    print(f"load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    runs: dict[tuple[str, int], list[dict]] = {}
    for r in range(args.repeats):
        for name, (config, overrides) in cases.items():
            for n in counts:
                m = measure(config, [*overrides, *args.overrides], n, name in FIG4)
                runs.setdefault((name, n), []).append(m)
                print(
                    f"  round {r}: {name} N={n}: wall {m['wall']:.1f} s, cpu {m['cpu']:.1f} s, "
                    f"peak RSS {m['rss']:.0f} MB (load {os.getloadavg()[0]:.2f})"
                    + "".join(f", {k} {v:.3f}" for k, v in m["phases"].items()),
                    flush=True,
                )
    print(
        f"{'case':<14}{'N':>4}{'wall s':>9}{'x 1 seed':>10}{'wall/seed':>11}{'cpu/seed':>10}"
        f"{'RSS MB':>9}{'MB/seed':>9}"
    )
    for name in cases:
        base = {k: statistics.median(r[k] for r in runs[(name, 1)]) for k in ("wall", "rss")}
        for n in counts:
            m = {
                k: statistics.median(r[k] for r in runs[(name, n)]) for k in ("wall", "cpu", "rss")
            }
            per_mb = (m["rss"] - base["rss"]) / (n - 1) if n > 1 else float("nan")
            print(
                f"{name:<14}{n:>4}{m['wall']:>9.1f}{m['wall'] / base['wall']:>10.2f}"
                f"{m['wall'] / n:>11.2f}{m['cpu'] / n:>10.2f}{m['rss']:>9.0f}{per_mb:>9.0f}"
            )
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
