"""Taxi family (Gymnasium ``Taxi-v4``): pure batched dynamics, exact model, instance distributions.

States use Taxi-v4's encoding ``((row * 5 + col) * 5 + passenger) * 4 + destination`` (500
states; ``passenger == 4`` means in the taxi). A step is table lookups (:class:`TaxiModel`); its
randomness is an input: ``outcome`` the rain draw (:func:`rain_outcome`), ``redraw`` the fickle
passenger's new destination. The rules (rain ``q``, fickle passenger ``f``) are Taxi-v4's:
docs/taxi.md#the-family.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from taskvar_torch import rng

MAP = (
    "+---------+",
    "|R: | : :G|",
    "| : | : : |",
    "| : : : : |",
    "| | : | : |",
    "|Y| : |B: |",
    "+---------+",
)
"""Taxi-v4's map: ``|`` is a wall between two cells, ``:`` an open side."""
LOCS = ((0, 0), (0, 4), (4, 0), (4, 3))
"""Pick-up/drop-off locations R, G, Y, B as ``(row, col)`` (Taxi-v4 order)."""
LOC_NAMES = ("R", "G", "Y", "B")
ACTIONS = ("south", "north", "east", "west", "pickup", "dropoff")
"""Action ``i`` is ``ACTIONS[i]`` (Taxi-v4 order)."""
NUM_ROWS, NUM_COLS = 5, 5
NUM_LOCS = 4
IN_TAXI = 4
"""Passenger index meaning "in the taxi"."""
NUM_STATES = 500
NUM_ACTIONS = 6
NUM_OUTCOMES = 3
"""Rain outcomes: 0 intended move, 1 left lateral, 2 right lateral."""
REWARD_STEP, REWARD_DELIVER, REWARD_ILLEGAL = -1, 20, -10

# (forward, left, right) (drow, dcol) per move action, as Gymnasium's ``moves`` table:
# south: left=east, right=west; north: left=west, right=east; east: left=north, right=south;
# west: left=south, right=north.
_MOVES = (
    ((1, 0), (0, 1), (0, -1)),
    ((-1, 0), (0, -1), (0, 1)),
    ((0, 1), (-1, 0), (1, 0)),
    ((0, -1), (1, 0), (-1, 0)),
)


def encode(row, col, passenger, destination):
    """Taxi-v4 state of ``(row, col, passenger, destination)``; ints or int64 tensors."""
    return ((row * NUM_COLS + col) * (NUM_LOCS + 1) + passenger) * NUM_LOCS + destination


def decode(state):
    """``(row, col, passenger, destination)`` of a Taxi-v4 state; ints or int64 tensors."""
    destination = state % NUM_LOCS
    state = state // NUM_LOCS
    passenger = state % (NUM_LOCS + 1)
    state = state // (NUM_LOCS + 1)
    return state // NUM_COLS, state % NUM_COLS, passenger, destination


def _open(row: int, col: int, dr: int, dc: int) -> bool:
    """Whether the side of ``(row, col)`` toward ``(dr, dc)`` is open (no wall, not the edge)."""
    if dr:
        return 0 <= row + dr < NUM_ROWS
    if dc == 1:
        return col < NUM_COLS - 1 and MAP[1 + row][2 * col + 2] == ":"
    return col > 0 and MAP[1 + row][2 * col] == ":"


def _moved(row: int, col: int, dr: int, dc: int) -> tuple[int, int]:
    """Position after a move toward ``(dr, dc)``; a wall or the edge leaves it in place."""
    return (row + dr, col + dc) if _open(row, col, dr, dc) else (row, col)


