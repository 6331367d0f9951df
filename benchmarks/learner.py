"""The heads' learner against its own arithmetic, side by side in one run (docs/benchmarks.md, Learner).

Per update, single-threaded, on windy replay data of ``configs/windy.yaml`` (batch 256):

(i)   bare DQN: one CleanRL-style MLP ([64, 64], Adam, double-DQN target, Polyak target): the
      floor of one small-network update on this machine;
(ii)  bare heads: exactly what taskvar's heads learner computes for the config, written out in
      plain tensors: the stacked heads (averaging, options, switching, the max-value gap) in one
      ``baddbmm`` pass at ``s`` and two on the batch's distinct ``s'`` (gathered back; distinct
      rows by one float64 key per row, ``heads/max_value.py`` ``distinct_rows``), the ``instance`` critic's TD pass and its
      target grid over the batch's distinct observations x 64 instances, every loss, one backward, the per-head gradient clip, one fused Adam step and one
      ``lerp_`` of every target; the relabelled batch is given (as CleanRL's sample is);
      checked against (iii): the same losses on the same weights and batch;
(ii') as (ii) with the s' passes and the critic grid on every row (B and B x 64 rows), what the
      learner ran before (issue 47);
(iii) taskvar's update: ``MultiHeadLearner.update`` on replay samples drawn beforehand
      (relabelling included); ``--recurrent`` adds the recurrent baseline's ``BaselineLearner``
      update (r) and the same as it ran before issue 47 (r': packed ``nn.GRU``, per-tensor Adam),
      ``--seeds N`` the update of ``taskvar train --seeds N`` (N runs' heads in one stack).

Rounds interleave the paths (i, ii, ii', iii, i, ...) and the medians are compared, so a loaded
machine slows all alike; prints ms per update and the ratios (iii)/(ii), (ii)/(i).

``--time-to-quality``: runs ``taskvar train`` on ``configs/windy.yaml`` (plus overrides) and
reports the wall until every oracle figure it prints is within the bounds of
``tests/families/windy/test_heads_windy.py`` and stays there (checked on learning-curve snapshots
of the eval weights, ``train.heads_every = --every`` frames, each with its wall seconds).

Usage: ``python benchmarks/learner.py [--rounds 7] [--updates 50] [--recurrent] [--seeds 5]
[--quick]``;
``python benchmarks/learner.py --time-to-quality [--every 5000] [override ...]``.
"""

from __future__ import annotations

import argparse
import copy
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from taskvar_torch.config import load_config
from taskvar_torch.factory import build_heads, make_learner, make_subtasks
from taskvar_torch.heads.behaviour import BehaviourPolicy
from taskvar_torch.heads.max_value import distinct_rows
from taskvar_torch.heads.networks import head_network
from taskvar_torch.training.collection import make_training_env
from taskvar_torch.training.replay import make_replay_buffer
from taskvar_torch.training.run_state import replay_rows

CONFIG = "configs/windy.yaml"


def real_learner(cfg, frames: int):
    """taskvar's learner of ``cfg`` and a replay buffer of ``frames`` real transitions."""
    from torchrl.collectors import Collector

    torch.manual_seed(cfg.seed)
    env = make_training_env(cfg)
    subtasks = make_subtasks(cfg, env.base_env)
    heads = build_heads(cfg, env, subtasks)
    learner = make_learner(cfg, heads, subtasks)
    buffer = make_replay_buffer(cfg, torch.Generator().manual_seed(0))
    policy = BehaviourPolicy(heads, subtasks, env.action_spec, option_prob=0.5)
    collector = Collector(env, policy, frames_per_batch=1024, total_frames=frames)
    for batch in collector:
        buffer.extend(replay_rows(cfg, batch))
    collector.shutdown()
    return learner, buffer


