"""Wargus Figure 4's fast loops equal the TorchRL ones (benchmarks/reference/wargus_torchrl_trial.py):
env, learning phase, batched test phases."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from torchrl.envs import InitTracker, TransformedEnv

from taskvar_torch import keys
from taskvar_torch.config import load_config
from taskvar_torch.controllers.side_by_side import SideBySide
from taskvar_torch.factory import make_env
from taskvar_torch.families.wargus import fig4, fig4_agent, fig4_repetition, fig4_trial
from taskvar_torch.families.wargus.env import WargusEnv
from taskvar_torch.heads.behaviour import BehaviourPolicy

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "benchmarks" / "reference"))
import wargus_torchrl_trial as reference  # noqa: E402  (the TorchRL loops, not the library)

torch.set_num_threads(1)

# small, but long enough episodes that items are picked, patrols chase and options switch
SMALL = [
    "env.wargus.size=10",
    "env.wargus.sight=3",
    "env.wargus.shoot_range=1",
    "env.wargus.horizon=40",
    "experiment.learning_episodes_per_trial=8",
    "train.init_random_frames=100",
    "train.batch_size=32",
    "train.frames_per_batch=64",
    "train.buffer_size=5000",
    "heads.hidden=[32]",
]
K, TRIALS, SEED = 3, 4, 5


def test_step_all_equals_envbase_step():
    """Same seed, same actions -> same observations, events, rewards, dones and instances."""
    a, b = (
        WargusEnv(6, seed=3, size=12, sight=4, shoot_range=2),
        WargusEnv(6, seed=3, size=12, sight=4, shoot_range=2),
    )
    td = a.reset()
    fast = b.reset_all()
    assert (td == fast.select(*td.keys(True, True))).all()
    g = torch.Generator().manual_seed(0)
    for _ in range(30):
        action = torch.randint(0, 8, (6,), generator=g)
        td = a.step(td.set(keys.ACTION, action))["next"]
        fast = b.step_all(action)
        assert set(fast.keys(True, True)) == set(td.keys(True, True))
        for key in td.keys(True, True):
            assert torch.equal(td[key], fast[key]), key
        td = td.exclude(keys.REWARD)


def _agent(cfg, torchrl: bool):
    torch.manual_seed(SEED)
    env = make_env(cfg, num_envs=cfg.experiment.learning_episodes_per_trial, seed=SEED)
    if torchrl:
        env = TransformedEnv(env, InitTracker())
    agent = fig4_agent.make_agent(cfg, env, SEED)
    return env, agent, SideBySide(fig4_agent.make_test_controllers(agent), K)


def _plain(tested: dict) -> dict:
    return {k: v.tolist() for k, v in tested.items()}


@pytest.mark.slow
def test_fast_trials_equal_torchrl_trials():
    """Learning phases (replay rows, updates, weights, global RNG) and test phases run later side
    by side on frozen heads equal the TorchRL loops trial by trial."""
    cfg = load_config(fig4.default_config_path(), SMALL)
    env, agent, policy = _agent(cfg, torchrl=True)
    test_env = TransformedEnv(
        fig4_agent.make_test_env(cfg, K, SEED), policy.controllers[-1].primer()
    )
    torch.manual_seed(11)
    ref = []
    for _ in range(TRIALS):
        learned = reference.learning_phase_torchrl(agent, env)
        ref.append(
            (learned, agent.updates, _plain(reference.test_phase_torchrl(policy, test_env, K)))
        )
    ref_agent, ref_rng = agent, torch.get_rng_state()

    env, agent, policy = _agent(cfg, torchrl=False)
    assert policy.batchable
    torch.manual_seed(11)
    learned, snapshots = [], []
    for _ in range(TRIALS):
        learned.append((fig4_trial.learning_phase(agent, env), agent.updates))
        snapshots.append(policy.head_values.snapshot())
    tested = fig4_trial.test_trials(
        policy, fig4_agent.make_test_env(cfg, K, SEED, 0, TRIALS), K, snapshots
    )
    fast = [(lrn, u, _plain(t)) for (lrn, u), t in zip(learned, tested)]
    assert fast == ref
    assert torch.equal(torch.get_rng_state(), ref_rng)
    assert agent.updates > 0 and sum(r[0]["learn_items"] for r in ref) > 0  # it did learn and pick
    n = len(ref_agent.buffer)
    assert len(agent.buffer) == n
    rows, ref_rows = agent.buffer[:n], ref_agent.buffer[:n]
    assert set(rows.keys(True, True)) == set(ref_rows.keys(True, True))
    for key in ref_rows.keys(True, True):
        assert torch.equal(rows[key], ref_rows[key]), key
    for p, q in zip(agent.heads.parameters(), ref_agent.heads.parameters()):
        assert torch.equal(p, q)
    # the last trial alone, on the live heads, as the batch gave it
    alone = fig4_trial.test_phase(policy, fig4_agent.make_test_env(cfg, K, SEED, TRIALS - 1), K)
    assert _plain(alone) == fast[-1][2]


def test_head_values_equal_each_head_alone():
    cfg = load_config(fig4.default_config_path(), SMALL)
    _, agent, policy = _agent(cfg, torchrl=False)
    obs = torch.rand(2 * 7, 24)
    values = policy.head_values(obs)
    snap = policy.head_values.snapshot()
    twice = policy.head_values(obs, [torch.stack(p) for p in zip(snap, snap)])
    for name in policy.head_names:
        head = agent.heads.heads[name]
        alone = head.module(obs)
        assert torch.equal(values[head.out_keys[0]], alone), name
        assert torch.equal(twice[head.out_keys[0]], alone), name


@pytest.mark.slow
def test_run_repetition_same_for_any_test_group(tmp_path):
    """Testing 2 trials side by side (then 1 left over) gives every trial's own episodes."""
    cfg = load_config(fig4.default_config_path(), [*SMALL, "experiment.trials=3"])
    one = fig4_repetition.run_repetition(cfg, 0, tmp_path / "one", test_group=1)
    two = fig4_repetition.run_repetition(cfg, 0, tmp_path / "two", test_group=2)
    for key in ("items", "interruptions", "control_steps", "learn_items", "frames", "updates"):
        assert one[key].tolist() == two[key].tolist(), key
    assert one["control_steps"].sum() > 0


