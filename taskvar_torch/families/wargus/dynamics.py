"""Wargus resource-gathering family (paper §3.5): config, instances, pure batched dynamics.

A square grid (row 0 is north), no obstacles, one agent, ``K`` patrols, ``M`` items; a batch of
``B`` episodes. **State** (:class:`WargusState`): ``agent`` (B, 2), ``patrols`` (B, K, 2),
``items`` (B, M, 2), ``t`` (B,), positions ``(row, col)`` int64.

**Instance** (paper §3.5): an integer seed ``s in [0, 2^32)``; :func:`instance_key` makes it the
key of the episode's counter-based stream (``rng.py``), from which every draw of the episode
comes, so the same seed and actions give the same episode on any batch or device.

**Step order** (:func:`step`):

1. the agent moves one cell in one of 8 compass directions (8 = stay, with ``noop``), clipped;
2. every item on the agent's cell is picked (+1 each) and reappears at a random other cell;
3. each patrol moves with probability ``patrol_speed``: towards the agent if it sees it
   (Chebyshev distance ``< sight``), else one random compass step, clipped;
4. every patrol within Chebyshev distance ``<= shoot_range`` shoots; each shot destroys the agent
   with probability ``hit_prob`` (terminated); the envs truncate at ``horizon``.

**Observation** (:func:`observe`), ``OBS_DIM = 24`` float32:

=========  =====================================================================================
index      meaning
=========  =====================================================================================
0:2        own ``(row, col) / (size - 1)``
2:10       bearing of the nearest item, one-hot over the 8 compass sectors ``BEARINGS``
10         item seen flag (Chebyshev distance ``< sight``)
11:13      item offset ``(drow, dcol) / sight`` (item minus agent) when seen, else 0
13:21      bearing of the nearest patrol, one-hot over ``BEARINGS``
21         patrol seen flag
22:24      patrol offset ``(drow, dcol) / sight`` when seen, else 0
=========  =====================================================================================

Nearest by Chebyshev distance (ties: lowest index); 45-degree sectors in exact integer arithmetic;
an object on the agent's cell has an all-zero bearing; sight is symmetric.

**Events** (for subtask terminations): ``picked`` (items picked on the step that led here) and
``item_lost`` (:func:`item_lost`); both 0 / False after a reset.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, NamedTuple

import torch

from taskvar_torch import rng

ACTIONS = (
    "north",
    "northeast",
    "east",
    "southeast",
    "south",
    "southwest",
    "west",
    "northwest",
    "noop",
)
"""Action ``i`` moves one cell towards ``ACTIONS[i]``; ``noop`` (8) exists only when ``noop=True``."""
BEARINGS = ACTIONS[:8]
"""Compass sectors of the bearing one-hots, in action order (sector i = direction of action i)."""
DELTAS = ((-1, 0), (-1, 1), (0, 1), (1, 1), (1, 0), (1, -1), (0, -1), (-1, -1), (0, 0))
"""(drow, dcol) per action."""

OBS_DIM = 24
OBS_AGENT = slice(0, 2)
OBS_ITEM_BEARING = slice(2, 10)
OBS_ITEM_SEEN = 10
OBS_ITEM_OFFSET = slice(11, 13)
OBS_PATROL_BEARING = slice(13, 21)
OBS_PATROL_SEEN = 21
OBS_PATROL_OFFSET = slice(22, 24)

# Tensordict keys this family emits beside the observation (plain names, see keys.py); all are
# state of the *next* observation's time step, so subtask rewards read td and td["next"].
AGENT_POS = "agent_pos"  # (N, 2) int64 (row, col)
ITEM_SEEN = "item_seen"  # (N,) bool: the nearest item is within sight
PATROL_SEEN = "patrol_seen"  # (N,) bool: some patrol is within sight
PICKED = "picked"  # (N,) int64: items picked on the step that led here (0 after reset)
ITEM_LOST = (
    "item_lost"  # (N,) bool: the step that led here lost sight of the item (False after reset)
)
# Hidden, under ("instance", ...): never read by a policy.
INSTANCE_SEED = "seed"  # (N,) int64 in [0, 2^32): the instance
PATROL_POS = "patrol_pos"  # (N, K, 2) int64
ITEM_POS = "item_pos"  # (N, M, 2) int64

MAX_PATROLS = 64
MAX_ITEMS = 64
MAX_SIZE = 4096  # draw_index needs size * size < 2^24
MIN_SIZE = 4

# Counters. Step t uses ``t * STRIDE + offset``; the offsets below keep every purpose (and every
# patrol / item) on its own counter, so adding a patrol never changes another's draws.
STRIDE = 4 * 64
_C_ITEM = 0  # + m: respawn cell of item m
_C_PATROL_MOVE = 64  # + k: does patrol k move this step (u < patrol_speed)
_C_PATROL_WALK = 128  # + k: random-walk direction of patrol k
_C_HIT = 192  # + k: does patrol k's shot hit (u < hit_prob)
MAX_HORIZON = rng.RESET_COUNTER // STRIDE - 1
# reset-time counters (from rng.RESET_COUNTER up)
_R_AGENT = rng.RESET_COUNTER
_R_ITEM = rng.RESET_COUNTER + 1  # + m
PATROL_START_TRIES = 16
_R_PATROL = rng.RESET_COUNTER + 128  # + k * PATROL_START_TRIES + try
_R_PICK = rng.RESET_COUNTER + 4096  # uniform choice among fixed seeds (on the env episode key)
_INSTANCE_SALT = 0x5851F42D

OPTION_KEYS = ("composed_reward",)
"""Keys of the family's ``env.wargus`` section read by the options, not the dynamics
(``families/wargus/family.py`` ``WargusSection``)."""
NOMINAL_SEEDS = (0, 1, 2, 3, 4)
"""The paper's "5 nominal test episodes" with fixed parameters (paper §3.5.1, Wargus Figure 4)."""


