"""Seeds as a batch dimension (``taskvar train --seeds N``, heads/seeds.py): each seed's rows meet
its own weights only, its losses and gradients are its one-seed run's, its env draws its own keys,
its bundle evaluates, and bad input is refused in one line."""

from __future__ import annotations

import pytest
import torch

from taskvar_torch.checkpoint import CheckpointError, load_checkpoint
from taskvar_torch.config import load_config
from taskvar_torch.factory import build_heads, load_heads, make_learner, make_subtasks
from taskvar_torch.heads.seeds import split_seed, stack_seeds
from taskvar_torch.training import train
from taskvar_torch.training.collection import make_training_env
from taskvar_torch.training.replay import raw_transitions
from taskvar_torch.training.run_state import seed_config

TINY = [
    "env.num_envs=4",
    "train.frames_per_batch=64",
    "train.batch_size=32",
    "train.init_random_frames=128",
    "train.total_frames=640",
    "train.log_every=320",
    "train.eps_decay_frames=256",
]


def _cfg(*extra: str, path: str = "configs/windy.yaml"):
    return load_config(path, [*TINY, *extra])


def _one(cfg, seed: int):
    """Seed ``seed``'s heads as its one-seed run initialises them (run_setup.build_run)."""
    c = seed_config(cfg, seed - cfg.seed)
    torch.manual_seed(c.seed)
    env = make_training_env(c)
    return build_heads(c, env, make_subtasks(c, env.base_env)), env


def _rollout(cfg, seeds):
    env = make_training_env(cfg, num_envs=cfg.env.num_envs * len(seeds))
    env.base_env.set_seed_blocks(seeds)
    torch.manual_seed(0)
    return env, env.rollout(12, break_when_any_done=False)


@pytest.mark.parametrize("path", ["configs/windy.yaml", "configs/taxi.yaml"])
def test_each_seed_rows_meet_its_own_weights_and_its_losses_are_its_runs(path):
    cfg = _cfg(path=path)
    runs = [_one(cfg, s)[0] for s in (0, 1, 2)]
    batch = stack_seeds(runs)
    _, td = _rollout(cfg, [0, 1, 2])  # (3 N, T)
    raw = raw_transitions(td, keep_instance=True)  # seed-major rows
    n = raw.shape[0] // 3
    obs = raw["observation"]
    for name in batch.paper_heads():
        y = batch.heads[name].module(obs)
        parts = [runs[k].heads[name].module(obs[k * n : (k + 1) * n]) for k in range(3)]
        assert torch.equal(y, torch.cat(parts)), name  # the same matmul per row: the same bits
    subtasks = make_subtasks(cfg, make_training_env(cfg).base_env)
    lb = make_learner(cfg, batch, subtasks).loss
    ones = [make_learner(cfg, r, subtasks).loss for r in runs]
    got = lb.losses(lb.relabel(raw))
    want = [o.losses(o.relabel(raw[k * n : (k + 1) * n])) for k, o in enumerate(ones)]
    for key in got:
        total = sum(w[key] for w in want)
        torch.testing.assert_close(got[key], total, rtol=1e-5, atol=1e-5)


def test_a_seed_gradient_ignores_the_other_seeds_rows():
    cfg = _cfg()
    runs = [_one(cfg, s)[0] for s in (0, 1)]
    _, td = _rollout(cfg, [0, 1])
    raw = raw_transitions(td, keep_instance=True)
    n = raw.shape[0] // 2
    subtasks = make_subtasks(cfg, make_training_env(cfg).base_env)

    def seed0_grads(rows):
        learner = make_learner(cfg, stack_seeds(runs), subtasks)
        loss = learner.loss
        sum(loss.losses(loss.relabel(rows)).values()).backward()
        return [p.grad.reshape(2, -1)[0].clone() for p in learner.heads.parameters()]

    other = raw.clone()
    other["observation"][n:] = other["observation"][n:].flip(0)  # seed 1 sees other data
    other["action"][n:] = (other["action"][n:] + 1) % 4
    for a, b in zip(seed0_grads(raw), seed0_grads(other)):
        assert torch.equal(a, b)


def test_seed_blocks_draw_what_one_seed_envs_draw():
    cfg = _cfg()
    env, td = _rollout(cfg, [3, 7])
    N = cfg.env.num_envs
    for k, seed in enumerate((3, 7)):
        one = make_training_env(seed_config(cfg, seed - cfg.seed))
        r = one.reset()
        first = td[k * N : (k + 1) * N, 0]
        assert torch.equal(first["cell"], r["cell"])
        assert torch.equal(first["instance", "p"], r["instance", "p"])
    with pytest.raises(ValueError, match="do not split into 3 seeds"):
        env.base_env.set_seed_blocks([0, 1, 2])


def test_split_seed_is_the_run_it_came_from():
    cfg = _cfg()
    runs = [_one(cfg, s)[0] for s in (0, 1, 2)]
    batch = stack_seeds(runs)
    for k, run in enumerate(runs):
        one = split_seed(batch, k, _one(cfg, 9)[0])
        for a, b in zip(one.state_dict().values(), run.state_dict().values()):
            assert torch.equal(a, b)
    with pytest.raises(ValueError, match=r"seed index must be in \[0, 3\)"):
        split_seed(batch, 3, runs[0])