@pytest.mark.slow
def test_behaviour_stacked_and_compiled_equal_each_head_alone():
    """The behaviour policy reads its heads from one stacked pass (HeadValues), and with
    compile=True (train.compile) runs it and its choices compiled: same actions, modes and global
    RNG draws as running each head on its own (paper widths, 30 rows)."""
    cfg = load_config(fig4.default_config_path(), SMALL[:-1])  # heads.hidden=[128, 128]
    env, agent, _ = _agent(cfg, torchrl=False)
    assert agent.behaviour._values is not None and agent.behaviour._values.stack is not None
    fused = BehaviourPolicy(  # the agent's, on the global stream rather than its own generator
        agent.heads, agent.subtasks, env.action_spec, option_prob=0.5, root_policy="averaging"
    )
    policies = [
        BehaviourPolicy(
            agent.heads,
            agent.subtasks,
            env.action_spec,
            option_prob=0.5,
            root_policy="averaging",
            stacked=stacked,
            compile=compile_,
        )
        for stacked, compile_ in ((False, False), (True, True))  # each head alone; compiled
    ]
    assert policies[0]._values is None
    td = env.reset_all()
    td.set("is_init", torch.ones(env.num_envs, 1, dtype=torch.bool))
    for step in range(12):
        outs = []
        for policy in (fused, *policies):
            policy.set_epsilon(0.3 * (step % 2))
            torch.manual_seed(step)
            out = policy(td.clone())
            # the draws left the stream in the same state
            outs.append({k: out[k] for k in (keys.ACTION, "behaviour")} | {"rng": torch.rand(3)})
        for out in outs[1:]:
            for key, v in out.items():
                assert torch.equal(v, outs[0][key]), (step, key)
        td = env.step_all(outs[0][keys.ACTION]).set("behaviour", outs[0]["behaviour"])
        td.set("is_init", torch.rand(env.num_envs, 1) < 0.1)
    assert policies[1]._compiled.failed is None


@pytest.mark.slow
def test_compiled_dynamics_equal_eager():
    """train.compile: step_all through the compiled dynamics gives the eager step's bits."""
    kw = dict(size=10, sight=4, shoot_range=2, patrol_speed=0.8, hit_prob=0.9, horizon=60)
    a, b = WargusEnv(12, seed=3, **kw), WargusEnv(12, seed=3, **kw)
    b.compile_dynamics()
    ta, tb = a.reset_all(), b.reset_all()
    g = torch.Generator().manual_seed(0)
    for _ in range(80):
        action = torch.randint(0, 8, (12,), generator=g)
        ta, tb = a.step_all(action), b.step_all(action)
        for key in ta.keys(True, True):
            assert torch.equal(ta[key], tb[key]), key
    assert b._dynamics.failed is None