@dataclass(frozen=True)
class WargusConfig:
    """Shape constants of a Wargus family; validated on construction.

    Args:
        size: grid side, in ``[4, 4096]``.
        num_patrols: K, in ``[1, 64]``. num_items: M, in ``[1, 64]`` (the paper: 1).
        sight: an object is seen at Chebyshev distance ``< sight``; in ``[1, size]``.
        shoot_range: a patrol shoots at distance ``<= shoot_range``; in ``[0, sight - 1]``.
        hit_prob: probability that a shot destroys the agent, in ``[0, 1]``.
        patrol_speed: probability that a patrol moves on a step, in ``[0, 1]``.
        horizon: steps before truncation, in ``[1, MAX_HORIZON]``.
        noop: add action 8, stay in place.
    """

    size: int = 32
    """Grid side length (size x size cells, no obstacles)."""
    num_patrols: int = 1
    """Number of enemy patrols."""
    num_items: int = 1
    """Number of items present at a time."""
    sight: int = 8
    """An object is seen when its Chebyshev distance to the viewer is < sight."""
    shoot_range: int = 5
    """A patrol shoots when the agent is within this Chebyshev distance."""
    hit_prob: float = 1.0
    """Probability that a shot destroys the agent."""
    patrol_speed: float = 0.8
    """Probability that a patrol moves on a given step."""
    horizon: int = 500
    """Steps before truncation."""
    noop: bool = False
    """Add a no-op action to the 8 compass moves."""

    def __post_init__(self) -> None:
        def _int(name: str, lo: int, hi: int) -> None:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ValueError(f"{name} must be an integer in [{lo}, {hi}], got {v!r}")

        def _prob(name: str) -> None:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= v <= 1.0:
                raise ValueError(f"{name} must be a probability in [0, 1], got {v!r}")
            object.__setattr__(self, name, float(v))

        _int("size", MIN_SIZE, MAX_SIZE)
        _int("num_patrols", 1, MAX_PATROLS)
        _int("num_items", 1, MAX_ITEMS)
        _int("sight", 1, self.size)
        _int("shoot_range", 0, self.sight - 1)
        _int("horizon", 1, MAX_HORIZON)
        _prob("hit_prob")
        _prob("patrol_speed")
        if not isinstance(self.noop, bool):
            raise ValueError(f"noop must be one of [True, False], got {self.noop!r}")

    @property
    def num_actions(self) -> int:
        return 9 if self.noop else 8

    @property
    def num_cells(self) -> int:
        return self.size * self.size

    @classmethod
    def from_any(cls, config: WargusConfig | dict | None = None, **overrides: Any) -> WargusConfig:
        """A config from a config, a dict or ``None``, with non-``None`` overrides; unknown names
        raise ``ValueError``; :data:`OPTION_KEYS` are skipped, so a whole ``env.wargus`` section
        builds it."""
        allowed = {f.name for f in fields(cls)}
        if config is None:
            base: dict[str, Any] = {}
        elif isinstance(config, WargusConfig):
            base = {name: getattr(config, name) for name in allowed}
        elif isinstance(config, dict):
            base = dict(config)
        else:
            raise ValueError(
                f"config must be a WargusConfig, a dict or None, got {type(config).__name__}"
            )
        base.update({k: v for k, v in overrides.items() if v is not None})
        base = {k: v for k, v in base.items() if k not in OPTION_KEYS}
        unknown = sorted(set(base) - allowed)
        if unknown:
            raise ValueError(
                f"unknown Wargus config field(s) {unknown}; allowed: {sorted(allowed)}"
            )
        return cls(**base)


