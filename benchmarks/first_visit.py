"""The trainer's first-visit filter on one collector batch: per step vs one pass, side by side.

``FirstVisitFilter.forward`` gets every collector batch ``(N, T)`` of the windy trainer
(``train.first_visit``; docs/benchmarks.md). Before, it walked the batch's ``T`` steps, clearing
the ``N x buckets`` flags of new episodes with a full-size ``masked_fill_`` and visiting one step
at a time (the *per-step* reference below, kept here as it was); now it hashes the whole batch,
splits each environment's steps at its episode starts and finds first visits with one sort
(:meth:`FirstVisitFilter.visit_steps`). Both give the same masks and flags (checked here on every
batch, and in ``tests/test_heads.py``). Batches are real ones: the 51x51 config's observations
and actions from TorchRL's ``Collector`` with a random policy. Runs alternate and the medians are
compared, so a loaded machine slows both alike. Single-threaded by default.

    python benchmarks/first_visit.py [--config configs/windy_xl.yaml] [--batches 20] [--threads 1]
        [--quick] [overrides ...]
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time

import torch

from taskvar_torch import keys
from taskvar_torch.config import load_config
from taskvar_torch.heads.first_visit import FirstVisitFilter
from taskvar_torch.training.collection import make_collector, make_training_env


def sync(device: torch.device | str) -> None:
    """Wait for ``device``'s queued kernels before a timer is read (CUDA runs asynchronously)."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def per_step(f: FirstVisitFilter, batch) -> torch.Tensor:
    """The filter's batch pass as it was: a clear and a visit per step."""
    obs, action = batch.get(keys.OBSERVATION), batch.get(keys.ACTION)
    is_init = batch.get("is_init").reshape(action.shape)
    keep = torch.empty(action.shape, dtype=torch.bool, device=action.device)
    for t in range(action.shape[1]):
        f.seen.masked_fill_(is_init[:, t].unsqueeze(-1), False)
        keep[:, t] = f.visit(obs[:, t], action[:, t])
    return keep


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="configs/windy_xl.yaml")
    ap.add_argument("--batches", type=int, default=20, help="collector batches")
    ap.add_argument("--repeats", type=int, default=5, help="alternating timed passes")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument(
        "--quick", action="store_true", help="5x5 windy.yaml, 2 batches, 1 pass (smoke run)"
    )
    ap.add_argument("overrides", nargs="*", help="config overrides (e.g. device=cuda)")
    args = ap.parse_args()
    if args.quick:
        args.config, args.batches, args.repeats = "configs/windy.yaml", 2, 1
    torch.set_num_threads(args.threads)
    cfg = load_config(args.config, args.overrides)
    env = make_training_env(cfg)
    collector = make_collector(cfg, env, None, cfg.train.frames_per_batch * args.batches)
    batches = [b.select(keys.OBSERVATION, keys.ACTION, "is_init").clone() for b in collector]
    collector.shutdown()
    N, T = batches[0].shape
    D = batches[0].get(keys.OBSERVATION).shape[-1]
    times: dict[str, list[float]] = {"per step": [], "one pass": []}
    for _ in range(args.repeats):
        a = FirstVisitFilter(N, D, device=cfg.device)
        b = copy.deepcopy(a)
        for name, f, run in (("per step", a, per_step), ("one pass", b, lambda f, x: f(x))):
            sync(cfg.device)
            start = time.perf_counter()
            masks = [run(f, x) for x in batches]
            sync(cfg.device)
            times[name].append((time.perf_counter() - start) / len(batches))
            if name == "per step":
                ref = masks
        assert all(torch.equal(m, r) for m, r in zip(masks, ref)) and torch.equal(a.seen, b.seen)
    kept = torch.cat([m.flatten() for m in ref]).float().mean()
    old, new = (statistics.median(times[k]) for k in ("per step", "one pass"))
    print(
        f"first-visit filter, {len(batches)} collector batches of N={N} x T={T} ({args.config}, "
        f"{args.threads} thread(s); {kept:.2f} of transitions kept, the same masks and flags)"
    )
    print(f"  per step (clear + visit per step)   {old * 1e3:8.2f} ms per batch")
    print(f"  one pass (visit_steps with is_init) {new * 1e3:8.2f} ms per batch")
    print(f"  ratio per step / one pass {old / new:.1f}x")


if __name__ == "__main__":
    main()
