"""The MiniGrid port against the ``minigrid`` package (3.2), as Taxi is against Gymnasium: each
episode's layout is copied from a ``minigrid`` env into the port's state, both are stepped with
the same actions (random, and a scripted solver with random slips), and every step's image,
reward, terminated and truncated must be equal; the port's layout sampler draws MiniGrid's layout
distribution; ``process_vis`` is checked against a literal copy of MiniGrid's loops.

The port reports ``truncated & ~terminated`` (the library's convention: an episode that reaches
the goal on its last step is terminated, not truncated); MiniGrid sets both there.
"""

from __future__ import annotations

import math
from collections import Counter, deque

import numpy as np
import pytest
import torch

gym = pytest.importorskip("gymnasium")
pytest.importorskip("minigrid")
import minigrid  # noqa: E402, F401  (registers the MiniGrid ids)
from minigrid.core.world_object import Door, Key  # noqa: E402
from tensordict import TensorDict  # noqa: E402

from taskvar_torch.families.minigrid import dynamics as D  # noqa: E402
from taskvar_torch.families.minigrid.env import MiniGridEnv  # noqa: E402
from taskvar_torch.families.minigrid.layouts import LayoutSampler, build_grids, layouts  # noqa: E402

torch.set_num_threads(1)
IDS = {
    ("doorkey", 5): "MiniGrid-DoorKey-5x5-v0",
    ("doorkey", 6): "MiniGrid-DoorKey-6x6-v0",
    ("doorkey", 8): "MiniGrid-DoorKey-8x8-v0",
    ("lavagap", 5): "MiniGrid-LavaGapS5-v0",
    ("lavagap", 7): "MiniGrid-LavaGapS7-v0",
}


def layout_params(task: str, u) -> tuple[int, ...]:
    """The layout (``layouts.py``) of a reset ``minigrid`` env ``u``."""
    if task == "lavagap":
        return int(u.gap_pos[0]), int(u.gap_pos[1])
    door = key = None
    for i in range(u.width):
        for j in range(u.height):
            obj = u.grid.get(i, j)
            if isinstance(obj, Door):
                door = (i, j)
            if isinstance(obj, Key):
                key = (i, j)
    return door[0], door[1], key[0], key[1]


def copy_state(env: MiniGridEnv, envs: list) -> None:
    """Install every ``minigrid`` env's grid, agent, carried object and step count in ``env``."""
    us = [e.unwrapped for e in envs]
    grid = np.stack([u.grid.encode().reshape(-1, 3) for u in us])
    carrying = np.stack(
        [np.zeros(3, np.uint8) if u.carrying is None else np.array(u.carrying.encode()) for u in us]
    )
    pos = np.array([[int(u.agent_pos[0]), int(u.agent_pos[1])] for u in us])
    env.set_state(
        grid, pos[:, 0], pos[:, 1], [u.agent_dir for u in us], carrying, [u.step_count for u in us]
    )


def scripted(u, rs: np.random.Generator, slip: float) -> int:
    """A solver with slips: with probability ``slip`` a random action, else the first action of a
    shortest turn/forward path to the next subgoal (pick the key up, open the door, the goal)."""
    if rs.random() < slip:
        return int(rs.integers(0, D.NUM_ACTIONS))
    target, act = None, D.FORWARD
    door = key = None
    for i in range(u.width):
        for j in range(u.height):
            obj = u.grid.get(i, j)
            door = (i, j, obj) if isinstance(obj, Door) else door
            key = (i, j) if isinstance(obj, Key) else key
    if door is not None and door[2].is_locked and u.carrying is None and key is not None:
        target, act = key[:2], D.PICKUP
    elif door is not None and not door[2].is_open:
        target, act = door[:2], D.TOGGLE
    goal = (u.width - 2, u.height - 2)
    start = (int(u.agent_pos[0]), int(u.agent_pos[1]), u.agent_dir)
    seen, queue = {start: None}, deque([start])
    while queue:
        x, y, d = queue.popleft()
        fx, fy = x + D.DIR_TO_VEC[d][0], y + D.DIR_TO_VEC[d][1]
        done = (fx, fy) == target if target else (fx, fy) == goal
        if done:
            first, s = (act if target else D.FORWARD), (x, y, d)
            while seen[s] is not None:
                s, first = seen[s]
            return first
        front = u.grid.get(fx, fy)
        passable = front is None or (front.can_overlap() and front.type != "lava")
        for a, nxt in (
            (D.LEFT, (x, y, (d + 3) % 4)),
            (D.RIGHT, (x, y, (d + 1) % 4)),
            (D.FORWARD, (fx, fy, d) if passable else None),
        ):
            if nxt is not None and nxt not in seen:
                seen[nxt] = ((x, y, d), a)
                queue.append(nxt)
    return int(rs.integers(0, D.NUM_ACTIONS))


