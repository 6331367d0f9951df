"""Keyed random numbers: the int32 hot path agrees with the reference, draws are uniform."""

from __future__ import annotations

import numpy as np
import torch

from taskvar_torch import rng


def test_int32_hot_path_equals_int64_reference_and_numpy():
    key = rng.sub_env_key(3, torch.arange(50000))
    t = torch.randint(0, 5000, (50000,))
    ref = rng.draw_bits(key, t)
    fast = rng.draw_bits_i32(rng.to_i32(key), t.to(torch.int32)).to(torch.int64) & rng.MASK32
    assert torch.equal(ref, fast)
    assert np.array_equal(rng.draw_bits(key.numpy(), t.numpy()), ref.numpy())
    assert rng.draw_bits(int(key[7]), int(t[7])) == int(ref[7])


def test_bernoulli_threshold_is_exactly_u_less_than_p():
    key = rng.sub_env_key(1, torch.arange(100000))
    p = torch.rand(100000)
    p[:3] = torch.tensor([0.0, 1.0, 0.5])
    u = rng.draw_uniform(key, 4)
    fast = rng.bernoulli_i32(rng.to_i32(key), 4, rng.probability_threshold(p))
    assert torch.equal(u < p, fast)
    assert not fast[0] and fast[1]


def test_draws_are_uniform_and_keys_independent():
    key = rng.episode_key(rng.sub_env_key(0, torch.arange(200000)), 0)
    u = rng.draw_uniform(key, 0)
    hist = torch.histc(u, bins=10, min=0, max=1) / u.numel()
    assert (hist - 0.1).abs().max() < 0.005
    v = rng.draw_uniform(key, 1)
    assert abs(torch.corrcoef(torch.stack([u, v]))[0, 1].item()) < 0.01
    idx = rng.draw_index(key, 2, 7)
    assert idx.min() == 0 and idx.max() == 6