@pytest.mark.slow  # trains (2-10 s on the shared 2-core CPU)
def test_train_seeds_writes_a_bundle_per_seed_that_evaluates(tmp_path):
    cfg = _cfg("train.seeds=2", "train.eval_ema_tau=0.05")
    result = train(cfg, tmp_path / "run", progress=False)
    assert [p.parent.name for p in result["seeds"]] == ["seed0", "seed1"]
    for k, path in enumerate(result["seeds"]):
        heads, c = load_heads(path)
        assert c.seed == k and c.train.seeds == 1
        assert (path.parent / "heads.pt").exists() and (path.parent / "config.yaml").exists()
        with pytest.raises(CheckpointError, match="does not resume alone"):
            train(None, tmp_path / f"again{k}", resume=path, progress=False)
    # the two seeds' weights differ (their own initialisation and data), both finite
    w = [load_checkpoint(p)["models"]["heads"] for p in result["seeds"]]
    key = next(k for k in w[0] if k.endswith("weights.0"))
    assert not torch.equal(w[0][key], w[1][key])
    # the batch's final.pt resumes as a batch, and does not evaluate as one run
    with pytest.raises(CheckpointError, match="holds a batch of 2 training runs"):
        load_heads(result["final"])
    scalars = tmp_path / "run" / "logs" / "scalars"
    assert (scalars / "episode_return_seed0.csv").exists()
    assert (scalars / "episode_return_seed1.csv").exists()
    more = train(
        None,
        tmp_path / "run",
        resume=result["final"],
        overrides=["train.total_frames=768"],
        progress=False,
    )
    assert more["frames"] == 768 and len(more["seeds"]) == 2


@pytest.mark.slow  # trains (2-10 s on the shared 2-core CPU)
def test_one_seed_batch_is_todays_run(tmp_path):
    cfg = _cfg()
    a = train(cfg, tmp_path / "a", progress=False)
    b = train(_cfg("train.seeds=1"), tmp_path / "b", progress=False)
    ha, hb = load_checkpoint(a["final"]), load_checkpoint(b["final"])
    for k, v in ha["models"]["heads"].items():
        assert torch.equal(v, hb["models"]["heads"][k])


@pytest.mark.parametrize(
    "args, message",
    [
        (["--seeds", "0"], "must be a positive integer, got '0'"),
        (["--seeds", "-2"], "must be a positive integer, got '-2'"),
        (["--seeds", "2.5"], "must be a positive integer, got '2.5'"),
    ],
)
def test_bad_seed_counts_are_one_line_errors(tmp_path, args, message, capsys):
    from taskvar_torch.cli import main

    try:
        status = main(["train", "configs/windy.yaml", "--out", str(tmp_path / "x"), *args])
    except SystemExit as e:  # argparse's error
        status = e.code
    assert status != 0
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_seeds_refuse_workers_and_conv_in_one_line():
    with pytest.raises(ValueError, match="runs in one collector process"):
        _cfg("train.seeds=2", "collector.num_workers=2")
    with pytest.raises(ValueError, match="needs heads.network=mlp"):
        load_config("configs/windy_large.yaml", ["train.seeds=2", "heads.network=conv"])


def test_seeds_into_a_folder_holding_a_run_is_refused(tmp_path):
    train(_cfg(), tmp_path / "run", progress=False)
    with pytest.raises(ValueError, match="already"):
        train(_cfg("train.seeds=2"), tmp_path / "run", progress=False)


@pytest.mark.slow  # trains (2-10 s on the shared 2-core CPU)
def test_a_diverging_batch_names_the_seed_and_writes_nothing(tmp_path):
    cfg = _cfg("train.seeds=2", "train.checkpoint_every=320")
    from taskvar_torch.training.learning import TrainingDiverged
    from taskvar_torch.training.run_state import TrainingRun

    original = TrainingRun.learn

    def poisoned(self):
        original(self)
        if self.counters["frames"] >= 512:
            with torch.no_grad():
                w = self.learner.heads.heads["averaging"].module.stack.weights[0]
                w.view(2, -1)[1, 0] = float("nan")  # seed index 1 only

    TrainingRun.learn = poisoned
    try:
        with pytest.raises(TrainingDiverged, match=r"non-finite weights in seed 1\)"):
            train(cfg, tmp_path / "run", progress=False)
    finally:
        TrainingRun.learn = original
    ckpt = tmp_path / "run" / "checkpoint_000000320.pt"
    assert ckpt.exists()
    assert torch.isfinite(
        load_checkpoint(ckpt)["models"]["heads"][
            next(k for k in load_checkpoint(ckpt)["models"]["heads"] if k.endswith("weights.0"))
        ]
    ).all()


@pytest.mark.slow  # trains (2-10 s on the shared 2-core CPU)
def test_seeds_with_nstep_first_visit_and_per_option_replay(tmp_path):
    cfg = _cfg(
        "train.seeds=2",
        "train.n_step=3",
        "train.first_visit=true",
        "train.replay_sampling=per_option",
    )
    result = train(cfg, tmp_path / "run", progress=False)
    assert result["updates"] > 0
    for path in result["seeds"]:
        heads, c = load_heads(path)
        assert c.train.n_step == 3 and c.train.seeds == 1