def _tables() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``next (S, A, 3)``, ``reward (S, A)``, ``done (S, A)`` of Taxi-v4 (numpy int64 / bool)."""
    S, A = NUM_STATES, NUM_ACTIONS
    nxt = np.zeros((S, A, NUM_OUTCOMES), dtype=np.int64)
    reward = np.full((S, A), REWARD_STEP, dtype=np.int64)
    done = np.zeros((S, A), dtype=bool)
    for s in range(S):
        row, col, pas, dest = decode(s)
        for a in range(A):
            if a < 4:
                forward, left, right = _MOVES[a]
                if _open(row, col, *forward):  # blocked intended move: no lateral drift either
                    cells = (_moved(row, col, *forward), _moved(row, col, *left))
                    cells += (_moved(row, col, *right),)
                else:
                    cells = ((row, col),) * 3
                nxt[s, a] = [encode(r, c, pas, dest) for r, c in cells]
                continue
            new_pas = pas
            if a == 4:  # pickup
                if pas < IN_TAXI and (row, col) == LOCS[pas]:
                    new_pas = IN_TAXI
                else:
                    reward[s, a] = REWARD_ILLEGAL
            elif pas == IN_TAXI and (row, col) == LOCS[dest]:  # dropoff at the destination
                new_pas, reward[s, a], done[s, a] = dest, REWARD_DELIVER, True
            elif pas == IN_TAXI and (row, col) in LOCS:  # dropoff at another location
                new_pas = LOCS.index((row, col))
            else:
                reward[s, a] = REWARD_ILLEGAL
            nxt[s, a] = encode(row, col, new_pas, dest)
    return nxt, reward, done


def initial_states() -> np.ndarray:
    """Taxi-v4's 300 start states (its ``initial_state_distrib`` is uniform over them), ascending:
    any taxi position, passenger at a location, destination another location."""
    states = [
        encode(r, c, p, d)
        for r in range(NUM_ROWS)
        for c in range(NUM_COLS)
        for p in range(NUM_LOCS)
        for d in range(NUM_LOCS)
        if p != d
    ]
    return np.array(sorted(states), dtype=np.int64)


class TaxiModel:
    """Lookup tables of Taxi-v4 on one device; the pure step functions read only these.

    Attributes: ``next (S, A, 3)`` int64 next state per rain outcome (0 intended, 1 left, 2 right),
    ``reward (S, A)`` float32, ``done (S, A)`` bool, ``start_states (300,)``, ``fickle_moves (S,
    S)`` and ``fickle_targets (S, 3)`` (as :func:`fickle_rule`); ``*_flat`` copies for one-gather
    lookups; ``np_*`` numpy copies for the single-environment Gymnasium path.
    """

    def __init__(self, device: torch.device | str = "cpu"):
        self.device = torch.device(device)
        nxt, reward, done = _tables()
        moves, targets = _fickle_tables()
        t = dict(dtype=torch.int64, device=self.device)
        self.next = torch.as_tensor(nxt, **t)
        self.next_flat = self.next.reshape(-1).contiguous()
        self.reward = torch.as_tensor(reward, dtype=torch.float32, device=self.device)
        self.reward_flat = self.reward.reshape(-1).contiguous()
        self.done = torch.as_tensor(done, device=self.device)
        self.done_flat = self.done.reshape(-1).contiguous()
        self.start_states = torch.as_tensor(initial_states(), **t)
        self.fickle_moves = torch.as_tensor(moves, device=self.device)
        self.fickle_targets = torch.as_tensor(targets, **t)
        self.fickle_targets_flat = self.fickle_targets.reshape(-1).contiguous()
        # fickle_fires_flat[(s * A + a) * 3 + k]: the rule fires on outcome k of (s, a)
        fires_sak = np.take_along_axis(moves, nxt.reshape(NUM_STATES, -1), 1)  # (S, A * 3)
        self.fickle_fires_flat = torch.as_tensor(fires_sak.reshape(-1).copy(), device=self.device)
        self.num_states, self.num_actions = NUM_STATES, NUM_ACTIONS


def _fickle_tables() -> tuple[np.ndarray, np.ndarray]:
    """``fires (S, S)`` bool and ``targets (S, 3)`` int64 of the fickle rule (see TaxiModel)."""
    s = np.arange(NUM_STATES)
    row, col, pas, dest = decode(s)
    pos = row * NUM_COLS + col
    fires = (pas[:, None] == IN_TAXI) & (pos[:, None] != pos[None, :])
    others = np.array([[d for d in range(NUM_LOCS) if d != k] for k in range(NUM_LOCS)])  # (4, 3)
    targets = encode(row[:, None], col[:, None], pas[:, None], others[dest])  # (S, 3)
    return fires, targets.astype(np.int64)


def fickle_rule(
    device: torch.device | str = "cpu",
) -> tuple[torch.Tensor, torch.Tensor]:
    """The fickle passenger rule as tensors, for an exact model over ``(state, armed)``.

    Returns ``(fires (S, S') bool, targets (S', 3) int64)``: whether an armed passenger changes
    destination on ``s -> s'``, and the three states ``s'`` becomes (probability 1/3 each).
    """
    moves, targets = _fickle_tables()
    return torch.as_tensor(moves, device=device), torch.as_tensor(targets, device=device)


def rain_outcome(u: torch.Tensor, rainy_probability: torch.Tensor) -> torch.Tensor:
    """Rain outcome (0 intended, 1 left, 2 right) of uniforms ``u (N,)`` under ``q (N,)``."""
    q = rainy_probability
    return (u >= q).to(torch.int64) + (u >= 0.5 * (1.0 + q)).to(torch.int64)


def step(
    model: TaxiModel,
    state: torch.Tensor,  # (N,) int64 Taxi-v4 state
    action: torch.Tensor,  # (N,) int64 in [0, 6)
    outcome: torch.Tensor,  # (N,) int64 rain outcome in {0, 1, 2} (0 when dry)
    armed: torch.Tensor,  # (N,) bool: the fickle passenger may still change destination
    redraw: torch.Tensor,  # (N,) int64 in {0, 1, 2}: which other destination, if the rule fires
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """One batched Taxi-v4 step with the randomness given.

    Returns ``(next_state, reward, terminated, armed)``, each ``(N,)`` (int64, float32, bool,
    bool); ``armed`` is cleared where the fickle rule fired.
    """
    sa = torch.add(action, state, alpha=NUM_ACTIONS)  # (N,)
    sao = torch.add(outcome, sa, alpha=NUM_OUTCOMES)  # (N,)
    nxt = model.next_flat.index_select(0, sao)  # (N,)
    reward = model.reward_flat.index_select(0, sa)  # (N,)
    terminated = model.done_flat.index_select(0, sa)  # (N,)
    fire = model.fickle_fires_flat.index_select(0, sao).logical_and_(armed)  # (N,)
    fired = model.fickle_targets_flat.index_select(0, torch.add(redraw, nxt, alpha=3))  # (N,)
    nxt = torch.where(fire, fired, nxt)
    return nxt, reward, terminated, armed & ~fire


def transition_tensors(
    rainy_probability: torch.Tensor | float | list[float],
    device: torch.device | str = "cpu",
    dtype: torch.dtype = torch.float64,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Exact model of Taxi-v4 without the fickle passenger for a batch of ``q`` (1.0 is dry).

    Returns ``P (B, S, A, S')``, ``R (B, S, A)`` and ``done (B, S, A)`` bool, as Gymnasium's ``P``
    (no absorbing state). Add the fickle passenger with :func:`fickle_rule`.
    """
    q = torch.as_tensor(rainy_probability, dtype=dtype, device=device).reshape(-1)
    if bool(((q < 0) | (q > 1) | q.isnan()).any()):
        raise ValueError(f"rainy_probability must be in [0, 1], got {q.tolist()}")
    model = _model(torch.device(device))
    B, S, A = q.shape[0], NUM_STATES, NUM_ACTIONS
    is_move = torch.arange(A, device=device) < 4  # (A,)
    lateral = (0.5 * (1.0 - q)).view(B, 1, 1)  # (B, 1, 1)
    p_int = torch.where(is_move, q.view(B, 1, 1), torch.ones_like(lateral))  # (B, 1, A)
    p_lat = torch.where(is_move, lateral, torch.zeros_like(lateral))  # (B, 1, A)
    probs = torch.stack([p_int, p_lat, p_lat], -1).expand(B, S, A, NUM_OUTCOMES)  # (B, S, A, 3)
    P = torch.zeros(B, S, A, S, dtype=dtype, device=device)
    P.scatter_add_(3, model.next.unsqueeze(0).expand(B, S, A, NUM_OUTCOMES), probs)
    R = model.reward.to(dtype).unsqueeze(0).expand(B, S, A).clone()
    done = model.done.unsqueeze(0).expand(B, S, A).clone()
    return P, R, done