class BareDQN:
    """(i) One MLP, CleanRL's DQN update (double-DQN target, Polyak target by ``lerp_``)."""

    def __init__(self, obs_dim: int, actions: int, hidden=(64, 64), lr=2e-3, tau=0.05):
        dims = [obs_dim, *hidden, actions]
        layers: list[nn.Module] = []
        for d_in, d_out in zip(dims[:-1], dims[1:]):
            layers += [nn.Linear(d_in, d_out), nn.ReLU()]
        self.q = nn.Sequential(*layers[:-1])
        self.target = copy.deepcopy(self.q).requires_grad_(False)
        self.opt = torch.optim.Adam(self.q.parameters(), lr=lr, fused=True)
        self.params, self.tparams = list(self.q.parameters()), list(self.target.parameters())
        self.tau = tau

    def update(self, b) -> None:
        with torch.no_grad():
            best = self.q(b.next_observation).argmax(-1, keepdim=True)
            nxt = self.target(b.next_observation).gather(-1, best).squeeze(-1)
            y = b.reward + 0.99 * (1.0 - b.terminated) * nxt
        q = self.q(b.observation).gather(-1, b.action.unsqueeze(-1)).squeeze(-1)
        loss = F.mse_loss(q, y)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        torch._foreach_lerp_(self.tparams, self.params, self.tau)


def _linears(module: nn.Module) -> list[tuple[torch.Tensor, torch.Tensor]]:
    return [(m.weight, m.bias) for m in module.modules() if isinstance(m, nn.Linear)]


def _mlp(layers, x: torch.Tensor) -> torch.Tensor:
    for i, (w, b) in enumerate(layers):
        x = F.linear(x, w, b)
        if i < len(layers) - 1:
            x = x.relu()
    return x


def _stack(ws, bs, x: torch.Tensor) -> torch.Tensor:  # (M, D) -> (K, M, P)
    h = x.unsqueeze(0).expand(ws[0].shape[0], *x.shape)
    for i, (w, b) in enumerate(zip(ws, bs)):
        h = torch.baddbmm(b, h, w)
        if i < len(ws) - 1:
            h = h.relu()
    return h


