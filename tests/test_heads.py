"""Head learners: losses against TorchRL's DQNLoss, the fused pass against the
heads run one by one, relabelling, first-visit replay, the behaviour policy, target updates."""

from __future__ import annotations

import copy

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Categorical
from torchrl.modules import QValueActor
from torchrl.objectives import DQNLoss

from taskvar_torch import keys
from taskvar_torch.config import TrainConfig, apply_overrides, load_config
from taskvar_torch.factory import build_heads, make_env, make_learner, make_subtasks
from taskvar_torch.heads.averaging import averaging_loss, make_averaging_head
from taskvar_torch.heads.behaviour import BEHAVIOUR, BehaviourPolicy
from taskvar_torch.heads.bundle import Heads
from taskvar_torch.heads.first_visit import FirstVisitFilter
from taskvar_torch.heads.learner import (
    CompiledLosses,
    ForeachSoftUpdate,
    MultiHeadLearner,
    MultiHeadLoss,
)
from taskvar_torch.heads.max_value import OptimismGapHead
from taskvar_torch.heads.networks import StackedMLP, head_network
from taskvar_torch.heads.relabel import Transitions, relabel
from taskvar_torch.heads.robustness import component_matrix, parent_closure, robustness_loss
from taskvar_torch.heads.targets import expectile_loss, masked_mean
from taskvar_torch.subtasks import Hierarchy

torch.set_num_threads(1)
CONFIG = "configs/windy.yaml"


@pytest.fixture(scope="module")
def windy():
    cfg = load_config(CONFIG, ["env.num_envs=4"])  # the paper's heads
    env = make_env(cfg)
    subtasks = make_subtasks(cfg, env)
    return cfg, env, subtasks


