"""CUDA path (skipped without a GPU): specs on device, and CPU/CUDA trajectories bit-identical."""

from __future__ import annotations

import pytest
import torch
from torchrl.envs.utils import check_env_specs

from taskvar_torch.families.windy import WindyGridEnv

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


@pytest.mark.parametrize("n", [1, 64])
def test_windy_check_env_specs_on_cuda(n):
    check_env_specs(WindyGridEnv(num_envs=n, seed=0, device="cuda"))


def test_windy_cpu_and_cuda_trajectories_are_identical():
    gen = torch.Generator().manual_seed(0)
    actions = torch.randint(0, 4, (300, 512), generator=gen)
    cells = {}
    for dev in ("cpu", "cuda"):
        env = WindyGridEnv(num_envs=512, seed=3, device=dev, validate_actions=False)
        td, out = env.reset(), []
        for a in actions:
            td["action"] = a.to(dev)
            step, td = env.step_and_maybe_reset(td)
            out.append(step["next", "cell"].cpu())
        cells[dev] = torch.stack(out)
    assert torch.equal(cells["cpu"], cells["cuda"])