def play(task: str, size: int, episodes: int, seed: int, max_steps: int | None, slip: float):
    """Play ``episodes`` episodes on both, step for step; returns the steps compared, the
    mismatches and the episodes that reached the goal."""
    kwargs = {} if max_steps is None else {"max_steps": max_steps}
    envs = [gym.make(IDS[(task, size)], **kwargs) for _ in range(episodes)]
    port = MiniGridEnv(episodes, task=task, size=size, max_steps=max_steps, instances="minigrid")
    port.reset()
    table = layouts(task, size)
    index = {tuple(p): i for i, p in enumerate(table.params.tolist())}
    obs = [e.reset(seed=seed + i)[0] for i, e in enumerate(envs)]
    params = [layout_params(task, e.unwrapped) for e in envs]
    built = build_grids(task, size, torch.tensor(params))
    grids = np.stack([e.unwrapped.grid.encode().reshape(-1, 3) for e in envs])
    mismatches = [
        f"layout {params[i]} built otherwise"
        for i in range(episodes)
        if not np.array_equal(built[i].numpy(), grids[i])
    ]
    mismatches += [f"layout {p} not in the table" for p in params if p not in index]
    copy_state(port, envs)
    live = np.ones(episodes, dtype=bool)
    rs = np.random.default_rng(seed)
    image = port.image().numpy()
    steps, goals = 0, 0
    for t in range(10 * size * size + 1):
        for i in np.flatnonzero(live):
            if not np.array_equal(image[i], obs[i]["image"]):
                mismatches.append(f"episode {i} step {t}: image")
                live[i] = False
        if not live.any():
            break
        actions = [
            scripted(e.unwrapped, rs, slip) if slip < 1 else int(rs.integers(0, 7)) for e in envs
        ]
        td = port.step(TensorDict({"action": torch.tensor(actions)}, [episodes]))["next"]
        image = port.image().numpy()
        for i in np.flatnonzero(live):
            o, r, term, trunc, _ = envs[i].step(actions[i])
            obs[i] = o
            steps += 1
            got = (float(td["reward"][i]), bool(td["terminated"][i]), bool(td["truncated"][i]))
            want = (float(np.float32(r)), term, trunc and not term)
            if got != want:
                mismatches.append(f"episode {i} step {t} action {actions[i]}: {got} != {want}")
                live[i] = False
            elif term or trunc:
                live[i] = False
                goals += r > 0
    return steps, mismatches, goals


CASES = [
    # (task, size, max_steps, slip): random play truncated early, and scripted play with slips
    ("doorkey", 5, 40, 1.0),
    ("doorkey", 5, None, 0.2),
    ("doorkey", 6, 30, 1.0),
    ("doorkey", 6, None, 0.3),
    ("doorkey", 8, 30, 1.0),
    pytest.param("doorkey", 8, None, 0.2, marks=pytest.mark.slow),  # ~3.5 s: make test only
    ("lavagap", 5, 30, 1.0),
    ("lavagap", 7, None, 0.2),
]


@pytest.mark.parametrize(("task", "size", "max_steps", "slip"), CASES)
def test_the_port_steps_as_minigrid_does(task, size, max_steps, slip):
    n = 48
    steps, mismatches, goals = play(task, size, n, 1000 * size, max_steps, slip)
    assert not mismatches, (len(mismatches), mismatches[:5])
    assert steps > n * 5
    if slip < 1:  # the scripted episodes pick the key up, open the door and reach the goal
        assert goals >= n // 2, goals