class BareHeads:
    """(ii) The heads learner's update for the windy config, in plain tensors (a copy of the
    learner's weights and targets; its own fused Adam)."""

    def __init__(self, learner, full_grid: bool = False):
        loss = learner.loss
        s = loss.settings
        assert loss.stack is not None and loss.avg_root is None and loss.seeds == 1
        assert (
            s.double_q and loss.mu_bar_temperature is None and s.max_value_estimator == "instance"
        )
        assert set(loss.heads.heads.keys()) == set(loss.head_names)
        assert set(loss.head_names) == {"averaging", "options", "switching", "max_value"}
        self.gamma, self.M = s.gamma, s.max_value_instances
        self.full_grid = full_grid
        net = lambda h, n: head_network(h.heads[n] if hasattr(h, "heads") else h[n])  # noqa: E731
        self.idx = {
            "averaging": net(loss.heads, "averaging").index,
            "options": net(loss.heads, "options").index,
            "switching": net(loss.heads, "switching").index,
            "gap": net(loss.heads, "max_value").gap.index,
        }
        self.O, self.A = net(loss.heads, "options").out_shape

        def clone(ts, grad):
            return [t.detach().clone().requires_grad_(grad) for t in ts]

        st, tst = loss.stack, loss.target_stack
        self.ws, self.bs = clone(st.weights, True), clone(st.biases, True)
        self.tws, self.tbs = clone(tst.weights, False), clone(tst.biases, False)
        crit = net(loss.heads, "max_value").critic
        tcrit = net(loss.target_heads, "max_value").critic
        self.crit = [tuple(clone(p, True)) for p in _linears(crit)]
        self.tcrit = [tuple(clone(p, False)) for p in _linears(tcrit)]
        self.stacked = [*self.ws, *self.bs]
        self.online = [*self.stacked, *(p for wb in self.crit for p in wb)]
        self.target = [*self.tws, *self.tbs, *(p for wb in self.tcrit for p in wb)]
        lr = learner.optimizer.param_groups[0]["lr"]
        self.opt = torch.optim.Adam(self.online, lr=lr, fused=True)
        self.tau = 1.0 - learner.target_updater.eps
        self.max_norm = learner.max_grad_norm
        self.critic_params = [p for wb in self.crit for p in wb]

    def losses(self, b) -> dict[str, torch.Tensor]:
        B, O, A, i = b.observation.shape[0], self.O, self.A, self.idx  # noqa: E741
        out = _stack(self.ws, self.bs, b.observation)  # (K, B, P)
        with torch.no_grad():  # s' passes on the distinct s' (ii), or on every row (ii')
            ahead, back = b.next_observation, slice(None)
            if not self.full_grid:
                ahead, back = distinct_rows(ahead)
            nxt = _stack(self.ws, self.bs, ahead)[:, back]
            tgt = _stack(self.tws, self.tbs, ahead)[:, back]
        q_avg, q_avg_n, q_avg_t = (x[i["averaging"], :, :A] for x in (out, nxt, tgt))
        q_o, q_o_n, q_o_t = (x[i["options"], :, : O * A].view(B, O, A) for x in (out, nxt, tgt))
        q_mu, q_mu_n, q_mu_t = (x[i["switching"], :, :O] for x in (out, nxt, tgt))
        gap = out[i["gap"], :, :O]
        notdone = 1.0 - b.terminated
        # averaging: double DQN
        with torch.no_grad():
            best = q_avg_n.argmax(-1, keepdim=True)
            y = b.reward + self.gamma * notdone * q_avg_t.gather(-1, best).squeeze(-1)
        l_avg = (q_avg.gather(-1, b.action.unsqueeze(-1)).squeeze(-1) - y).pow(2).mean()
        # options: double DQN on subtask rewards over each initiation set
        init = b.initiation.float()
        act = b.action.view(-1, 1, 1).expand(-1, O, 1)
        with torch.no_grad():
            done = torch.maximum(b.terminated.unsqueeze(-1), b.beta_next)
            boot = q_o_t.gather(-1, q_o_n.argmax(-1, keepdim=True)).squeeze(-1)
            y_o = b.subtask_reward + self.gamma * (1.0 - done) * boot
        sq = (q_o.gather(-1, act).squeeze(-1) - y_o).pow(2)
        l_opt = ((sq * init).sum(0) / init.sum(0).clamp_min(1.0)).sum()
        # switching: intra-option Q-learning under greedy mu_bar
        pi = q_o.detach().argmax(-1)
        consistent = (b.initiation & (pi == b.action.unsqueeze(-1))).float()
        with torch.no_grad():
            allowed = b.initiation_next | ~b.initiation_next.any(-1, keepdim=True)
            mu = F.one_hot(q_mu_n.masked_fill(~allowed, float("-inf")).argmax(-1), O).float()

            def cont(v):
                return (1.0 - b.beta_next) * v + b.beta_next * (mu * v).sum(-1, keepdim=True)

            y_mu = b.reward.unsqueeze(-1) + self.gamma * notdone.unsqueeze(-1) * cont(q_mu_t)
        den_c = consistent.sum(0).clamp_min(1.0)
        l_sw = (((q_mu - y_mu).pow(2) * consistent).sum(0) / den_c).sum()
        # max value (instance estimator): critic TD in its own instance, Q_hat on the grid's max
        z = b.instance
        c = _mlp(self.crit, torch.cat([b.observation, z], -1))
        with torch.no_grad():
            c_n = _mlp(self.tcrit, torch.cat([b.next_observation, z], -1))
            y_c = b.reward.unsqueeze(-1) + self.gamma * notdone.unsqueeze(-1) * cont(c_n)
            zs = z[: self.M]
            obs, rows = b.observation, None
            if not self.full_grid:
                obs, rows = distinct_rows(obs)
            U, M = obs.shape[0], zs.shape[0]
            grid = torch.cat([obs.unsqueeze(1).expand(U, M, -1), zs.expand(U, M, -1)], -1)
            q_max = _mlp(self.tcrit, grid).max(1).values
            q_max = q_max if rows is None else q_max[rows]
        q_hat = q_mu.detach() + F.softplus(gap)
        l_c = (((c - y_c).pow(2) * consistent).sum(0) / den_c).sum()
        l_hat = (((q_hat - q_max).pow(2) * init).sum(0) / init.sum(0).clamp_min(1.0)).sum()
        return {
            "loss_averaging": l_avg,
            "loss_options": l_opt,
            "loss_switching": l_sw,
            "loss_max_value": l_c + l_hat,
        }

    def update(self, b) -> None:
        total = sum(self.losses(b).values())
        self.opt.zero_grad(set_to_none=True)
        total.backward()
        grads = [p.grad for p in self.stacked if p.grad is not None]  # per-member clip
        sq = torch.stack([g.pow(2).flatten(1).sum(1) for g in grads]).sum(0)
        coef = (self.max_norm / (sq.sqrt() + 1e-6)).clamp(max=1.0)
        for g in grads:
            g.mul_(coef.view(-1, *([1] * (g.dim() - 1))))
        gs = [p.grad for p in self.critic_params]
        norm = torch.linalg.vector_norm(torch.stack(torch._foreach_norm(gs)))
        torch._foreach_mul_(gs, (self.max_norm / (norm + 1e-6)).clamp(max=1.0))
        self.opt.step()
        torch._foreach_lerp_(self.target, self.online, self.tau)


