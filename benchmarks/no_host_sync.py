"""No host round trips in the CUDA hot paths: ``torch.cuda.set_sync_debug_mode("error")``.

The CUDA half of ``tests/test_no_host_sync.py`` (which checks the pure step functions on the
``meta`` device). Each hot path is built and run once on CUDA with the debug mode off (set-up,
allocator and cuBLAS warm-up, lazy inits), then run ``--iters`` more times with
``torch.cuda.set_sync_debug_mode("error")``: any synchronising call inside (``.item()``,
``bool(t)``, ``.tolist()``, ``nonzero``, boolean-mask indexing, a blocking host-to-device copy)
raises, the path is reported ``SYNC`` with the error, and the script exits 1. Hot paths:

- env steps: the pure ``windy.step`` and ``wargus`` reset / step / observe / item_lost, and the
  batched envs' own steps without TorchRL's wrappers (``WindyGridEnv._advance`` and ``_step``,
  ``TaxiEnv._advance``, ``WargusEnv.step_all``; ``validate_actions=False``, as an accelerator
  step runs);
- controllers' batched decisions: ``decide`` (bundle layout), ``decide_of`` (option-first) and
  ``act`` (head forward + decision on plain tensors) of averaging, options, interruption and
  hierarchy at batch ``B``;
- learner updates: ``MultiHeadLearner.update`` on replay samples drawn beforehand (the replay
  buffer's sampling and the logging interval's ``pop_losses`` sync by design and are left out).

Left out: TorchRL's ``step_and_maybe_reset`` / ``rollout`` and the reference ``rollout_fast``, which
ask ``done.any()`` on the host to decide on partial resets.

Without CUDA it prints one line saying it was skipped and exits 0 (the paths still run once on
CPU, so an API change is caught by the suite's ``--quick`` run, ``tests/test_benchmarks.py``).

    python benchmarks/no_host_sync.py [--batch 4096] [--iters 5] [--quick]
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

import torch

from taskvar_torch import keys, rng
from taskvar_torch.config import load_config
from taskvar_torch.controllers import make_controller, option_first
from taskvar_torch.factory import build_heads, make_learner, make_subtasks
from taskvar_torch.families.taxi.env import TaxiEnv
from taskvar_torch.families.wargus import WargusEnv
from taskvar_torch.families.wargus import dynamics as wargus
from taskvar_torch.families.windy import WindyGridEnv
from taskvar_torch.families.windy import dynamics as windy
from taskvar_torch.heads.bundle import Heads
from taskvar_torch.heads.networks import make_head
from taskvar_torch.subtasks import Hierarchy
from taskvar_torch.training.collection import make_training_env
from taskvar_torch.training.replay import make_replay_buffer, raw_transitions

S, A = 25, 4  # the default windy grid's one-hot observation and actions


def env_paths(device: torch.device, B: int) -> dict[str, Callable[[], object]]:
    """The env step hot paths, set up on ``device`` with batch ``B``."""
    paths: dict[str, Callable[[], object]] = {}
    model = windy.WindyModel(windy.WindyLayout.named("default"), device)
    cell = model.start_cells[torch.arange(B, device=device) % len(model.start_cells)]
    action = torch.randint(0, 4, (B,), device=device)
    direction = torch.randint(0, 2, (B,), device=device)
    key32 = rng.to_i32(rng.sub_env_key(0, torch.arange(B, device=device)))
    t = torch.zeros(B, dtype=torch.int32, device=device)
    threshold = rng.probability_threshold(torch.rand(B, device=device))

    def windy_pure():
        gust = rng.bernoulli_i32(key32, t, threshold)
        return windy.step(model, cell, action, direction, gust)

    paths["windy.step (pure)"] = windy_pure

    cfg = wargus.WargusConfig(size=16, num_patrols=3, num_items=2, hit_prob=0.5, patrol_speed=0.8)
    wmodel = wargus.WargusModel(cfg, device)
    wkey = torch.arange(B, device=device, dtype=torch.int64)
    waction = torch.randint(0, 4, (B,), device=device)

    def wargus_pure():
        state = wargus.reset(wmodel, wkey)
        _, seen, _ = wargus.observe(wmodel, state)
        state, picked, destroyed = wargus.step(wmodel, state, waction, wkey)
        _, seen2, _ = wargus.observe(wmodel, state)
        return wargus.item_lost(seen, seen2, picked), destroyed

    paths["wargus reset/step/observe (pure)"] = wargus_pure

    wenv = WindyGridEnv(num_envs=B, seed=0, validate_actions=False, device=device)
    wtd = wenv.reset()
    wtd.set(keys.ACTION, action)
    paths["WindyGridEnv._advance"] = lambda: wenv._advance(action)
    paths["WindyGridEnv._step"] = lambda: wenv._step(wtd)

    tenv = TaxiEnv(B, instances="storm", seed=0, validate_actions=False, device=device)
    tenv.reset()
    taction = torch.randint(0, 6, (B,), device=device)
    paths["TaxiEnv._advance"] = lambda: tenv._advance(taction)

    genv = WargusEnv(num_envs=B, seed=0, validate_actions=False, device=device)
    genv.reset()
    gaction = torch.randint(0, genv.action_spec.space.n, (B,), device=device)
    paths["WargusEnv.step_all"] = lambda: genv.step_all(gaction)
    return paths


def make_heads(num_options: int, device: torch.device) -> Heads:
    """A small bundle (MLP 2 x 64 per head) over the default grid's one-hot observation."""
    names = ("root", "exit_north", "exit_south")[-num_options:]
    k, hidden = num_options, (64, 64)
    return Heads(
        names,
        averaging=make_head(keys.ACTION_VALUE, S, A, hidden),
        options=make_head(keys.OPTION_ACTION_VALUE, S, (k, A), hidden),
        switching=make_head(keys.OPTION_VALUE, S, k, hidden),
        max_value=make_head(keys.MAX_VALUE, S, k, hidden),
        robustness=make_head(keys.ROBUSTNESS, S, (k, A), hidden),
    ).to(device)


