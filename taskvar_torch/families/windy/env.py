"""TorchRL ``EnvBase`` over the batched windy dynamics (paper §3.3.1)."""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded

from taskvar_torch import keys, rng
from taskvar_torch.envs import gym_checks
from taskvar_torch.envs.batched import BatchedFamilyEnv
from taskvar_torch.families.windy import dynamics as windy
from taskvar_torch.families.windy import render
from taskvar_torch.families.windy.instances import WindyInstances, windy_instances

OBS_ENCODINGS = ("onehot", "coords_patch", "fourier_patch", "rowcol_patch", "exits_patch")
_C_START = rng.RESET_COUNTER + 4
_FLAGS = (keys.DONE, keys.TERMINATED, keys.TRUNCATED)


def observation_size(
    layout: windy.WindyLayout, encoding: str = "onehot", patch_radius: int = 2
) -> int:
    """``D``, the length of :func:`observation_table`'s rows, without building the table."""
    coords_patch = 2 + 3 * (2 * patch_radius + 1) ** 2
    side = max(layout.height, layout.width)
    return {
        "onehot": layout.num_cells,
        "coords_patch": coords_patch,
        "exits_patch": coords_patch + 2 * len(layout.exit_cells),
        "rowcol_patch": coords_patch + layout.height + layout.width,
        "fourier_patch": coords_patch + 4 * (int(np.ceil(np.log2(max(side, 2)))) + 1),
    }[encoding]


def observation_table(
    layout: windy.WindyLayout, encoding: str = "onehot", patch_radius: int = 2
) -> np.ndarray:
    """Observation of every cell, ``(S, D)`` float32 (the env gathers rows): ``onehot`` (D = S),
    ``coords_patch`` (normalised ``(row, col)`` and a ``(2r+1)^2`` wall/windy/goal patch),
    ``fourier_patch``, ``rowcol_patch`` and ``exits_patch`` (``coords_patch`` plus positional
    features, docs/scale.md). The instance is never in it.
    """
    S = layout.num_cells
    if encoding == "onehot":
        return np.eye(S, dtype=np.float32)
    if encoding == "exits_patch":  # coords_patch + (row, col) offset to each exit, / side
        base = observation_table(layout, "coords_patch", patch_radius)
        side = max(layout.height - 1, layout.width - 1, 1)
        rows, cols = np.divmod(np.arange(S), layout.width)
        offsets = []
        for group in layout.exit_cells:
            er, ec = np.divmod(np.asarray(group), layout.width)
            offsets += [(er.mean() - rows) / side, (ec.mean() - cols) / side]
        return np.concatenate([base, np.stack(offsets, 1)], 1).astype(np.float32)
    if encoding == "rowcol_patch":  # coords_patch + one-hot row + one-hot column (D + H + W)
        base = observation_table(layout, "coords_patch", patch_radius)
        rows, cols = np.divmod(np.arange(S), layout.width)
        extra = np.concatenate([np.eye(layout.height)[rows], np.eye(layout.width)[cols]], 1)
        return np.concatenate([base, extra], 1).astype(np.float32)
    if encoding == "fourier_patch":
        base = observation_table(layout, "coords_patch", patch_radius)
        side = max(layout.height, layout.width)
        freqs = np.pi * 2.0 ** np.arange(int(np.ceil(np.log2(max(side, 2)))) + 1)  # (F,)
        x = base[:, :2, None] * freqs  # (S, 2, F)
        extra = np.concatenate([np.sin(x), np.cos(x)], 1).reshape(S, -1)  # (S, 4F)
        return np.concatenate([base, extra], 1).astype(np.float32)
    if encoding != "coords_patch":
        raise ValueError(
            f"observation encoding must be one of {list(OBS_ENCODINGS)}, got {encoding!r}"
        )
    if patch_radius < 0:
        raise ValueError(f"patch_radius must be >= 0, got {patch_radius}")
    H, W, r = layout.height, layout.width, patch_radius
    k = 2 * r + 1
    out = np.zeros((S, 2 + 3 * k * k), dtype=np.float32)
    for cell in range(S):
        row, col = divmod(cell, W)
        out[cell, 0] = row / max(H - 1, 1)
        out[cell, 1] = col / max(W - 1, 1)
        for i, dr in enumerate(range(-r, r + 1)):
            for j, dc in enumerate(range(-r, r + 1)):
                rr, cc = row + dr, col + dc
                inside = 0 <= rr < H and 0 <= cc < W
                ch = layout.rows[rr][cc] if inside else "#"
                base = 2 + i * k + j
                out[cell, base] = ch == "#"
                out[cell, base + k * k] = ch == "W"
                out[cell, base + 2 * k * k] = ch == "G"
    return out