def check_same_losses(bare: BareHeads, learner, batch) -> None:
    """(ii) computes what (iii) does: the same losses on the same weights and batch."""
    with torch.no_grad():
        ours, theirs = bare.losses(batch), learner.losses(batch)
    for k, v in theirs.items():
        if not torch.allclose(ours[k], v, rtol=1e-4, atol=1e-5):
            sys.exit(f"bare heads differ from the learner on {k}: {ours[k]} vs {v}")


def recurrent_updates(cfg) -> dict:
    """The recurrent baseline's ``BaselineLearner`` update on replay slices drawn beforehand
    (``--recurrent``; as (iii), sampling outside the timing): (r) as shipped (its GRU run over the
    padded slices, ``heads/recurrent.py`` ``PaddedGRU``), (r') as before issue 47 (the same bits): the same
    weights and slices through ``nn.GRU`` on a packed sequence, and per-tensor Adam (not foreach)."""
    from torchrl.collectors import Collector

    from taskvar_torch.training.baselines import BaselineLearner, build_for_training

    net, _, env = build_for_training(cfg, "recurrent")
    packed_net = copy.deepcopy(net)
    padded = packed_net[1].gru
    packed = nn.GRU(padded.input_size, padded.hidden_size, batch_first=True)
    packed.load_state_dict(padded.state_dict())
    packed_net[1].gru = packed
    learner = BaselineLearner(net, env.action_spec, cfg, True)
    before = BaselineLearner(packed_net, env.action_spec, cfg, True)
    before.optim = torch.optim.Adam(before.loss.parameters(), lr=float(cfg.train.lr), foreach=False)
    collector = Collector(env, net, frames_per_batch=1024, total_frames=4096)
    for data in collector:
        learner.store(data)
    collector.shutdown()
    samples = [learner.sample() for _ in range(64)]
    it = iter(range(10**9))
    return {
        "(r) recurrent BaselineLearner.update": lambda: learner.update(samples[next(it) % 64]),
        "(r') recurrent as before (packed, per-tensor)": lambda: before.update(
            samples[next(it) % 64]
        ),
    }


def seeds_update(cfg, seeds: int, samples):
    """``train.seeds = S``'s learner (``S`` runs' heads stacked, heads/seeds.py) on ``S`` seed-major
    replay samples: what one update of ``taskvar train --seeds S`` computes."""
    from taskvar_torch.heads.seeds import stack_seeds

    env = make_training_env(cfg)
    subtasks = make_subtasks(cfg, env.base_env)
    heads = stack_seeds([build_heads(cfg, env, subtasks) for _ in range(seeds)])
    learner = make_learner(cfg, heads, subtasks)
    batches = [torch.cat(samples[i : i + seeds]) for i in range(0, len(samples) - seeds, seeds)]
    it = iter(range(10**9))
    return lambda: learner.update(batches[next(it) % len(batches)])