def controller_paths(device: torch.device, B: int) -> dict[str, Callable[[], object]]:
    """Every controller's batched decisions at batch ``B``."""
    paths: dict[str, Callable[[], object]] = {}
    tree = Hierarchy(root="root", children={"root": ("exit_north", "exit_south")})
    obs = torch.zeros(B, S, device=device)
    obs[torch.arange(B, device=device), torch.randint(0, S, (B,), device=device)] = 1.0
    inputs = {keys.OBSERVATION: obs}
    for name in ("averaging", "options", "interruption", "hierarchy"):
        heads = make_heads(3 if name == "hierarchy" else 2, device)
        ctrl = make_controller(name, heads, hierarchy=tree, tau=0.0)
        with torch.no_grad():
            vals = ctrl.head_values(inputs)
        vals_of = {k: option_first(v).contiguous() for k, v in vals.items()}
        run = torch.randint(-1, ctrl.num_options, (B,), device=device) if ctrl.stateful else None
        paths[f"{name}.decide"] = lambda c=ctrl, v=vals, r=run: c.decide(v, r, None)
        paths[f"{name}.decide_of"] = lambda c=ctrl, v=vals_of, r=run: c.decide_of(v, r, None)
        paths[f"{name}.act"] = lambda c=ctrl, r=run: c.act(inputs, r)
    return paths


def learner_paths(device: torch.device, iters: int) -> dict[str, Callable[[], object]]:
    """``MultiHeadLearner.update`` of the windy config's heads on samples drawn beforehand."""
    cfg = load_config(
        "configs/windy.yaml",
        [f"device={device}", "env.num_envs=64", "train.batch_size=256", "train.buffer_size=4096"],
    )
    torch.manual_seed(0)
    env = make_training_env(cfg)
    subtasks = make_subtasks(cfg, env.base_env)
    heads = build_heads(cfg, env, subtasks)
    learner = make_learner(cfg, heads, subtasks)
    buffer = make_replay_buffer(cfg, torch.Generator().manual_seed(0))
    batch = env.rollout(16, break_when_any_done=False)  # random actions: data for the losses
    buffer.extend(raw_transitions(batch, cfg.train.max_value_estimator == "instance"))
    samples = [buffer.sample().to(device) for _ in range(iters + 1)]
    it = iter(samples)
    return {"MultiHeadLearner.update": lambda: learner.update(next(it))}


def check(name: str, fn: Callable[[], object], iters: int, cuda: bool) -> str | None:
    """Warm ``fn`` up once with the debug mode off, then run it ``iters`` times with it on
    ("error"); the error of the first synchronising call, or None."""
    fn()
    if not cuda:
        return None
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for _ in range(iters):
            fn()
    except RuntimeError as e:
        return str(e).splitlines()[0] if str(e) else repr(e)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    torch.cuda.synchronize()
    return None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=4096, help="sub-envs / decisions per call")
    ap.add_argument("--iters", type=int, default=5, help="calls per path under the debug mode")
    ap.add_argument("--quick", action="store_true", help="batch 64, 2 calls per path (smoke run)")
    args = ap.parse_args(argv)
    if args.quick:
        args.batch, args.iters = 64, 2
    torch.set_num_threads(1)
    cuda = torch.cuda.is_available()
    device = torch.device("cuda" if cuda else "cpu")
    paths = {**env_paths(device, args.batch), **controller_paths(device, args.batch)}
    paths.update(learner_paths(device, 2 + args.iters))
    failed = []
    for name, fn in paths.items():
        error = check(name, fn, args.iters, cuda)
        if cuda:
            print(f"  {'SYNC' if error else 'ok':4s}  {name}" + (f": {error}" if error else ""))
        if error:
            failed.append(name)
    if not cuda:
        print(
            f"no_host_sync: skipped, no CUDA device (the {len(paths)} hot paths ran once on CPU; "
            "the sync check needs a GPU)"
        )
        return 0
    print(
        f"no_host_sync on {torch.cuda.get_device_name()}, batch {args.batch}, {args.iters} calls "
        f"per path: {len(paths) - len(failed)}/{len(paths)} without a host sync"
    )
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