CONFIGS = {
    "default": WargusConfig(),
    "large": WargusConfig(size=64, num_patrols=3, horizon=1000),
}
"""Named scaled-up variants (docs/scale.md); ``large`` matches ``taskvar/Wargus-Large-v0``."""


@dataclass(frozen=True)
class WargusInstances:
    """Distribution of Wargus instance seeds (paper §3.5).

    ``seeds=None``: a fresh seed per episode (the episode key, ``rng.py``); else from ``seeds``,
    with ``order="cycle"`` (episode ``e`` of sub-env ``i`` plays ``seeds[(i + e) % len(seeds)]``) or
    ``"uniform"`` (keyed). Named (:meth:`named`): ``train``, ``test``, ``nominal``
    (:data:`NOMINAL_SEEDS`, cycled)."""

    seeds: tuple[int, ...] | None = None
    order: str = "cycle"

    NAMES = ("train", "test", "nominal")
    ORDERS = ("cycle", "uniform")

    def __post_init__(self) -> None:
        if self.order not in self.ORDERS:
            raise ValueError(f"order must be one of {list(self.ORDERS)}, got {self.order!r}")
        if self.seeds is not None:
            seeds = tuple(self.seeds)
            if not seeds:
                raise ValueError("seeds must hold at least one seed (or be None for fresh seeds)")
            for s in seeds:
                if isinstance(s, bool) or not isinstance(s, int) or not 0 <= s <= rng.MASK32:
                    raise ValueError(f"seeds must be integers in [0, {rng.MASK32}], got {s!r}")
            object.__setattr__(self, "seeds", seeds)

    @classmethod
    def named(cls, name: str) -> WargusInstances:
        """``train``, ``test`` or ``nominal``."""
        if name in ("train", "test"):
            return cls()
        if name == "nominal":
            return cls(seeds=NOMINAL_SEEDS)
        raise ValueError(f"instance distribution must be one of {list(cls.NAMES)}, got {name!r}")

    @classmethod
    def fixed(cls, seed: int) -> WargusInstances:
        """A single instance."""
        return cls(seeds=(seed,))

    def sample(
        self,
        key: torch.Tensor,  # (B,) int64: env episode keys
        index: torch.Tensor,  # (B,) int64: global sub-environment indices
        episode: torch.Tensor,  # (B,) int64: episode numbers
    ) -> torch.Tensor:
        """Instance seeds ``(B,)`` int64 in ``[0, 2^32)``."""
        if self.seeds is None:
            return key
        table = torch.tensor(self.seeds, dtype=torch.int64, device=key.device)  # (L,)
        if self.order == "cycle":
            return table[(index + episode) % len(self.seeds)]
        return table[rng.draw_index(key, _R_PICK, len(self.seeds))]


def wargus_instances(spec: str | WargusInstances | dict) -> WargusInstances:
    """Coerce a name, a dict of fields, or a :class:`WargusInstances` into one."""
    if isinstance(spec, WargusInstances):
        return spec
    if isinstance(spec, str):
        return WargusInstances.named(spec)
    if isinstance(spec, dict):
        allowed = {"seeds", "order"}
        unknown = sorted(set(spec) - allowed)
        if unknown:
            raise ValueError(f"unknown instance field(s) {unknown}; allowed: {sorted(allowed)}")
        seeds = spec.get("seeds")
        return WargusInstances(
            seeds=None if seeds is None else tuple(seeds), order=spec.get("order", "cycle")
        )
    raise ValueError(
        f"instances must be a name {list(WargusInstances.NAMES)}, a dict or WargusInstances"
    )


def instance_key(seed: torch.Tensor) -> torch.Tensor:
    """Key of the random stream of instance ``seed`` (B,) int64 (a bijection on uint32)."""
    return rng.hash32((seed ^ _INSTANCE_SALT) & rng.MASK32)


