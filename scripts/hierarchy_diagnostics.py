"""Why does the composition hierarchy score what it scores? (Wargus, paper §3.4-3.5, Algorithm 2.)

Loads the heads of a ``wargus-fig4`` repetition (``DIR/rep0/final.pt``) and plays N fixed instances
greedily with: the averaging policy, each option's policy alone (TG, FE, TG+FE), and the hierarchy
(Algorithm 2 as the experiments build it, ``taskvar_torch.factory.make_method_controller``: the
checkpoint config's thresholds, calibrated on training states, unless ``--tau`` fixes one). Prints items per episode,
``item_lost`` events per episode, destruction rate, and for the hierarchy the control split, how
often control moved, and R(root, s, a_root) on the steps where the root acted and lost sight of the
item; and the options controller (items, share of steps per option). For the averaging policy it also checks the root's robustness critic against Monte Carlo:
R(root, s, a) predicted at each step vs the discounted return-to-go of the root's robustness rewards
(gamma = ``train.robustness_gamma``) actually received along the same greedy rollout, over the
steps where the item is seen and the patrol is not (where the root should take control), and the
fraction of those steps with R > tau (predicted, and by the rollout). Last, every option's critic
against Monte Carlo returns of its own runs up to its termination, as its TD target is defined
(``taskvar_torch.families.wargus.robustness_mc``, docs/hierarchy-critics.md). Single-threaded; a few
seconds per 32 episodes.

    python scripts/hierarchy_diagnostics.py /tmp/h1/rep0/final.pt --episodes 32
"""

from __future__ import annotations

import argparse
import dataclasses

import torch
from torchrl.envs import TransformedEnv

from taskvar_torch import keys
from taskvar_torch.factory import load_heads, make_method_controller, make_subtasks
from taskvar_torch.families.wargus import dynamics as wargus
from taskvar_torch.families.wargus.robustness_mc import (
    fixed_instances_env,
    format_report,
    robustness_monte_carlo,
)


@torch.no_grad()
def play(heads, cfg, method: str, seeds, tau: float) -> dict[str, float]:
    n = len(seeds)
    env = fixed_instances_env(cfg, seeds)
    names = list(heads.option_names)
    subtasks = make_subtasks(cfg, env)
    ctrl = (
        make_method_controller(cfg, "hierarchy", heads, subtasks) if method == "hierarchy" else None
    )
    td = env.reset()
    running = torch.full((n,), -1, dtype=torch.int64)
    alive = torch.ones(n, dtype=torch.bool)
    items = torch.zeros(n)
    lost = torch.zeros(n)
    control = torch.zeros(len(names))
    moves = torch.zeros(n)
    root_lost_r: list[torch.Tensor] = []
    root = root_id = names.index(subtasks.hierarchy.root)
    r_pred: list[torch.Tensor] = []  # (n,) R(root, s, a) of the acted action, per step
    r_rew: list[torch.Tensor] = []  # (n,) root robustness reward of the step
    masks: list[torch.Tensor] = []  # (n,) alive, item seen, patrol unseen at s
    unseen: list[torch.Tensor] = []  # (n,) alive, item unseen at s
    for _ in range(env.horizon):
        td = heads(td)
        q_opt = td.get(keys.OPTION_ACTION_VALUE)  # (B, O, A)
        option = None
        if method == "averaging":
            action = td.get(keys.ACTION_VALUE).argmax(-1)
        elif method in names:
            action = q_opt[:, names.index(method)].argmax(-1)
        else:  # hierarchy: the experiments' controller (calibrated on training states)
            rob = td.get(keys.ROBUSTNESS)
            td.set(keys.RUNNING_OPTION, running)
            td = ctrl(td)
            action, option = td.get(keys.ACTION), td.get(keys.OPTION)
            control += torch.bincount(option[alive], minlength=len(names)).float()
            moves += ((running >= 0) & (option != running) & alive).float()
            r_root = rob[torch.arange(n), root, action]  # R(root, s, a) of the acted action
        td.set(keys.ACTION, action)
        td = env.step(td)
        nxt = td.get(keys.NEXT)
        if method == "averaging":
            rob = td.get(keys.ROBUSTNESS)  # (n, O, A)
            r_pred.append(rob[torch.arange(n), root_id, action])
            r_rew.append(subtasks.robustness_reward(td)[:, root_id] * alive)
            seen = td.get(wargus.ITEM_SEEN).reshape(n) & ~td.get(wargus.PATROL_SEEN).reshape(n)
            masks.append(seen & alive)
            unseen.append(~td.get(wargus.ITEM_SEEN).reshape(n) & alive)
        lost_now = nxt.get(wargus.ITEM_LOST).reshape(n) & alive
        lost += lost_now.float()
        if option is not None:
            sel = lost_now & (option == root)
            root_lost_r.append(r_root[sel])
            running = option
        items += torch.where(alive, nxt.get(keys.REWARD).reshape(n), 0.0)
        alive = alive & ~nxt.get(keys.DONE).reshape(n)
        if not bool(alive.any()):
            break
        td = nxt.clone()
    out = {
        "items": float(items.mean()),
        "item_lost": float(lost.mean()),
        "destroyed": float((~alive).float().mean()),
    }
    if method == "averaging" and r_pred:
        g = cfg.train.robustness_gamma
        rtg, acc = [], torch.zeros(n)
        for r in reversed(r_rew):  # discounted return-to-go (0 after the episode ends)
            acc = r + g * acc
            rtg.append(acc)
        rtg.reverse()
        for key, ms in (("R_root_item_seen", masks), ("R_root_item_unseen", unseen)):
            m = torch.stack(ms)
            pred, mc = torch.stack(r_pred)[m], torch.stack(rtg)[m]
            out[key] = (
                f"critic {pred.mean():.2f} vs MC {mc.mean():.2f} (n={m.sum()}); R>tau: "
                f"critic {(pred > tau).float().mean():.0%}, MC {(mc > tau).float().mean():.0%}"
            )
    if method == "hierarchy":
        share = control / control.sum().clamp_min(1)
        out["control"] = "/".join(f"{n_}:{v:.0%}" for n_, v in zip(names, share.tolist()))
        out["moves"] = float(moves.mean())
        r = torch.cat(root_lost_r) if root_lost_r else torch.zeros(0)
        out["R_root_at_root_losses"] = (
            f"mean {r.mean():.2f} min {r.min():.2f} (n={r.numel()})" if r.numel() else "n=0"
        )
    return out


