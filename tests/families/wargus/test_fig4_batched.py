"""Figure 4's repetitions batched in one loop give each repetition's numbers alone, bit for bit."""

from __future__ import annotations

import pytest
import torch
from budgets import FIG4  # tests/budgets.py

from taskvar_torch.config import load_config
from taskvar_torch.families.wargus import fig4, fig4_agent, fig4_repetition
from taskvar_torch.heads.seeds import load_seed, split_seed, stack_seeds

torch.set_num_threads(1)

TINY = [
    "env.wargus.size=12",
    "env.wargus.horizon=60",
    "experiment.runs=3",
    "experiment.trials=4",
    *FIG4,
]
KEYS = ("items", "interruptions", "control_steps", "item_lost", "learn_items", "frames", "updates")


@pytest.mark.slow
def test_batched_repetitions_equal_each_alone(tmp_path):
    """Three repetitions in one loop: each one's test scores (nominal and held-out), frames,
    updates and final weights equal its run alone, though their episodes end at different steps
    (a repetition whose episodes all ended draws nothing more) and their update phases fall at
    different steps."""
    cfg = load_config(fig4.default_config_path(), TINY)
    batch = fig4_repetition.run_repetitions_batched(
        cfg, [0, 1, 2], tmp_path / "batch", test_group=2
    )
    frames = [b["frames"].tolist() for b in batch]
    assert len({tuple(f) for f in frames}) == 3  # distinct streams, distinct phase lengths
    assert max(int(b["updates"][-1]) for b in batch) > 0
    for rep in (0, 2):
        alone = fig4_repetition.run_repetition(cfg, rep, tmp_path / f"alone{rep}", test_group=2)
        for key in (*KEYS, *(f"heldout_{k}" for k in fig4_repetition.HELDOUT_KEYS)):
            assert alone[key].tolist() == batch[rep][key].tolist(), (rep, key)
        a = torch.load(tmp_path / f"alone{rep}/rep{rep}/final.pt", weights_only=True)
        b = torch.load(tmp_path / f"batch/rep{rep}/final.pt", weights_only=True)
        for part in ("heads", "targets"):
            for k, v in a["models"][part].items():
                assert torch.equal(v, b["models"][part][k]), (rep, part, k)


def test_repetition_batches_split_evenly():
    assert fig4.repetition_batches(5, 1) == [[0, 1, 2, 3, 4]]
    assert fig4.repetition_batches(5, 2) == [[0, 1, 2], [3, 4]]
    assert fig4.repetition_batches(5, 5) == [[0], [1], [2], [3], [4]]
    assert fig4.repetition_batches(2, 8) == [[0], [1]]


def test_load_seed_is_split_seed_inverse():
    """Copying a run's weights into a stack and cutting it back out returns them; the other
    runs' rows are untouched."""
    cfg = load_config(fig4.default_config_path(), TINY)
    runs = [fig4_repetition._start_repetition(cfg, r, 1) for r in range(3)]
    heads = [r.agent.heads for r in runs]
    batch = stack_seeds(heads)
    with torch.no_grad():
        for p in heads[1].parameters():
            p.add_(1.0)
    load_seed(batch, 1, heads[1])
    template = fig4_repetition._start_repetition(cfg, 0, 1).agent.heads
    for s in range(3):
        out = split_seed(batch, s, template)
        for (name, p), q in zip(out.named_parameters(), heads[s].parameters()):
            assert torch.equal(p, q), (s, name)
    with pytest.raises(ValueError, match="seed index"):
        load_seed(batch, 3, heads[0])


def test_behaviour_blocks_draw_from_their_own_generator_only():
    """With generators, block s's draws come from generator s alone: the same whatever the other
    blocks hold, and an inactive block draws nothing (its generator is left as it was)."""
    cfg = load_config(fig4.default_config_path(), TINY)
    run = fig4_repetition._start_repetition(cfg, 0, 1)
    a = run.agent
    env = run.learn_env
    td = env.reset_all().set("is_init", torch.ones(env.num_envs, 1, dtype=torch.bool))

    def act(active):
        gens = [torch.Generator().manual_seed(s) for s in range(2)]
        batch = stack_seeds([a.heads, a.heads])
        pol = fig4_agent.make_behaviour(cfg, batch, a.subtasks, env.action_spec, gens)
        pol.set_epsilon(0.5)
        pol.set_active(active)
        both = torch.cat([td, td])
        out = pol(both.clone())
        return out["action"], out["behaviour"], [g.get_state() for g in gens]

    act_all, mode_all, gens_all = act(None)
    act_one, mode_one, gens_one = act([True, False])
    n = env.num_envs
    assert torch.equal(act_all[:n], act_one[:n]) and torch.equal(mode_all[:n], mode_one[:n])
    assert torch.equal(gens_all[0], gens_one[0])
    assert torch.equal(gens_one[1], torch.Generator().manual_seed(1).get_state())
    assert not torch.equal(gens_all[1], gens_one[1])
