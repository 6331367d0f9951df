"""The Gymnasium adapter's default observation encoder equals ``gymnasium.spaces.flatten`` row by
row (taskvar_torch/families/gymnasium/encoder.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from gymnasium import spaces
from gymnasium.spaces.utils import flatten
from gymnasium.vector.utils import batch_space, iterate

from taskvar_torch.families.gymnasium import SpaceEncoder

SPACES = {
    "discrete": spaces.Discrete(5, start=-2),
    "box": spaces.Box(-1.0, 2.0, (3,), np.float32),
    "image": spaces.Box(0, 255, (7, 7, 3), np.uint8),
    "multidiscrete": spaces.MultiDiscrete([2, 3, 4], start=[0, 1, -1]),
    "multibinary": spaces.MultiBinary(4),
    "dict": spaces.Dict(
        {
            "image": spaces.Box(0, 255, (2, 2, 3), np.uint8),
            "direction": spaces.Discrete(4),
            "inner": spaces.Dict({"z": spaces.MultiBinary(2), "a": spaces.Discrete(2)}),
        }
    ),
    "tuple": spaces.Tuple((spaces.Discrete(3), spaces.Box(0.0, 1.0, (2,), np.float64))),
}


@pytest.mark.parametrize("name", list(SPACES))
def test_the_encoding_is_gymnasiums_flatten_of_every_row(name):
    space = SPACES[name]
    space.seed(0)
    batched = batch_space(space, 6)
    batched.seed(1)
    obs = batched.sample()
    enc = SpaceEncoder(space)
    got = enc(obs)
    want = torch.tensor(
        np.stack([flatten(space, row) for row in iterate(batched, obs)]), dtype=torch.float32
    )
    assert got.dtype == torch.float32 and got.shape == (6, enc.size)
    assert torch.equal(got, want)
    assert bool(((got >= enc.low) & (got <= enc.high)).all())


def test_keys_keep_part_of_a_dict_and_a_space_without_a_flat_encoding_is_refused():
    space = spaces.Dict(
        {"image": spaces.Box(0, 255, (2, 2, 3), np.uint8), "mission": spaces.Text(8)}
    )
    with pytest.raises(ValueError, match=r"observation\['mission'\] is Text.*keys=") as e:
        SpaceEncoder(space)
    assert "\n" not in str(e.value)
    enc = SpaceEncoder(space, keys=("image",))
    assert enc.size == 12
    with pytest.raises(ValueError, match=r"keys must be among \['image', 'mission'\]"):
        SpaceEncoder(space, keys=("view",))