@torch.no_grad()
def play_options(heads, cfg, seeds) -> dict[str, object]:
    """The options controller (mu_bar over Q_mu, options run to termination): items per episode
    and the share of live steps each option ran."""

    n = len(seeds)
    env = fixed_instances_env(cfg, seeds)
    ctrl = make_method_controller(cfg, "options", heads, make_subtasks(cfg, env))
    td = TransformedEnv(env, ctrl.primer()).rollout(env.horizon, ctrl, break_when_any_done=False)
    done = td.get((keys.NEXT, keys.DONE)).reshape(n, -1)
    alive = (done.long().cumsum(-1) - done.long()) == 0  # steps up to the first episode end
    items = (td.get((keys.NEXT, keys.REWARD)).reshape(n, -1) * alive).sum(-1)
    option = td.get(keys.OPTION).reshape(n, -1)[alive]
    share = torch.bincount(option, minlength=len(heads.option_names)).float()
    share = share / share.sum().clamp_min(1)
    split = "/".join(f"{o}:{v:.0%}" for o, v in zip(heads.option_names, share.tolist()))
    return {"items": float(items.mean()), "option_steps": split}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint")
    ap.add_argument("--episodes", type=int, default=32)
    ap.add_argument("--tau", type=float, default=None)
    ap.add_argument("--first-seed", type=int, default=10_000)
    ap.add_argument(
        "--keep-share", type=float, default=None, help="calibrated threshold's keep share"
    )
    ap.add_argument(
        "--only", default=None, help="comma list of methods to play (robustness-mc: the MC check)"
    )
    a = ap.parse_args()
    torch.set_num_threads(1)
    heads, cfg = load_heads(a.checkpoint)
    if a.tau is not None:  # a fixed threshold instead of the configured one
        cfg = dataclasses.replace(
            cfg,
            train=dataclasses.replace(
                cfg.train, robustness_threshold="fixed", robustness_tau=a.tau
            ),
        )
    if a.keep_share is not None:
        cfg = dataclasses.replace(
            cfg, train=dataclasses.replace(cfg.train, robustness_keep_share=a.keep_share)
        )
    tau = cfg.train.robustness_tau
    seeds = range(a.first_seed, a.first_seed + a.episodes)
    t = cfg.train
    print(
        f"{a.checkpoint}: {a.episodes} episodes, tau={tau}, robustness_target="
        f"{getattr(t, 'robustness_target', 'greedy')}, root policy {t.hierarchy_root_policy}"
    )
    only = a.only.split(",") if a.only else None
    for method in ("averaging", *heads.option_names, "hierarchy"):
        if only is None or method in only:
            print(f"{method:>10}: {play(heads, cfg, method, seeds, tau)}")
    if only is None or "options" in only:
        print(f"{'options':>10}: {play_options(heads, cfg, list(seeds))}")
    if only is None or "robustness-mc" in only:
        print(
            f"robustness critics vs Monte Carlo returns of their own option's runs "
            f"(robustness_until={t.robustness_until}, gamma_R={t.robustness_gamma}, "
            f"threshold {t.robustness_threshold}):"
        )
        for line in format_report(robustness_monte_carlo(heads, cfg, list(seeds))):
            print(f"  {line}")


if __name__ == "__main__":
    main()