def timed(fn, n: int) -> tuple[float, float]:
    """ms per call over ``n`` calls: wall and this thread's CPU time."""
    start, cpu = time.perf_counter(), time.thread_time()
    for _ in range(n):
        fn()
    return (time.perf_counter() - start) / n * 1e3, (time.thread_time() - cpu) / n * 1e3


def update_benchmark(args) -> None:
    cfg = load_config(CONFIG, list(args.overrides))
    learner, buffer = real_learner(cfg, 2048 if args.quick else 8192)
    samples = [buffer.sample() for _ in range(64)]
    batches = [learner.loss.relabel(s) for s in samples]
    bare = BareHeads(learner)
    check_same_losses(bare, learner, batches[0])
    full = BareHeads(learner, full_grid=True)
    dqn = BareDQN(batches[0].observation.shape[1], bare.A)
    it = {"n": 0}

    def nxt(seq):
        it["n"] += 1
        return seq[it["n"] % len(seq)]

    paths = {
        "(i) bare DQN, one MLP": lambda: dqn.update(nxt(batches)),
        "(ii) bare heads (distinct-state grid)": lambda: bare.update(nxt(batches)),
        "(ii') bare heads, s' and grid on every row": lambda: full.update(nxt(batches)),
        "(iii) taskvar MultiHeadLearner.update": lambda: learner.update(nxt(samples)),
    }
    if args.recurrent:
        paths.update(recurrent_updates(cfg))
    if args.seeds > 1:
        paths[f"(s) --seeds {args.seeds}: one batched update"] = seeds_update(
            cfg, args.seeds, samples
        )
    distinct = statistics.median(torch.unique(b.observation, dim=0).shape[0] for b in batches)
    for fn in paths.values():  # warm-up
        timed(fn, 3)
    times: dict[str, list[tuple[float, float]]] = {k: [] for k in paths}
    for _ in range(args.rounds):
        for k, fn in paths.items():
            times[k].append(timed(fn, args.updates))
    med = {k: statistics.median(w for w, _ in v) for k, v in times.items()}
    cpu = {k: statistics.median(c for _, c in v) for k, v in times.items()}
    B = batches[0].observation.shape[0]
    print(
        f"windy learner, batch {B} ({distinct:.0f} distinct states per batch, median), "
        f"{torch.get_num_threads()} thread(s), {args.rounds} rounds x {args.updates} updates"
    )
    for k, v in med.items():
        print(f"  {k:42s} {v:7.3f} ms/update ({cpu[k]:7.3f} CPU ms)")
    i, ii, ii_full, iii = (med[k] for k in list(paths)[:4])
    print(f"  ratio (iii)/(ii)  = {iii / ii:.2f}   (the package over its own arithmetic)")
    print(f"  ratio (ii)/(i)    = {ii / i:.2f}   (the heads' arithmetic over one bare MLP)")
    print(f"  ratio (ii')/(ii)  = {ii_full / ii:.2f}   (every row over distinct states)")
    if args.recurrent:
        r, r_packed = (k for k in paths if k.startswith("(r"))
        heads = list(paths)[3]
        for what, x, y, about in (
            ("(r)/(iii)", r, heads, "the recurrent baseline's update over the heads'"),
            ("(r')/(r) ", r_packed, r, "before over after"),
        ):
            print(
                f"  ratio {what}  = {med[x] / med[y]:.2f} ({cpu[x] / cpu[y]:.2f} CPU)   ({about})"
            )
    if args.seeds > 1:
        k = f"(s) --seeds {args.seeds}: one batched update"
        print(
            f"  ratio (s)/(iii)   = {med[k] / iii:.2f}   ({args.seeds} seeds' update over one seed's)"
        )