def _process_vis(see: np.ndarray) -> np.ndarray:
    """MiniGrid's ``Grid.process_vis`` loops, literally, on a ``(7, 7)`` see-through mask."""
    mask = np.zeros((7, 7), dtype=bool)
    mask[3, 6] = True
    for j in reversed(range(7)):
        for i in range(6):
            if mask[i, j] and see[i, j]:
                mask[i + 1, j] = True
                if j > 0:
                    mask[i + 1, j - 1] = mask[i, j - 1] = True
        for i in reversed(range(1, 7)):
            if mask[i, j] and see[i, j]:
                mask[i - 1, j] = True
                if j > 0:
                    mask[i - 1, j - 1] = mask[i, j - 1] = True
    return mask


def test_visibility_is_process_vis():
    g = torch.Generator().manual_seed(0)
    see = torch.rand(2000, 7, 7, generator=g) < torch.rand(2000, 1, 1, generator=g)
    want = np.stack([_process_vis(s) for s in see.numpy()])
    assert np.array_equal(D.visibility(see).numpy(), want)


def chi2_bound(df: int, z: float = 3.09) -> float:
    """The chi-square 0.999 quantile for ``df`` degrees of freedom (Wilson-Hilferty)."""
    return df * (1 - 2 / (9 * df) + z * math.sqrt(2 / (9 * df))) ** 3


def chi2(counts: Counter, probs: dict, n: int) -> tuple[float, int]:
    assert set(counts) <= set(probs), set(counts) - set(probs)
    stat = sum((counts.get(k, 0) - n * p) ** 2 / (n * p) for k, p in probs.items())
    return stat, len(probs) - 1


@pytest.mark.parametrize(("task", "size"), [("doorkey", 5), ("doorkey", 8), ("lavagap", 7)])
def test_the_layout_sampler_draws_minigrids_distribution(task, size):
    """MiniGrid's layouts over 3000 seeds and the port's over 3000 keys, each against the exact
    probabilities of ``layouts()``: every drawn layout is in the table, and each chi-square
    statistic (of the joint of layout and start for 5x5 DoorKey, of the layout and the start
    separately otherwise) is below its 0.999 quantile; seeds are fixed, so the test is
    deterministic."""
    n = 3000
    table = layouts(task, size)
    p_layout = {tuple(p): q for p, q in zip(table.params.tolist(), table.prob)}
    env = gym.make(IDS[(task, size)])
    mg = []
    for s in range(n):
        env.reset(seed=s)
        u = env.unwrapped
        mg.append((layout_params(task, u), (int(u.agent_pos[0]), int(u.agent_pos[1]), u.agent_dir)))
    drawn = LayoutSampler(task, size, "minigrid").draw(torch.arange(n) * 7919 + 12345)
    port = [
        (tuple(table.params[i].tolist()), (int(x), int(y), int(d)))
        for i, x, y, d in zip(drawn["layout"], drawn["x"], drawn["y"], drawn["direction"])
    ]
    for name, sample in (("minigrid", mg), ("port", port)):
        stat, df = chi2(Counter(p for p, _ in sample), p_layout, n)
        assert stat < chi2_bound(df), (name, "layout", stat, df)
        if task == "doorkey":  # the start given the layout: uniform over free cells, 4 directions
            start = Counter((p, s) for p, s in sample)
            probs = {}
            for p, q in p_layout.items():
                s_col, _, kx, ky = p
                cells = [
                    (x, y)
                    for x in range(1, s_col)
                    for y in range(1, size - 1)
                    if (x, y) != (kx, ky)
                ]
                for x, y in cells:
                    for d in range(4):
                        probs[(p, (x, y, d))] = q / (4 * len(cells))
            if size == 5:
                stat, df = chi2(start, probs, n)
                assert stat < chi2_bound(df), (name, "joint", stat, df)
            else:
                d_counts = Counter(s[2] for _, s in sample)
                stat, df = chi2(d_counts, {d: 0.25 for d in range(4)}, n)
                assert stat < chi2_bound(df), (name, "direction", stat, df)
                assert set(start) <= set(probs)
        else:
            assert {s for _, s in sample} == {(1, 1, 0)}