class WargusState(NamedTuple):
    """Batched dynamic state; ``t`` counts the steps taken in the episode."""

    agent: torch.Tensor  # (B, 2) int64
    patrols: torch.Tensor  # (B, K, 2) int64
    items: torch.Tensor  # (B, M, 2) int64
    t: torch.Tensor  # (B,) int64


class WargusModel:
    """A config's small constant tensors on one device; the pure functions read only these."""

    def __init__(self, config: WargusConfig, device: torch.device | str = "cpu"):
        self.config = config
        self.device = torch.device(device)
        c = config
        i64 = dict(dtype=torch.int64, device=self.device)
        self.size, self.sight, self.shoot_range = c.size, c.sight, c.shoot_range
        self.num_patrols, self.num_items = c.num_patrols, c.num_items
        self.num_actions = c.num_actions
        self.deltas = torch.tensor(DELTAS, **i64)  # (9, 2)
        self.walk_deltas = self.deltas[:8]  # (8, 2)
        # one-hot bearing of a quantised step (sr, sc) in {-1,0,1}^2, row (sr+1)*3 + (sc+1)
        table = torch.zeros(9, 8, dtype=torch.float32, device=self.device)
        for k, (dr, dc) in enumerate(DELTAS[:8]):
            table[(dr + 1) * 3 + (dc + 1), k] = 1.0
        self.bearing_table = table  # (9, 8); the row of (0, 0) is all zeros
        K, M = c.num_patrols, c.num_items
        self.item_offsets = torch.arange(M, **i64) + _C_ITEM  # (M,)
        self.move_offsets = torch.arange(K, **i64) + _C_PATROL_MOVE  # (K,)
        self.walk_offsets = torch.arange(K, **i64) + _C_PATROL_WALK  # (K,)
        self.hit_offsets = torch.arange(K, **i64) + _C_HIT  # (K,)
        self._step_offsets: dict[tuple[bool, bool], torch.Tensor] = {}
        self.item_reset_offsets = torch.arange(M, **i64) + _R_ITEM  # (M,)
        self.patrol_reset_offsets = (
            _R_PATROL
            + torch.arange(K, **i64).unsqueeze(-1) * PATROL_START_TRIES
            + torch.arange(PATROL_START_TRIES, **i64)
        )  # (K, T)
        self.try_ids = torch.arange(PATROL_START_TRIES, **i64)  # (T,)
        self.rank_items = torch.arange(M, **i64)  # (M,) tie-breaks for "nearest"
        self.rank_patrols = torch.arange(K, **i64)  # (K,)
        low = torch.zeros(OBS_DIM, dtype=torch.float32, device=self.device)
        low[OBS_ITEM_OFFSET] = -1.0
        low[OBS_PATROL_OFFSET] = -1.0
        self.obs_low, self.obs_high = low, torch.ones_like(low)  # (D,)

    def step_offsets(self, move: bool, hit: bool) -> torch.Tensor:
        """Counter offsets of one step's draws, ``[items | walks | moves if move | hits if hit]``."""
        offsets = self._step_offsets.get((move, hit))
        if offsets is None:
            parts = [self.item_offsets, self.walk_offsets]
            parts += [self.move_offsets] if move else []
            parts += [self.hit_offsets] if hit else []
            offsets = self._step_offsets[move, hit] = torch.cat(parts)
        return offsets


_INV24 = 1.0 / (1 << 24)