_MODELS: dict[torch.device, TaxiModel] = {}


def _model(device: torch.device) -> TaxiModel:
    """A cached :class:`TaxiModel` per device (the tables are constants)."""
    if device not in _MODELS:
        _MODELS[device] = TaxiModel(device)
    return _MODELS[device]


# reset-time counters (see rng.RESET_COUNTER); the env adds its own for the start state and arming
_C_RAINY, _C_Q, _C_FICKLE, _C_F = (rng.RESET_COUNTER + k for k in (1, 2, 3, 4))
_C_POINT = rng.RESET_COUNTER + 5


@dataclass(frozen=True)
class TaxiInstances:
    """Distribution of Taxi instances ``(rainy_probability q, fickle_probability f)``.

    Per episode rainy with probability ``rain_share`` (``q ~ U[q_low, q_high]``, else 1.0) and
    fickle with probability ``fickle_share`` (``f ~ U[f_low, f_high]``, else 0.0); or uniform over
    ``points``. Named distributions (:meth:`named`): docs/taxi.md#the-family.
    """

    rain_share: float = 0.5
    q_low: float = 0.7
    q_high: float = 0.9
    fickle_share: float = 0.5
    f_low: float = 0.2
    f_high: float = 0.4
    points: tuple[tuple[float, float], ...] | None = None

    NAMES = ("train", "test", "dry", "heavy_rain", "fickle", "storm", "gymnasium")

    def __post_init__(self):
        for name in ("rain_share", "q_low", "q_high", "fickle_share", "f_low", "f_high"):
            v = getattr(self, name)
            if not 0.0 <= float(v) <= 1.0:  # NaN fails too
                raise ValueError(f"{name} must be in [0, 1], got {v}")
            object.__setattr__(self, name, float(v))
        for lo, hi in (("q_low", "q_high"), ("f_low", "f_high")):
            if getattr(self, lo) > getattr(self, hi):
                raise ValueError(
                    f"{lo} ({getattr(self, lo)}) must be <= {hi} ({getattr(self, hi)})"
                )
        if self.points is not None:
            pts = tuple((float(q), float(f)) for q, f in self.points)
            if not pts:
                raise ValueError("points must hold at least one (rainy_probability, f) pair")
            for q, f in pts:
                if not 0.0 <= q <= 1.0:
                    raise ValueError(f"rainy_probability must be in [0, 1], got {q}")
                if not 0.0 <= f <= 1.0:
                    raise ValueError(f"fickle_probability must be in [0, 1], got {f}")
            object.__setattr__(self, "points", pts)
        object.__setattr__(self, "_tensors", {})  # device -> point tensors (not a field)

    @classmethod
    def named(cls, name: str) -> TaxiInstances:
        """One of :attr:`NAMES`."""
        if name in ("train", "test"):
            return cls()
        if name == "dry":
            return cls(rain_share=0.0, fickle_share=0.0)
        if name == "heavy_rain":
            return cls(rain_share=1.0, q_low=0.5, q_high=0.7, fickle_share=0.0)
        if name == "fickle":
            return cls(rain_share=0.0, fickle_share=1.0, f_low=0.8, f_high=1.0)
        if name == "storm":
            return cls(
                rain_share=1.0, q_low=0.5, q_high=0.7, fickle_share=1.0, f_low=0.8, f_high=1.0
            )
        if name == "gymnasium":
            return cls.fixed(0.8, 0.3)
        raise ValueError(f"instance distribution must be one of {list(cls.NAMES)}, got {name!r}")

    @classmethod
    def fixed(
        cls, rainy_probability: float = 1.0, fickle_probability: float = 0.0
    ) -> TaxiInstances:
        """A single instance (``q = 1`` dry, ``f = 0`` never fickle)."""
        return cls(points=((float(rainy_probability), float(fickle_probability)),))

    @property
    def counters(self) -> tuple[int, ...]:
        """The reset counters :meth:`sample` draws from (one per random quantity)."""
        return (_C_POINT,) if self.points is not None else (_C_RAINY, _C_Q, _C_FICKLE, _C_F)

    def sample(self, key: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(rainy_probability, fickle_probability)`` float32 for each episode key (B,) int64."""
        counters = torch.tensor(self.counters, device=key.device).unsqueeze(-1)  # (C, 1)
        return self.from_bits(rng.draw_bits(key, counters))

    def from_bits(self, bits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`sample` from ``rng.draw_bits(key, c)`` for the ``c`` in :attr:`counters`
        (``(C, B)``), so a caller can draw them together with its own counters."""
        if self.points is not None:
            values = self._tensors.get(bits.device)
            if values is None:
                pts = torch.tensor(self.points, dtype=torch.float32, device=bits.device)  # (K, 2)
                values = self._tensors[bits.device] = (pts[:, 0].clone(), pts[:, 1].clone())
            k = rng.index_of(bits[0], len(self.points))
            return values[0].index_select(0, k), values[1].index_select(0, k)
        u = rng.uniform_of(bits)  # (4, B) float32
        rainy = u[0] < self.rain_share
        q = torch.where(rainy, self.q_low + (self.q_high - self.q_low) * u[1], 1.0)
        fickle = u[2] < self.fickle_share
        f = torch.where(fickle, self.f_low + (self.f_high - self.f_low) * u[3], 0.0)
        return q, f


def taxi_instances(spec: str | TaxiInstances | dict) -> TaxiInstances:
    """Coerce a name, a dict of fields, or a :class:`TaxiInstances` into one."""
    if isinstance(spec, TaxiInstances):
        return spec
    if isinstance(spec, str):
        return TaxiInstances.named(spec)
    if isinstance(spec, dict):
        allowed = {"rain_share", "q_low", "q_high", "fickle_share", "f_low", "f_high", "points"}
        unknown = sorted(set(spec) - allowed)
        if unknown:
            raise ValueError(f"unknown instance field(s) {unknown}; allowed: {sorted(allowed)}")
        return TaxiInstances(**spec)
    raise ValueError(
        f"instances must be a name {list(TaxiInstances.NAMES)}, a dict or TaxiInstances"
    )


def render_ansi(
    state: int,
    rainy_probability: float | None = None,
    fickle_probability: float | None = None,
    last_action: int | None = None,
) -> str:
    """Taxi-v4's map as plain text, with Taxi-v4's header and footer."""
    row, col, pas, dest = decode(int(state))
    out = [list(line) for line in MAP]
    if pas < IN_TAXI:
        pr, pc = LOCS[pas]
        out[1 + pr][2 * pc + 1] = out[1 + pr][2 * pc + 1].lower()
    out[1 + row][2 * col + 1] = "P" if pas == IN_TAXI else "T"
    where = "in taxi" if pas == IN_TAXI else LOC_NAMES[pas]
    head = f"passenger: {where}, destination: {LOC_NAMES[dest]}"
    if rainy_probability is not None:
        head += f" | rainy_probability={rainy_probability:.2f}"
    if fickle_probability is not None:
        head += f" fickle_probability={fickle_probability:.2f}"
    foot = "" if last_action is None else f"  ({ACTIONS[int(last_action)].capitalize()})"
    return head + "\n" + "\n".join("".join(line) for line in out) + "\n" + foot + "\n"


_LOC_COLOURS = ((220, 60, 60), (60, 180, 60), (230, 200, 40), (60, 90, 220))
CELL_PX = 32


def render_rgb(state: int, cell_px: int = CELL_PX) -> np.ndarray:
    """``(5*px, 5*px, 3)`` uint8 image of a state."""
    row, col, pas, dest = decode(int(state))
    px = cell_px
    img = np.full((NUM_ROWS * px, NUM_COLS * px, 3), 245, dtype=np.uint8)
    for k, (r, c) in enumerate(LOCS):
        tile = img[r * px : (r + 1) * px, c * px : (c + 1) * px]
        tile[:] = (np.array(_LOC_COLOURS[k]) * 0.35 + 245 * 0.65).astype(np.uint8)
        if k == dest:
            b = max(px // 10, 1)
            tile[:b], tile[-b:], tile[:, :b], tile[:, -b:] = (_LOC_COLOURS[k],) * 4
    yy, xx = np.mgrid[0:px, 0:px]
    c0 = (px - 1) / 2
    disc = (yy - c0) ** 2 + (xx - c0) ** 2 <= (0.22 * px) ** 2
    if pas < IN_TAXI:
        r, c = LOCS[pas]
        img[r * px : (r + 1) * px, c * px : (c + 1) * px][disc] = (120, 40, 160)
    m = px // 5
    taxi = img[row * px + m : (row + 1) * px - m, col * px + m : (col + 1) * px - m]
    taxi[:] = (250, 190, 0)
    if pas == IN_TAXI:
        taxi[m : -m or None, m : -m or None] = (120, 40, 160)
    for r in range(NUM_ROWS):
        for c in range(NUM_COLS - 1):
            if MAP[1 + r][2 * c + 2] == "|":
                img[r * px : (r + 1) * px, (c + 1) * px - 2 : (c + 1) * px + 2] = (40, 40, 50)
    img[::px, :] = img[:, ::px] = (200, 200, 200)
    return img
