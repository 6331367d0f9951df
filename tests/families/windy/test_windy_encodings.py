"""Large-grid windy observations (fourier_patch, rowcol_patch, exits_patch) and the exit options'
own inputs (heads.option_inputs=subtask with exits_patch)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from taskvar_torch.config import load_config
from taskvar_torch.families.windy.dynamics import WindyModel, make_layout
from taskvar_torch.families.windy.env import observation_table
from taskvar_torch.families.windy.subtasks import WindySubtasks

LAYOUT = make_layout(11, 11, num_exits=3, wind_cells_per_exit=2)


def test_encodings_extend_coords_patch():
    base = observation_table(LAYOUT, "coords_patch", 1)
    for enc, extra in (("fourier_patch", 4 * 5), ("rowcol_patch", 22), ("exits_patch", 6)):
        obs = observation_table(LAYOUT, enc, 1)
        assert obs.shape == (LAYOUT.num_cells, base.shape[1] + extra), enc
        assert np.array_equal(obs[:, : base.shape[1]], base)  # coords_patch comes first
        assert len({row.tobytes() for row in obs}) == LAYOUT.num_cells  # every cell distinct


def test_exits_patch_offsets_are_zero_at_each_exit():
    obs = observation_table(LAYOUT, "exits_patch", 1)
    for k, group in enumerate(LAYOUT.exit_cells):
        assert np.allclose(obs[group[0], -6 + 2 * k : -6 + 2 * k + 2], 0.0)


def test_option_input_mask_shows_each_option_its_own_exit():
    obs_dim = observation_table(LAYOUT, "exits_patch", 1).shape[1]
    sub = WindySubtasks(WindyModel(LAYOUT), obs_encoding="exits_patch")
    mask = sub.option_input_mask(obs_dim)
    assert mask.shape == (3, obs_dim)
    assert torch.equal(mask[:, : obs_dim - 6], torch.ones(3, obs_dim - 6))
    assert torch.equal(mask[:, obs_dim - 6 :], torch.eye(3).repeat_interleave(2, dim=1))
    assert WindySubtasks(WindyModel(LAYOUT)).option_input_mask(obs_dim) is None


def test_subtask_inputs_need_exits_patch():
    with pytest.raises(ValueError, match="needs env.windy.obs_encoding='exits_patch'"):
        load_config(
            "configs/windy_xl.yaml",
            ["heads.option_inputs=subtask", "env.windy.obs_encoding=coords_patch"],
        )
    cfg = load_config(
        "configs/windy_xl.yaml",
        ["heads.option_inputs=subtask", "env.windy.obs_encoding=exits_patch"],
    )
    assert cfg.heads.option_inputs == "subtask"