QUALITY = {  # tests/families/windy/test_heads_windy.py, on the default layout
    "averaging": lambda r: r["averaging_return"] >= r["oracle_averaging_return"] - 0.5,
    "options": lambda r: all(
        g >= b - 0.5 for g, b in zip(r["option_returns"], r["oracle_option_returns"])
    ),
    "mu_bar": lambda r: r["mu_bar_cells"] >= 8 and r["mu_bar_agreement"] == 1.0,
    "max_value": lambda r: r["max_value_error"] <= 1.0,
    "interruption": lambda r: r["interruption_agreement"] >= 0.95,
}


def time_to_quality(args) -> None:
    """Wall of ``train`` until every oracle figure is within its test bound, read off the
    learning-curve snapshots (``train.heads_every``: the eval weights and the wall seconds at
    each); the checks run after training, outside the wall."""
    from taskvar_torch.checkpoint import load_checkpoint
    from taskvar_torch.factory import load_heads
    from taskvar_torch.families.windy import WindyOracle
    from taskvar_torch.heads.validate import compare_with_oracle
    from taskvar_torch.training import train
    from taskvar_torch.training.run_state import HEADS_SNAPSHOTS

    overrides = [*args.overrides, f"train.heads_every={args.every}", "train.checkpoint_every=0"]
    if args.quick:
        overrides += ["train.total_frames=4096", "train.init_random_frames=1024"]
    cfg = load_config(CONFIG, overrides)
    print(f"time to quality: {CONFIG} {' '.join(args.overrides)}")
    with tempfile.TemporaryDirectory() as out:
        result = train(cfg, out, progress=False)
        wall = result["seconds"]
        oracle = WindyOracle(
            cfg.env.windy.layout,
            gamma=cfg.train.gamma,
            horizon=cfg.env.windy.horizon,
            train_instances="train",
        )
        points = sorted((Path(out) / HEADS_SNAPSHOTS).glob("heads_*.pt"))
        met = None
        for path in [*points, Path(result["final"])]:
            counters = load_checkpoint(path).get("counters", {})
            frames = int(counters.get("frames", result["frames"]))
            at = float(counters.get("seconds", wall))
            r = compare_with_oracle(load_heads(path)[0], oracle)
            ok = {k: bool(f(r)) for k, f in QUALITY.items()}
            out_of = ",".join(k for k, v in ok.items() if not v)
            print(
                f"  {frames:6d} frames {at:6.1f} s: averaging {r['averaging_return']:.3f} "
                f"options {'/'.join(f'{x:.3f}' for x in r['option_returns'])} "
                f"mu_bar {r['mu_bar_agreement']:.3f} max|Q_hat-oracle| "
                f"{r['max_value_error']:.3f} interruption {r['interruption_agreement']:.3f}  "
                + ("within every bound" if not out_of else f"out: {out_of}")
            )
            if met is None and not out_of:
                met = (frames, at)
            elif out_of:
                met = None  # within the bounds from the last point that stays within them
    print(
        f"train wall {wall:.1f} s for {result['frames']} frames, {result['updates']} updates; "
        + (
            "not within every bound at the end"
            if met is None
            else f"within every bound from {met[0]} frames on, {met[1]:.1f} s"
        )
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rounds", type=int, default=7)
    p.add_argument("--updates", type=int, default=50)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--recurrent", action="store_true", help="also the recurrent baseline's update")
    p.add_argument("--seeds", type=int, default=1, help="> 1: also train.seeds=N's batched update")
    p.add_argument("--time-to-quality", action="store_true")
    p.add_argument("--every", type=int, default=5000, help="frames between quality checks")
    p.add_argument("--quick", action="store_true", help="tiny sizes, a few seconds")
    p.add_argument("overrides", nargs="*", help="config overrides, key.sub=value")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    if args.quick:
        args.rounds, args.updates = 2, 2
    if args.time_to_quality:
        time_to_quality(args)
    else:
        update_benchmark(args)


if __name__ == "__main__":
    main()