def random_batch(env, B: int = 64, seed: int = 0) -> TensorDict:
    """B raw windy transitions from uniformly random actions (like the replay buffer's rows)."""
    g = torch.Generator().manual_seed(seed)
    td = env.rollout(B // env.num_envs + 30, break_when_any_done=False)  # (N, T)
    td = td.reshape(-1)
    idx = torch.randperm(td.shape[0], generator=g)[:B]
    return td[idx].exclude(keys.INSTANCE, (keys.NEXT, keys.INSTANCE))


def test_averaging_loss_equals_torchrl_double_dqn_loss(windy):
    cfg, env, subtasks = windy
    head = make_averaging_head(env.observation_spec[keys.OBSERVATION].shape[-1], 4)
    actor = QValueActor(head.module, in_keys=[keys.OBSERVATION], spec=env.action_spec[0])
    ref = DQNLoss(actor, action_space="categorical", delay_value=True, double_dqn=True)
    ref.make_value_estimator(gamma=0.99)
    with torch.no_grad():  # make the target differ from the online network
        for p in ref.target_value_network_params.values(True, True):
            p.add_(0.1 * torch.randn_like(p))
    batch = random_batch(env)
    expected = ref(batch.clone())["loss"]

    tr = relabel(batch, subtasks)
    q = head.module(tr.observation)
    q_next = head.module(tr.next_observation).detach()
    target_net = copy.deepcopy(head.module)
    with torch.no_grad():
        src = ref.target_value_network_params
        for (_, p), (_, t) in zip(
            sorted(src.items(True, True)), sorted(dict(target_net.named_parameters()).items())
        ):
            t.copy_(p)
    got = averaging_loss(q, q_next, target_net(tr.next_observation), tr, 0.99, double_q=True)
    torch.testing.assert_close(got, expected)


def test_stacked_mlp_members_are_independent_networks():
    torch.manual_seed(0)
    stack = StackedMLP(7, (3, 5, 2), hidden=(16, 8))
    x = torch.randn(11, 7)
    out = stack(x)  # (K, 11, 5)
    for k, size in enumerate((3, 5, 2)):
        torch.testing.assert_close(out[k, :, :size], stack.forward_one(x, k))
    # a member's gradient never touches another member's slice
    stack.forward_one(x, 1).sum().backward()
    for w in stack.weights:
        assert (
            w.grad[0].abs().sum() == 0 and w.grad[2].abs().sum() == 0 and w.grad[1].abs().sum() > 0
        )


def test_forward_snapshots_equals_forward_per_snapshot():
    """``G`` stacked snapshots on ``G`` row groups give each group what its copy's ``forward``
    gives; no ``params``: the live weights, ``G = 1``; snapshots are detached copies."""
    torch.manual_seed(0)
    stack = StackedMLP(7, (3, 5, 2), hidden=(16, 8), input_mask=(torch.rand(3, 7) > 0.3).float())
    x = torch.randn(2 * 11, 7)
    with torch.no_grad():
        assert torch.equal(stack.forward_snapshots(x)[0], stack(x))  # the same baddbmm calls
        first = stack.snapshot()
        before = copy.deepcopy(stack)
        for p in stack.parameters():
            p.add_(0.5)
        second = stack.snapshot()
        one = stack.forward_snapshots(x[11:], [p.unsqueeze(0) for p in second])
        assert torch.equal(one[0], stack(x[11:]))
        out = stack.forward_snapshots(x, [torch.stack(p) for p in zip(first, second)])
        assert out.shape == (2, 3, 11, 5)
        # G > 1: a larger batched matmul, whose last bits the BLAS may give differently (here the
        # second group's); the Wargus shapes are checked bit for bit in test_wargus_fast_loop.py
        torch.testing.assert_close(out[0], before(x[:11]))
        torch.testing.assert_close(out[1], stack(x[11:]))
    assert not any(p.requires_grad for p in first)
    assert [tuple(p.shape) for p in first] == [
        *(tuple(w.shape) for w in stack.weights),
        *(tuple(b.shape) for b in stack.biases),
    ]


def test_fused_pass_equals_each_head_run_alone(windy):
    cfg, env, subtasks = windy
    torch.manual_seed(0)
    heads = build_heads(cfg, env, subtasks)
    loss = MultiHeadLoss(heads, subtasks, TrainConfig())
    assert loss.stack is not None  # every head is a member of one StackedMLP
    batch = random_batch(env)
    cur, nxt, nxt_target, *_ = loss._head_outputs(
        batch[keys.OBSERVATION], batch[keys.NEXT, keys.OBSERVATION]
    )
    out = heads(batch.select(keys.OBSERVATION).clone())
    out_next = heads(TensorDict({keys.OBSERVATION: batch[keys.NEXT, keys.OBSERVATION]}, [64]))
    for name, key in (
        ("averaging", keys.ACTION_VALUE),
        ("options", keys.OPTION_ACTION_VALUE),
        ("switching", keys.OPTION_VALUE),
        ("max_value", keys.MAX_VALUE),
    ):
        torch.testing.assert_close(cur[name], out[key])
        torch.testing.assert_close(nxt[name], out_next[key])
        torch.testing.assert_close(nxt_target[name], out_next[key])  # targets start as copies
    assert out[keys.OPTION_ACTION_VALUE].shape == (64, 2, 4)


def test_max_value_head_is_never_below_switching_head(windy):
    cfg, env, subtasks = windy
    heads = build_heads(cfg, env, subtasks)
    assert isinstance(head_network(heads.heads["max_value"]), OptimismGapHead)
    with torch.no_grad():
        for p in heads.parameters():
            p.normal_(0, 3.0)
    td = heads(TensorDict({keys.OBSERVATION: torch.rand(256, 25)}, [256]))
    assert (td[keys.MAX_VALUE] >= td[keys.OPTION_VALUE]).all()


def test_every_loss_trains_only_its_own_head(windy):
    cfg, env, subtasks = windy
    torch.manual_seed(0)
    heads = build_heads(cfg, env, subtasks)
    loss = MultiHeadLoss(heads, subtasks, TrainConfig())
    losses = loss(random_batch(env))
    order = {n: head_network(heads.heads[n]).index for n in ("averaging", "options", "switching")}
    order["max_value"] = head_network(heads.heads["max_value"]).gap.index
    for name, k in order.items():
        heads.zero_grad()
        losses[f"loss_{name}"].backward(retain_graph=True)
        g = head_network(heads.heads["averaging"]).stack.weights[0].grad  # (K, D, H)
        touched = [j for j in range(g.shape[0]) if g[j].abs().sum() > 0]
        assert touched == [k], (name, touched)


def test_relabel_gives_each_option_its_subtask_reward(windy):
    cfg, env, subtasks = windy
    batch = random_batch(env, B=256)
    tr = relabel(batch, subtasks)
    assert tr.subtask_reward.shape == (256, 2) and tr.initiation.dtype == torch.bool
    arrived = tr.terminated.bool()
    exit_used = env.model.exit_id[batch[keys.CELL]]
    for o in range(2):
        wrong = arrived & (exit_used != o)
        expected = torch.where(wrong, -101.0, -1.0)
        torch.testing.assert_close(tr.subtask_reward[:, o], expected)


def test_masked_mean_averages_each_column_over_its_own_rows():
    loss = torch.tensor([[1.0, 10.0], [3.0, 20.0], [5.0, 30.0]])
    mask = torch.tensor([[True, False], [True, False], [False, False]])
    assert masked_mean(loss, mask) == pytest.approx(2.0)


def test_expectile_loss_minimiser_is_the_expectile():
    samples = torch.tensor([-5.0, -4.0, -4.0, -3.0, -1.0])
    for level, expected in ((0.5, samples.mean().item()), (0.999, -1.0)):
        x = torch.zeros((), requires_grad=True)
        opt = torch.optim.LBFGS([x], lr=1.0, max_iter=200)

        def closure(x=x, level=level, opt=opt):
            opt.zero_grad()
            loss = expectile_loss(x.expand(5), samples, level).mean()
            loss.backward()
            return loss

        opt.step(closure)
        assert x.item() == pytest.approx(expected, abs=0.02)


def test_max_value_expectile_sets_the_level_of_the_max_value_loss(windy):
    """``train.max_value_expectile`` reaches the learner (``factory.make_learner``) and weighs the
    max-value head's TD errors: the same heads on the same sample give a loss linear in the level
    (the expectile weights above), different at 0.25 and 0.75."""
    cfg, env, subtasks = windy
    batch = random_batch(env)
    losses = {}
    for level in (0.25, 0.5, 0.75):
        over = ["train.max_value_estimator=expectile", f"train.max_value_expectile={level}"]
        cfg_level = apply_overrides(cfg, over)
        torch.manual_seed(0)
        learner = make_learner(cfg_level, build_heads(cfg_level, env, subtasks), subtasks)
        assert learner.loss.settings.max_value_expectile == level
        losses[level] = learner.loss(batch.clone())["loss_max_value"].item()
    assert losses[0.25] != pytest.approx(losses[0.75], rel=1e-3)
    assert losses[0.5] == pytest.approx((losses[0.25] + losses[0.75]) / 2, rel=1e-5)


def test_parent_closure_sends_component_updates_to_the_composed_parent():
    h = Hierarchy(root="TG+FE", children={"TG+FE": ("TG", "FE")})
    m = component_matrix(("TG", "FE", "TG+FE"), h)
    mask = torch.tensor([[True, False, False], [False, True, False], [False, False, False]])
    got = parent_closure(mask, m)
    assert got.tolist() == [[True, False, True], [False, True, True], [False, False, False]]


def _robustness_batch(B: int, num_options: int):
    """A hand-built relabelled batch: zero robustness rewards, nothing terminated."""

    z = torch.zeros(B, 1)
    return Transitions(
        observation=z,
        next_observation=z,
        action=torch.zeros(B, dtype=torch.int64),
        reward=torch.zeros(B),
        terminated=torch.zeros(B),
        initiation=torch.ones(B, num_options, dtype=torch.bool),
        initiation_next=torch.ones(B, num_options, dtype=torch.bool),
        beta_next=torch.zeros(B, num_options),
        subtask_reward=torch.zeros(B, num_options),
        robustness_reward=torch.zeros(B, num_options),
    )


def test_robustness_target_follows_the_options_own_action_not_the_max():
    # R(o, s, a) is the attainability of o's goal *when following o* (paper §3.4.3): at s' the
    # option's own action (2) keeps the goal (R 1.0), the robustness-greedy action (0) would be
    # worth 9.0 but the option never takes it. The "option" target must read 1.0, "greedy" 9.0.
    batch = _robustness_batch(1, 1)
    r = torch.zeros(1, 1, 3)  # online R(o, s, .): the loss is the squared target
    r_next_target = torch.tensor([[[9.0, 5.0, 1.0]]])
    pi_next = torch.tensor([[2]])  # pi^o(s')
    mask = torch.ones(1, 1, dtype=torch.bool)
    on_policy = robustness_loss(r, r_next_target, r_next_target, mask, batch, 0.5, True, pi_next)
    greedy = robustness_loss(r, r_next_target, r_next_target, mask, batch, 0.5, True)
    torch.testing.assert_close(on_policy, torch.tensor((0.5 * 1.0) ** 2))
    torch.testing.assert_close(greedy, torch.tensor((0.5 * 9.0) ** 2))


def test_fused_robustness_loss_bootstraps_with_each_options_greedy_action():
    cfg = load_config("configs/wargus.yaml", ["env.wargus.size=16", "env.num_envs=4"])
    env = make_env(cfg)
    subtasks = make_subtasks(cfg, env)
    torch.manual_seed(0)
    heads = build_heads(cfg, env, subtasks)
    batch = env.rollout(20, break_when_any_done=False).reshape(-1)
    batch = batch.exclude(keys.INSTANCE, (keys.NEXT, keys.INSTANCE))
    losses = {}
    cases = (
        ("option", "option", "termination"),
        ("greedy", "option", "termination"),
        ("option", "averaging", "termination"),
        ("option", "averaging", "episode"),
    )
    for target, root, until in cases:
        settings = TrainConfig(
            robustness_target=target, hierarchy_root_policy=root, robustness_until=until
        )
        loss = MultiHeadLoss(heads, subtasks, settings)
        with torch.no_grad():  # make the target network differ from the online one
            for p in loss.target_heads_params.values(True, True):
                p.add_(0.1 * torch.randn_like(p))
        got = loss(batch.clone())["loss_robustness"]
        tr = relabel(batch, subtasks, robustness=True)
        cur, nxt, nxt_t, *_ = loss._head_outputs(tr.observation, tr.next_observation)
        mask = parent_closure(tr.initiation, loss.components)
        pi_next = nxt["options"].argmax(-1) if target == "option" else None
        if root == "averaging":  # the root (TG+FE, index 2) follows pi^avg (paper §3.4.2)
            pi_next[:, 2] = nxt["averaging"].argmax(-1)
        want = robustness_loss(
            cur["robustness"],
            nxt["robustness"],
            nxt_t["robustness"],
            mask,
            tr,
            settings.robustness_gamma,  # train.robustness_gamma's default, 0.99
            True,
            pi_next,
            until_termination=until == "termination",
        )
        torch.testing.assert_close(got, want)
        losses[target, root, until] = got
    # the targets differ here, so the checks above tell them apart
    assert len({round(v.item(), 6) for v in losses.values()}) == 4
    with pytest.raises(ValueError, match="robustness_target must be one of"):
        MultiHeadLoss(heads, subtasks, TrainConfig(robustness_target="max"))


def _looped_first_visit(obs, action, is_init):
    keep = torch.zeros_like(action, dtype=torch.bool)
    for n in range(action.shape[0]):
        seen: set = set()
        for t in range(action.shape[1]):
            if is_init[n, t]:
                seen = set()
            key = (tuple(obs[n, t].tolist()), int(action[n, t]))
            keep[n, t] = key not in seen
            seen.add(key)
    return keep


def test_first_visit_filter_matches_a_per_environment_loop():
    g = torch.Generator().manual_seed(0)
    N, T, D = 5, 40, 3
    obs = torch.randint(0, 3, (N, T, D), generator=g).float()  # many repeats
    action = torch.randint(0, 2, (N, T), generator=g)
    is_init = torch.rand(N, T, generator=g) < 0.1
    is_init[:, 0] = True
    batch = TensorDict(
        {keys.OBSERVATION: obs, keys.ACTION: action, "is_init": is_init.unsqueeze(-1)}, [N, T]
    )
    f = FirstVisitFilter(N, D, buckets=1 << 16)
    first, second = f(batch[:, :17]), f(batch[:, 17:])  # the flags carry across batches
    expected = _looped_first_visit(obs, action, is_init)
    assert torch.equal(torch.cat([first, second], 1), expected)
    assert 0 < expected.float().mean() < 1


def test_behaviour_picks_a_mode_per_episode_and_keeps_it(windy):
    cfg, env, subtasks = windy
    heads = build_heads(cfg, env, subtasks)
    torch.manual_seed(0)
    td = TensorDict(
        {
            keys.OBSERVATION: torch.eye(25)[:8],
            keys.CELL: torch.arange(8),
            "is_init": torch.ones(8, 1, dtype=torch.bool),
        },
        [8],
    )
    for prob, check in ((0.0, lambda m: (m == -1).all()), (1.0, lambda m: (m >= 0).all())):
        pol = BehaviourPolicy(heads, subtasks, _spec(8), prob, eps=0.0)
        out = pol(td.clone())
        assert check(out[BEHAVIOUR])
    pol = BehaviourPolicy(heads, subtasks, _spec(8), 0.5, eps=0.0)
    out = pol(td.clone())
    modes = out[BEHAVIOUR].clone()
    out.set("is_init", torch.zeros(8, 1, dtype=torch.bool))
    again = pol(out)  # not a new episode: the mode is kept (windy options never terminate early)
    assert torch.equal(again[BEHAVIOUR], modes)
    q = head_network(heads.heads["options"])(td[keys.OBSERVATION]).argmax(-1)  # (8, O)
    q_avg = head_network(heads.heads["averaging"])(td[keys.OBSERVATION]).argmax(-1)
    expected = torch.where(modes >= 0, q.gather(-1, modes.clamp(min=0)[:, None])[:, 0], q_avg)
    assert torch.equal(again[keys.ACTION], expected)  # eps = 0: the chosen head's greedy action


def _spec(n: int):

    return Categorical(4, shape=(n,), dtype=torch.int64)


@pytest.mark.slow
def test_compiled_learner_matches_eager(windy):
    """train.compile: the compiled losses (forward and backward) give the eager losses and
    weights within float rounding, update after update (averaging and options heads: a small
    graph, so a cold compile stays short)."""
    cfg, env, subtasks = windy
    batch = random_batch(env)
    learners = []
    for compile_ in (False, True):
        torch.manual_seed(0)
        full = build_heads(cfg, env, subtasks)
        names = ("averaging", "options")
        heads = Heads(full.option_names, **{n: full.heads[n] for n in names})
        loss = MultiHeadLoss(heads, subtasks, TrainConfig())
        learners.append(MultiHeadLearner(loss, compile=compile_))
    eager, compiled = learners
    assert isinstance(compiled.losses, CompiledLosses)
    for _ in range(3):
        a, b = eager.update(batch), compiled.update(batch)
        for k in a.keys():
            torch.testing.assert_close(b[k], a[k], rtol=1e-5, atol=1e-6)
    assert compiled.losses.failed is None
    for p, q in zip(eager.heads.parameters(), compiled.heads.parameters()):
        torch.testing.assert_close(q, p, rtol=1e-5, atol=1e-6)


def test_bfloat16_matmuls_match_float32_losses(windy):
    """train.matmul_dtype=bfloat16: the network passes run their matmuls in bfloat16 (autocast),
    every loss stays float32 and within bfloat16 rounding of the float32 losses; the weights stay
    float32 and move; an unknown dtype is refused in one line naming the allowed values."""
    cfg, env, subtasks = windy
    batch = random_batch(env)
    learners = {}
    for dtype in ("float32", "bfloat16"):
        torch.manual_seed(0)
        heads = build_heads(cfg, env, subtasks)
        loss = MultiHeadLoss(heads, subtasks, TrainConfig(matmul_dtype=dtype))
        learners[dtype] = MultiHeadLearner(loss)
    before = [p.detach().clone() for p in learners["bfloat16"].heads.parameters()]
    a, b = learners["float32"].update(batch), learners["bfloat16"].update(batch)
    assert set(a.keys()) == set(b.keys())
    for k in a.keys():
        assert b[k].dtype == torch.float32
        torch.testing.assert_close(b[k], a[k], rtol=2e-2, atol=2e-3)
        assert not torch.equal(b[k], a[k])  # the matmuls really ran in bfloat16
    after = list(learners["bfloat16"].heads.parameters())
    assert all(p.dtype == torch.float32 for p in after)
    assert any(not torch.equal(p, q) for p, q in zip(before, after))
    with pytest.raises(ValueError, match=r"matmul_dtype must be one of \['bfloat16', 'float32'\]"):
        MultiHeadLoss(learners["float32"].heads, subtasks, TrainConfig(matmul_dtype="half"))
    with pytest.raises(ValueError, match="train.matmul_dtype must be one of"):
        load_config(CONFIG, ["train.matmul_dtype=float16"])


def test_eval_ema_tau_averages_the_weights_after_every_update(windy):
    """``eval_ema_tau``: the learner's eval_heads start at the initial weights and follow ``ema <-
    ema + tau (online - ema)`` after every update, without gradients."""
    cfg, env, subtasks = windy
    tau = 0.25
    learner = MultiHeadLearner(
        MultiHeadLoss(build_heads(cfg, env, subtasks), subtasks, TrainConfig()), eval_ema_tau=tau
    )
    ema = [p.detach().clone() for p in learner.heads.parameters()]  # the initial weights
    assert all(torch.equal(e, p) for e, p in zip(ema, learner.eval_heads.parameters()))
    batch = random_batch(env)
    for _ in range(3):
        learner.update(batch)
        ema = [e + tau * (p.detach() - e) for e, p in zip(ema, learner.heads.parameters())]
    for e, p in zip(ema, learner.eval_heads.parameters()):
        torch.testing.assert_close(p, e, rtol=1e-6, atol=1e-7)
        assert not p.requires_grad


@pytest.mark.slow
def test_compiled_learner_falls_back_to_eager(windy, monkeypatch):
    cfg, env, subtasks = windy
    heads = build_heads(cfg, env, subtasks)
    learner = MultiHeadLearner(MultiHeadLoss(heads, subtasks, TrainConfig()), compile=True)

    def broken(batch):
        raise RuntimeError("no C++ compiler\nmore lines")

    learner.losses.compiled = broken
    with pytest.warns(UserWarning, match="running eager: RuntimeError: no C\\+\\+ compiler$"):
        losses = learner.update(random_batch(env))
    assert set(losses.keys()) == {
        "loss_averaging",
        "loss_options",
        "loss_switching",
        "loss_max_value",
    }
    assert isinstance(learner.losses.failed, RuntimeError)
    learner.update(random_batch(env))  # eager from now on, no second warning


def test_soft_update_moves_every_target_once_by_tau(windy):
    cfg, env, subtasks = windy
    heads = build_heads(cfg, env, subtasks)
    learner = MultiHeadLearner(MultiHeadLoss(heads, subtasks, TrainConfig()), target_tau=0.25)
    assert isinstance(learner.target_updater, ForeachSoftUpdate)
    stack = learner.loss.stack
    target = learner.loss.target_stack
    before = [t.detach().clone() for t in target.parameters()]
    with torch.no_grad():
        for p in stack.parameters():
            p.add_(1.0)
    learner.target_updater.step()
    for b, t in zip(before, target.parameters()):
        torch.testing.assert_close(t, b + 0.25)  # each shared tensor lerped exactly once


def test_learner_update_changes_weights_and_pops_mean_losses(windy):
    cfg, env, subtasks = windy
    torch.manual_seed(0)
    heads = build_heads(cfg, env, subtasks)
    learner = MultiHeadLearner(MultiHeadLoss(heads, subtasks, TrainConfig()))
    batch = random_batch(env)
    w0 = [p.detach().clone() for p in heads.parameters()]
    l1 = learner.update(batch)
    l2 = learner.update(batch)
    assert any(not torch.equal(a, b) for a, b in zip(w0, heads.parameters()))
    row = learner.pop_losses()
    assert set(row) == {"loss_averaging", "loss_options", "loss_switching", "loss_max_value"}
    assert row["loss_options"] == pytest.approx(
        (l1["loss_options"] + l2["loss_options"]).item() / 2
    )
    assert learner.pop_losses() == {}


def test_first_visit_steps_equal_one_visit_per_step():
    """FirstVisitFilter.visit_steps (T steps at once) equals T calls of visit: masks and flags."""
    g = torch.Generator().manual_seed(0)
    for T in (1, 2, 17, 40):
        N, D = 7, 3
        obs = torch.randint(0, 3, (T, N, D), generator=g).float()  # few values: many revisits
        action = torch.randint(0, 2, (T, N), generator=g)
        a, b = FirstVisitFilter(N, D, buckets=64), FirstVisitFilter(N, D, buckets=64)
        before = torch.randint(0, 3, (N, D), generator=g).float(), torch.zeros(N, dtype=torch.long)
        a.visit(*before), b.visit(*before)  # flags from earlier steps count too
        ref = torch.stack([a.visit(obs[t], action[t]) for t in range(T)])
        assert torch.equal(b.visit_steps(obs, action), ref)
        assert torch.equal(a.seen, b.seen)


def test_first_visit_batch_equals_a_clear_and_visit_per_step():
    """FirstVisitFilter's batch pass (episodes starting inside the batch) equals, step by step,
    clearing the flags of new episodes and one visit: masks and flags, with hash collisions."""
    g = torch.Generator().manual_seed(1)
    N, D = 9, 3
    a, b = FirstVisitFilter(N, D, buckets=32), FirstVisitFilter(N, D, buckets=32)
    kept = []
    for T in (1, 5, 23, 40):  # consecutive batches: flags carry over
        obs = torch.randint(0, 3, (N, T, D), generator=g).float()
        action = torch.randint(0, 2, (N, T), generator=g)
        is_init = torch.rand(N, T, generator=g) < 0.15
        ref = torch.empty(N, T, dtype=torch.bool)
        for t in range(T):
            a.seen[is_init[:, t]] = False
            ref[:, t] = a.visit(obs[:, t], action[:, t])
        batch = TensorDict(
            {keys.OBSERVATION: obs, keys.ACTION: action, "is_init": is_init.unsqueeze(-1)}, [N, T]
        )
        assert torch.equal(b(batch), ref)
        assert torch.equal(a.seen, b.seen)
        kept.append(ref.flatten())
    assert 0 < torch.cat(kept).float().mean() < 1  # revisits dropped, first visits kept