def resolve_layout(layout: str | windy.WindyLayout) -> windy.WindyLayout:
    """A :class:`WindyLayout` from a layout name, a map string, or a layout."""
    if isinstance(layout, windy.WindyLayout):
        return layout
    if isinstance(layout, str) and layout in windy.LAYOUTS:
        return windy.WindyLayout.named(layout)
    if isinstance(layout, str) and "\n" in layout.strip():
        return windy.WindyLayout.from_map(layout)
    raise ValueError(
        f"layout must be one of {sorted(windy.LAYOUTS)}, a multi-line map string or a WindyLayout, "
        f"got {layout!r}"
    )


def start_cell(layout: windy.WindyLayout, start: object) -> int:
    """The flat cell of a start ``(row, col)``: a pair of integers inside the grid on a free cell
    (not a wall or goal), else a one-line ``ValueError``."""
    r, c = gym_checks.check_cell(start, layout.height, layout.width)
    if layout.rows[r][c] in "#G":
        raise ValueError(
            f"start must be a free (row, col) cell (not a wall or goal), got {start!r}"
        )
    return r * layout.width + c


class WindyGridEnv(BatchedFamilyEnv):
    """Batched windy gridworld family (paper §3.3.1) as a TorchRL environment.

    Each sub-env draws a hidden instance ``(p, direction)`` at every (partial) reset; actions
    ``Categorical(4)`` (north, south, east, west); reward -1 a step; terminated on a goal cell,
    truncated after ``horizon``. Keys: ``observation``, ``cell`` (``row * width + col``) and
    ``("instance", "p" | "direction")`` (analysis only).

    Args:
        num_envs: batch size N.
        layout: layout name, map string or :class:`WindyLayout`.
        instances: ``train``, ``test``, ``south``, ``north`` or a :class:`WindyInstances`.
        horizon: steps before truncation (default :func:`windy.default_horizon`).
        obs_encoding: see :func:`observation_table`.
        start: optional fixed start ``(row, col)``.
        seed: sub-env ``i`` draws from key ``(seed, index_offset + i)`` (any split reproduces).
        index_offset: global index of sub-env 0.
        noise_seed: salt of the gust stream; equal ``noise_seed`` means the same gusts
            (docs/windy-fig2.md).
        validate_actions: one-line error on an out-of-range action; ``None``: on CPU only.
        device: torch device.
    """

    def __init__(
        self,
        num_envs: int = 1,
        layout: str | windy.WindyLayout = "default",
        instances: str | WindyInstances | dict = "train",
        horizon: int | None = None,
        obs_encoding: str = "onehot",
        patch_radius: int = 2,
        start: tuple[int, int] | None = None,
        seed: int = 0,
        index_offset: int = 0,
        noise_seed: int = 0,
        validate_actions: bool | None = None,
        device: torch.device | str = "cpu",
    ):
        if int(num_envs) < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        super().__init__(device=device, batch_size=torch.Size([int(num_envs)]))
        self.layout = resolve_layout(layout)
        self.model = windy.WindyModel(self.layout, self.device)
        self.instances = windy_instances(instances)
        self.horizon = int(horizon) if horizon is not None else windy.default_horizon(self.layout)
        if self.horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        self.obs_encoding = obs_encoding
        self._obs_table = torch.as_tensor(
            observation_table(self.layout, obs_encoding, patch_radius), device=self.device
        )
        self.start = None if start is None else start_cell(self.layout, start)
        self.index_offset = int(index_offset)
        self.noise_seed = int(noise_seed)
        self._noise_salt = rng.hash32(rng.hash32(self.noise_seed & rng.MASK32) ^ 0x5BD1E995)
        self.validate_actions = (
            self.device.type == "cpu" if validate_actions is None else bool(validate_actions)
        )
        counters = (*self.instances.counters, _C_START)  # the instance's, then the start cell's
        self._reset_counters = torch.tensor(counters, device=self.device).unsqueeze(-1)  # (C, 1)
        self._make_specs()
        self._set_seed(seed)

    def _make_specs(self) -> None:
        N, S = self.num_envs, self.model.num_cells
        D = self._obs_table.shape[1]
        dev = self.device
        self.observation_spec = Composite(
            {
                keys.OBSERVATION: Bounded(0.0, 1.0, shape=(N, D), dtype=torch.float32, device=dev),
                keys.CELL: Categorical(S, shape=(N,), dtype=torch.int64, device=dev),
                keys.INSTANCE: Composite(
                    p=Bounded(0.0, 1.0, shape=(N,), dtype=torch.float32, device=dev),
                    direction=Categorical(4, shape=(N,), dtype=torch.int64, device=dev),
                    shape=(N,),
                    device=dev,
                ),
            },
            shape=(N,),
            device=dev,
        )
        self.action_spec = Categorical(4, shape=(N,), dtype=torch.int64, device=dev)
        self.reward_spec = Unbounded(shape=(N, 1), dtype=torch.float32, device=dev)
        self.make_done_spec()

    runtime_state = ("_base_key", "_episode", "_key32", "_threshold", "_t", "_p", "_dir", "_cell")
    """Simulator state that changes as the env runs (saved for exact resume)."""

    def state_bounds(self) -> dict[str, tuple[float, float]]:
        return {
            **super().state_bounds(),
            "cell": (0, self.layout.num_cells - 1),
            "dir": (0, len(windy.DIRECTIONS) - 1),
            "p": (0.0, 1.0),
            "t": (0, self.horizon),
            "threshold": (0, 1 << 24),
        }

    def _out(self, cell, p, direction, reward=None, terminated=None, truncated=None):
        td = {
            keys.OBSERVATION: self._obs_table.index_select(0, cell),
            keys.CELL: cell,
            keys.INSTANCE: TensorDict._new_unsafe(
                {"p": p, "direction": direction}, batch_size=self.batch_size, device=self.device
            ),
        }
        return self.finish(td, reward, terminated, truncated)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        reset = None if tensordict is None else tensordict.get("_reset", None)
        self._start_episodes(reset if hasattr(self, "_cell") else None)
        return self._out(self._cell, self._p, self._dir)

    def _start_episodes(self, reset: torch.Tensor | None) -> None:
        """Start the next episode of the sub-envs where ``reset`` (``(N,)`` or ``(N, 1)`` bool) is
        set, or of all of them (``None``): new instance, start cell, gust key and step counter."""
        idx, key = self.next_episodes_where(reset)
        bits = rng.draw_bits(key, self._reset_counters)  # (C, n): every reset draw in one pass
        p, direction = self.instances.from_bits(bits)
        if self.start is None:
            starts = self.model.start_cells
            cell = starts.index_select(0, rng.index_of(bits[-1], starts.numel()))
        else:
            cell = torch.full_like(key, self.start)
        noise_key = key if self.noise_seed == 0 else rng.hash32(key ^ self._noise_salt)
        key32, threshold = rng.to_i32(noise_key), rng.probability_threshold(p)
        t = torch.zeros_like(key32)
        state = dict(_key32=key32, _threshold=threshold, _t=t, _p=p, _dir=direction, _cell=cell)
        if idx is not None:  # out-of-place updates: tensors already handed out are never mutated
            state = {k: getattr(self, k).index_put((idx,), v) for k, v in state.items()}
        self.replace_state(state)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(keys.ACTION).reshape(-1)
        cell, terminated, truncated = self._advance(action)
        reward = torch.full((self.num_envs, 1), -1.0, device=self.device)
        return self._out(
            cell, self._p, self._dir, reward, terminated.unsqueeze(-1), truncated.unsqueeze(-1)
        )

    def _advance(self, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One step of every sub-env: gusts, move, count; returns ``(cell, terminated, truncated)``
        ``(N,)``."""
        if self.validate_actions and (
            bool((action < 0).any()) or bool((action >= self.model.num_actions).any())
        ):
            bad = action[(action < 0) | (action >= self.model.num_actions)][0].item()
            raise ValueError(f"action must be in [0, {self.model.num_actions - 1}], got {bad}")
        gust = rng.bernoulli_i32(self._key32, self._t, self._threshold)  # (N,) this step's wind
        cell, terminated = windy.step(self.model, self._cell, action, self._dir, gust)
        self.replace_state({"_cell": cell, "_t": self._t + 1})
        truncated = (self._t >= self.horizon) & ~terminated
        return cell, terminated, truncated

    def render(self, index: int = 0, mode: str = "ansi"):
        """Render sub-environment ``index`` as text (``ansi``) or an image (``rgb_array``)."""

        cell = int(self._cell[index])
        p, d = float(self._p[index]), windy.DIRECTIONS[int(self._dir[index])]
        if mode == "ansi":
            return render.windy_ansi(self.layout, cell, p, d)
        if mode == "rgb_array":
            return render.windy_rgb(self.layout, cell, d)
        raise ValueError(f"render mode must be one of ['ansi', 'rgb_array'], got {mode!r}")
