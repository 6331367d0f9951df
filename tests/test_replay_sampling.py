"""``train.replay_sampling``: uniform, or equal shares per behaviour mode (PerOptionSampler)."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from test_train import CONFIG
from test_train import TINY as TINY_TRAIN  # tests/ is on sys.path (rootdir import mode)
from torchrl.data import LazyTensorStorage, ReplayBuffer

from taskvar_torch.checkpoint import load_checkpoint
from taskvar_torch.config import load_config
from taskvar_torch.training import train
from taskvar_torch.training.replay import PerOptionSampler, load_replay_state, replay_state

torch.set_num_threads(1)
TINY = [*TINY_TRAIN, "train.replay_sampling=per_option"]  # test_train's tiny windy run


def buffer(modes: list[int], capacity: int = 1000, seed: int = 0) -> ReplayBuffer:
    rb = ReplayBuffer(
        storage=LazyTensorStorage(capacity),
        sampler=PerOptionSampler(),
        batch_size=300,
        generator=torch.Generator().manual_seed(seed),
    )
    if modes:
        rows = {"behaviour": torch.tensor(modes), "row": torch.arange(len(modes))}
        rb.extend(TensorDict(rows, [len(modes)]))
    return rb


def test_every_mode_gets_an_equal_share_uniformly_within_it():
    modes = [-1] * 700 + [0] * 200 + [2] * 95 + [3] * 5  # option 1 never ran
    rb = buffer(modes)
    counts = torch.zeros(5, dtype=torch.long)
    seen_rare = set()
    for _ in range(20):
        s = rb.sample()
        c = torch.bincount(s["behaviour"] + 1, minlength=5)
        assert c.tolist() == [75, 75, 0, 75, 75]  # 300 rows over the 4 modes present
        counts += c
        assert bool((torch.tensor(modes)[s["row"]] == s["behaviour"]).all())
        seen_rare |= set(s["row"][s["behaviour"] == 3].tolist())
    assert seen_rare == set(range(995, 1000))  # every row of the rare mode is drawn
    # within the largest mode, draws spread over its rows (not a fixed subset)
    rows = torch.cat([rb.sample()["row"] for _ in range(20)])
    assert len(set(rows[rows < 700].tolist())) > 600


def test_groups_follow_writes_and_overwrites():
    rb = buffer([-1] * 10, capacity=10)
    assert set(rb.sample()["behaviour"].tolist()) == {-1}
    rb.extend(TensorDict({"behaviour": torch.tensor([4, 4]), "row": torch.tensor([10, 11])}, [2]))
    s = rb.sample()  # the two oldest rows overwritten by option 4's
    assert torch.bincount(s["behaviour"] + 1).tolist() == [150, 0, 0, 0, 0, 150]
    assert set(s["row"][s["behaviour"] == 4].tolist()) == {10, 11}


def test_a_refilled_buffer_samples_as_the_saved_one():
    modes = torch.randint(-1, 3, (600,), generator=torch.Generator().manual_seed(1)).tolist()
    a = buffer(modes, capacity=500)  # wrapped: the first 100 rows overwritten
    a.sample()
    b = buffer([], capacity=500)
    load_replay_state(b, replay_state(a))
    b.set_rng(torch.Generator())
    b._rng.set_state(a._rng.get_state())
    for _ in range(3):
        assert torch.equal(a.sample()["row"], b.sample()["row"])


def test_bad_modes_and_bad_config_values_are_refused():
    with pytest.raises(ValueError, match="'behaviour' < -1"):
        buffer([-1, -2]).sample()
    with pytest.raises(
        ValueError,
        match=r"train.replay_sampling must be one of \['per_option', 'uniform'\], got 'stratified'",
    ):
        load_config(CONFIG, ["train.replay_sampling=stratified"])


@pytest.mark.slow
def test_training_with_it_resumes_bit_for_bit(tmp_path):
    cfg = load_config(CONFIG, TINY)
    train(cfg, tmp_path / "straight", progress=False)
    half = tmp_path / "straight" / "checkpoint_000001000.pt"
    train(None, tmp_path / "resumed", resume=half, progress=False)
    a = load_checkpoint(tmp_path / "straight" / "final.pt")
    b = load_checkpoint(tmp_path / "resumed" / "final.pt")
    assert a["counters"]["updates"] > 20
    for name, t in a["models"]["heads"].items():
        assert torch.equal(t, b["models"]["heads"][name]), name
    # and it is not the uniform sampler under another name: the heads differ from uniform's
    uniform = load_config(CONFIG, [*TINY, "train.replay_sampling=uniform"])
    train(uniform, tmp_path / "uniform", progress=False)
    c = load_checkpoint(tmp_path / "uniform" / "final.pt")
    assert any(not torch.equal(t, c["models"]["heads"][n]) for n, t in a["models"]["heads"].items())


@pytest.mark.parametrize("sampling", ["uniform", "per_option"])
def test_sample_many_draws_what_as_many_samples_would(sampling):
    from taskvar_torch.training.replay import make_replay_buffer, sample_many

    cfg = load_config(
        "configs/windy.yaml",
        [f"train.replay_sampling={sampling}", "train.batch_size=8", "train.buffer_size=64"],
    )
    rows = TensorDict(
        {
            "observation": torch.arange(64.0).unsqueeze(-1),
            "behaviour": torch.arange(64) % 3 - 1,
        },
        [64],
    )
    one, many = (make_replay_buffer(cfg, torch.Generator().manual_seed(3)) for _ in range(2))
    one.extend(rows)
    many.extend(rows)
    expected = [one.sample() for _ in range(5)]
    got = sample_many(many, 5)
    assert len(got) == 5 and all((a == b).all() for a, b in zip(expected, got))
    assert torch.equal(one.sample()["observation"], many.sample()["observation"])  # same stream
