"""Multi-step targets (heads/nstep.py): window quantities on a hand-made batch, and the losses
using them only on the rows the head's own behaviour made."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from taskvar_torch import keys
from taskvar_torch.heads.averaging import averaging_loss
from taskvar_torch.heads.nstep import nstep_returns
from taskvar_torch.heads.relabel import relabel
from taskvar_torch.subtasks.base import Subtasks

G = 0.9


class TableSubtasks(Subtasks):
    """Two options whose reward and termination are read from the batch (test stub)."""

    names = ("a", "b")

    def initiation(self, td):
        return torch.ones(*td.shape, 2, dtype=torch.bool)

    def termination(self, td):
        return td.get("beta")

    def reward(self, td):
        return td.get("r_sub")


def batch(mode, reward, done, beta=None, r_sub=None):
    """A (1, T) batch; observation t is [t], next observation [t + 1]."""
    T = len(mode)
    obs = torch.arange(T, dtype=torch.float32).view(1, T, 1)
    beta = torch.zeros(1, T, 2, dtype=torch.bool) if beta is None else beta.view(1, T, 2)
    r_sub = torch.full((1, T, 2), -1.0) if r_sub is None else r_sub.view(1, T, 2)
    done = torch.tensor(done, dtype=torch.bool).view(1, T, 1)
    return TensorDict(
        {
            keys.OBSERVATION: obs,
            keys.ACTION: torch.zeros(1, T, dtype=torch.int64),
            "behaviour": torch.tensor(mode).view(1, T),
            "r_sub": r_sub,
            keys.NEXT: {
                keys.OBSERVATION: obs + 1,
                keys.REWARD: torch.tensor(reward, dtype=torch.float32).view(1, T, 1),
                keys.DONE: done,
                keys.TERMINATED: done.clone(),
                "beta": beta,
            },
        },
        batch_size=[1, T],
    )


def test_windows_stop_at_done_mode_change_and_batch_end():
    td = nstep_returns(batch([-1, -1, -1, 0, 0, 0], [-1, -2, -3, -4, -5, -6],
                             [0, 0, 1, 0, 0, 0]), TableSubtasks(), G, 4)  # fmt: skip
    w = td.get("nstep")
    assert w["steps"][0].tolist() == [3, 2, 1, 3, 2, 1]
    assert w["reward"][0, 0].item() == pytest.approx(-1 - 2 * G - 3 * G**2)
    assert w["reward"][0, 3].item() == pytest.approx(-4 - 5 * G - 6 * G**2)
    assert w["discount"][0].tolist() == pytest.approx([G**3, G**2, G, G**3, G**2, G])
    assert w["terminated"][0].tolist() == [True, True, True, False, False, False]
    assert w[keys.OBSERVATION][0, :, 0].tolist() == [3, 3, 3, 6, 6, 6]  # s_{t+k}
    # subtask sums over the same windows
    assert w["subtask_reward"][0, 0].tolist() == pytest.approx([-(1 + G + G**2)] * 2)


def test_window_stops_at_mode_change_and_running_option_termination():
    beta = torch.zeros(5, 2, dtype=torch.bool)
    beta[1, 0] = True  # option a terminates after step 1; option b does not care
    td = nstep_returns(batch([0, 0, 0, 1, 1], [-1] * 5, [0] * 5, beta=beta), TableSubtasks(), G, 3)
    w = td.get("nstep")
    assert w["steps"][0].tolist() == [
        2,
        1,
        1,
        2,
        1,
    ]  # t=0 stops at a's beta, t=2 at the mode change
    assert w["beta"][0, 0].tolist() == [True, False]  # beta at s_{t+k} = s_2


def test_n_equal_one_is_the_one_step_target():
    td = nstep_returns(batch([-1, 0, 1], [-1, -2, -3], [0, 0, 1]), TableSubtasks(), G, 1)
    w = td.get("nstep")
    assert w["steps"].tolist() == [[1, 1, 1]]
    assert torch.equal(w["reward"], td["next", keys.REWARD].squeeze(-1))
    assert torch.equal(w[keys.OBSERVATION], td["next", keys.OBSERVATION])


def test_averaging_loss_uses_the_window_on_averaging_rows_only():
    td = nstep_returns(batch([-1, -1, 0], [-1, -1, -1], [0, 0, 0]), TableSubtasks(), G, 2)
    tr = relabel(td.reshape(-1), TableSubtasks())
    q = torch.zeros(3, 4, requires_grad=True)
    near, far = torch.full((3, 4), -10.0), torch.full((3, 4), -20.0)
    loss = averaging_loss(q, near, near, tr, G, True, far, far)
    loss.backward()
    # row 0: 2-step window (-1 - G + G^2 * -20); row 1: the mode changes, 1 step (-1 + G * -20);
    # row 2 (an option's episode): the one-step target (-1 + G * -10)
    y = torch.tensor([-1 - G - 20 * G**2, -1 - 20 * G, -1 - 10 * G])
    expected = (y**2).mean()
    assert loss.item() == pytest.approx(expected.item(), rel=1e-6)