def chebyshev(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Chebyshev distance over the last dim (2) of broadcastable int64 positions."""
    return (a - b).abs().amax(-1)


def _random_cell_except(
    model: WargusModel,
    key: torch.Tensor,  # (B, 1) int64
    counter: torch.Tensor,  # (B, M) or (M,) int64
    avoid: torch.Tensor,  # (B, 2) int64
) -> torch.Tensor:
    """Uniform cell other than ``avoid``, (B, M, 2) int64."""
    size = model.size
    flat = rng.draw_index(key, counter, size * size - 1)  # (B, M)
    avoid_flat = (avoid[:, 0] * size + avoid[:, 1]).unsqueeze(-1)  # (B, 1)
    flat = flat + (flat >= avoid_flat).to(torch.int64)
    return torch.stack((flat // size, flat % size), dim=-1)


def reset(
    model: WargusModel,
    key: torch.Tensor,  # (B,) int64 instance keys
    start: torch.Tensor | None = None,  # (B, 2) int64 or None
) -> WargusState:
    """Initial state of each episode from its instance key: the agent at a uniform cell (or
    ``start``), items elsewhere, patrols outside its sight (keyed rejection sampling,
    ``PATROL_START_TRIES``)."""
    size, B = model.size, key.shape[0]
    k1 = key.unsqueeze(-1)  # (B, 1)
    if start is None:
        flat = rng.draw_index(key, _R_AGENT, size * size)  # (B,)
        agent = torch.stack((flat // size, flat % size), dim=-1)  # (B, 2)
    else:
        agent = start.to(torch.int64).expand(B, 2).clone()
    items = _random_cell_except(model, k1, model.item_reset_offsets, agent)  # (B, M, 2)
    cand = rng.draw_index(key.view(B, 1, 1), model.patrol_reset_offsets, size * size)  # (B, K, T)
    cand = torch.stack((cand // size, cand % size), dim=-1)  # (B, K, T, 2)
    ok = chebyshev(cand, agent.view(B, 1, 1, 2)) >= model.sight  # (B, K, T)
    first = torch.where(ok, model.try_ids, PATROL_START_TRIES - 1).amin(-1)  # (B, K)
    patrols = cand.gather(2, first.view(B, -1, 1, 1).expand(-1, -1, 1, 2)).squeeze(2)  # (B, K, 2)
    return WargusState(agent, patrols, items, torch.zeros_like(key))


def step(
    model: WargusModel,
    state: WargusState,
    action: torch.Tensor,  # (B,) int64
    key: torch.Tensor,  # (B,) int64 instance keys
    hit_prob: float | None = None,
    patrol_speed: float | None = None,
) -> tuple[WargusState, torch.Tensor, torch.Tensor]:
    """One batched step in the module docstring's order; returns ``(next_state, picked (B,) int64,
    destroyed (B,) bool)``; truncation is the caller's.
    """
    cfg = model.config
    hit_prob = cfg.hit_prob if hit_prob is None else hit_prob
    patrol_speed = cfg.patrol_speed if patrol_speed is None else patrol_speed
    B, K, M = action.shape[0], model.num_patrols, model.num_items
    hi, size = model.size - 1, model.size
    k1 = key.unsqueeze(-1)  # (B, 1)
    base = (state.t * STRIDE).unsqueeze(-1)  # (B, 1)
    # every draw of the step in one hash: columns [items | walks | moves? | hits?] (static flags:
    # at speed / hit probability 1 the draw u < 1 always holds and is skipped)
    move, hit = patrol_speed < 1.0, hit_prob < 1.0
    u24 = rng.draw_bits(k1, base + model.step_offsets(move, hit)) >> 8  # (B, C) in [0, 2^24)
    # 1. agent move
    agent = (state.agent + model.deltas.index_select(0, action)).clamp_(0, hi)  # (B, 2)
    a1 = agent.unsqueeze(1)  # (B, 1, 2)
    # 2. pickup and respawn at a uniform cell other than the agent's (as _random_cell_except)
    got = (state.items == a1).all(-1)  # (B, M)
    picked = got.sum(-1)  # (B,)
    flat = (u24[:, :M] * (size * size - 1)) >> 24  # (B, M) = rng.draw_index
    flat = flat + (flat >= (agent[:, :1] * size + agent[:, 1:])).to(torch.int64)
    fresh = torch.stack((flat // size, flat % size), dim=-1)  # (B, M, 2)
    items = state.items + (fresh - state.items) * got.unsqueeze(-1)  # (B, M, 2)
    # 3. patrols: chase what they see, else random walk; each moves with prob patrol_speed
    diff = a1 - state.patrols  # (B, K, 2)
    sees = (diff.abs().amax(-1) < model.sight).unsqueeze(-1)  # (B, K, 1)
    walk_dir = (u24[:, M : M + K] * 8) >> 24  # (B, K) = rng.draw_index(., ., 8)
    walk = model.walk_deltas.index_select(0, walk_dir.reshape(-1)).view(B, K, 2)  # (B, K, 2)
    delta = walk + (diff.sign() - walk) * sees  # (B, K, 2)
    c = M + K
    if move:
        moves = u24[:, c : c + K].to(torch.float32) * _INV24 < patrol_speed  # rng.draw_uniform
        delta = delta * moves.unsqueeze(-1)
        c += K
    patrols = (state.patrols + delta).clamp_(0, hi)  # (B, K, 2)
    # 4. shots
    in_range = chebyshev(a1, patrols) <= model.shoot_range  # (B, K)
    if hit:
        in_range = in_range & (u24[:, c : c + K].to(torch.float32) * _INV24 < hit_prob)
    destroyed = in_range.any(-1)  # (B,)
    return WargusState(agent, patrols, items, state.t + 1), picked, destroyed


def _nearest(
    model: WargusModel,
    agent: torch.Tensor,  # (B, 2)
    objs: torch.Tensor,  # (B, J, 2)
    rank: torch.Tensor,  # (J,)
) -> tuple[torch.Tensor, torch.Tensor]:
    """Offset (object minus agent) of the nearest object (B, 2) and its Chebyshev distance (B,)."""
    diff = objs - agent.unsqueeze(1)  # (B, J, 2)
    dist = diff.abs().amax(-1)  # (B, J)
    if objs.shape[1] == 1:
        return diff[:, 0], dist[:, 0]
    J = rank.shape[0]
    best = (dist * J + rank).amin(-1)  # (B,): unique scores, ties to the lowest index
    j = best % J  # (B,)
    return diff.gather(1, j.view(-1, 1, 1).expand(-1, 1, 2)).squeeze(1), best // J


def bearing_index(diff: torch.Tensor) -> torch.Tensor:
    """Row of :attr:`WargusModel.bearing_table` for offsets ``diff`` (..., 2): 45-degree sectors
    decided in exact integers; ``(0, 0)`` maps to row 4 (zeros)."""
    a = diff.abs()  # (..., 2)
    s = (a[..., 0] + a[..., 1]).unsqueeze(-1)  # (..., 1)
    sq2 = 2 * a * a  # (..., 2)
    keep = (s * s >= sq2.flip(-1)).to(
        diff.dtype
    )  # (..., 2): row kept unless east/west, col unless N/S
    q = diff.sign() * keep + 1  # (..., 2) in {0, 1, 2}
    return q[..., 0] * 3 + q[..., 1]


def bearing_onehot(model: WargusModel, diff: torch.Tensor) -> torch.Tensor:
    """One-hot compass sector (..., 8) float32 of offsets ``diff`` (..., 2) int64 (zeros for (0, 0))."""
    idx = bearing_index(diff)
    return model.bearing_table.index_select(0, idx.reshape(-1)).view(*idx.shape, 8)


def observe(
    model: WargusModel, state: WargusState
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(observation (B, 24) float32, item_seen (B,) bool, patrol_seen (B,) bool)``."""
    agent, B = state.agent, state.agent.shape[0]
    i_diff, i_dist = _nearest(model, agent, state.items, model.rank_items)  # (B, 2), (B,)
    p_diff, p_dist = _nearest(model, agent, state.patrols, model.rank_patrols)
    diff = torch.stack((i_diff, p_diff), 1)  # (B, 2 objects, 2)
    seen = torch.stack((i_dist, p_dist), 1) < model.sight  # (B, 2 objects)
    seen_f = seen.unsqueeze(-1).to(torch.float32)  # (B, 2, 1)
    per_object = torch.cat(
        (bearing_onehot(model, diff), seen_f, diff.to(torch.float32) * (seen_f / model.sight)), -1
    )  # (B, 2, 11): bearing, seen flag, offset
    obs = torch.cat(
        (agent.to(torch.float32) * (1.0 / (model.size - 1)), per_object.view(B, 22)), -1
    )  # (B, 24)
    return obs, seen[:, 0], seen[:, 1]


def item_lost(
    seen_before: torch.Tensor,  # (B,) bool: item_seen before the step
    seen_after: torch.Tensor,  # (B,) bool: item_seen after it
    picked: torch.Tensor,  # (B,) int64: items picked on the step
) -> torch.Tensor:
    """The event "lost sight of the item" (B,) bool: seen before the step, not after, nothing
    picked."""
    return seen_before & ~seen_after & (picked == 0)


def check_actions(model: WargusModel, action: torch.Tensor) -> None:
    """Raise ``ValueError`` naming the range if any action is outside ``[0, num_actions)`` (syncs)."""
    bad = (action < 0) | (action >= model.num_actions)
    if bool(bad.any()):
        raise ValueError(
            f"action must be in [0, {model.num_actions - 1}] ({', '.join(ACTIONS[: model.num_actions])}), "
            f"got {action[bad][0].item()}"
        )
