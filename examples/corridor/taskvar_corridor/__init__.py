"""The corridor family: an outside task family for taskvar_torch, in one module.

A corridor of ``length`` cells. The goal is at one end, and which end is hidden; a move slips to
the opposite direction with a hidden probability ``slip``. Both are drawn per episode (the
instance), so a memoryless policy cannot know which end it has already tried, while the options
``west`` and ``east`` (each initiable everywhere but at its own end) can: at an end, only the
other option can start.

It follows taskvar_torch's family contract (docs/families.md there): a batched TorchRL env built on
``BatchedFamilyEnv`` with keyed randomness, options as a ``Subtasks``, named instance and test
distributions, its own config keys under ``env.corridor``, and the entry point
``taskvar_torch.families: corridor = "taskvar_corridor:family"`` in ``pyproject.toml``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded

from taskvar_torch import keys, rng
from taskvar_torch.envs.batched import BatchedFamilyEnv
from taskvar_torch.families import Family, TestDistribution
from taskvar_torch.subtasks.base import Subtasks

_C_GOAL, _C_SLIP, _C_START = rng.RESET_COUNTER + 1, rng.RESET_COUNTER + 2, rng.RESET_COUNTER + 3
WEST, EAST = 0, 1


@dataclass(frozen=True)
class CorridorConfig:
    """The family's own keys (``env.corridor.*``)."""

    length: int = 7
    """Cells of the corridor (>= 3)."""
    horizon: int = 40
    """Steps before truncation."""

    def __post_init__(self):
        if self.length < 3:
            raise ValueError(f"length must be >= 3, got {self.length}")
        if self.horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {self.horizon}")


@dataclass(frozen=True)
class CorridorInstances:
    """Goal at the east end with probability ``east_share``; ``slip ~ U[slip_low, slip_high]``."""

    east_share: float = 0.5
    slip_low: float = 0.0
    slip_high: float = 0.2

    NAMES = ("train", "test", "east", "slippery")

    def __post_init__(self):
        for name in ("east_share", "slip_low", "slip_high"):
            if not 0.0 <= float(getattr(self, name)) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if self.slip_low > self.slip_high:
            raise ValueError(f"slip_low ({self.slip_low}) must be <= slip_high ({self.slip_high})")

    @classmethod
    def of(cls, spec: Any) -> CorridorInstances:
        """A name, a dict of fields or an instance distribution."""
        if isinstance(spec, cls):
            return spec
        if isinstance(spec, dict):
            return cls(**spec)
        named = {
            "train": cls(),
            "test": cls(),
            "east": cls(east_share=1.0),
            "slippery": cls(slip_low=0.3, slip_high=0.5),
        }
        if spec not in named:
            raise ValueError(f"instances must be one of {list(cls.NAMES)}, got {spec!r}")
        return named[spec]


class CorridorEnv(BatchedFamilyEnv):
    """A batched corridor; actions 0 west, 1 east; reward -1 per step; the goal end terminates.

    Keys: ``observation`` (one-hot cell), ``cell`` (int64), ``("instance", "goal")`` (0 west, 1
    east) and ``("instance", "slip")``, hidden.
    """

    runtime_state = ("_base_key", "_episode", "_key", "_t", "_cell", "_goal", "_slip")
    """What ``env.state_dict()`` saves for exact resume: every state tensor ``(N, ...)``."""

    def __init__(
        self,
        num_envs: int = 1,
        length: int = 7,
        horizon: int = 40,
        instances: Any = "train",
        seed: int = 0,
        index_offset: int = 0,
        noise_seed: int = 0,
        validate_actions: bool | None = None,
        device: torch.device | str = "cpu",
    ):
        super().__init__(device=device, batch_size=torch.Size([int(num_envs)]))
        self.length, self.horizon = int(length), int(horizon)
        self.instances = CorridorInstances.of(instances)
        self.index_offset, self.noise_seed = int(index_offset), int(noise_seed)
        self.validate_actions = (
            self.device.type == "cpu" if validate_actions is None else bool(validate_actions)
        )
        N, L, dev = self.num_envs, self.length, self.device
        self.observation_spec = Composite(
            {
                keys.OBSERVATION: Bounded(0.0, 1.0, shape=(N, L), dtype=torch.float32, device=dev),
                keys.CELL: Categorical(L, shape=(N,), dtype=torch.int64, device=dev),
                keys.INSTANCE: Composite(
                    goal=Categorical(2, shape=(N,), dtype=torch.int64, device=dev),
                    slip=Bounded(0.0, 1.0, shape=(N,), dtype=torch.float32, device=dev),
                    shape=(N,),
                    device=dev,
                ),
            },
            shape=(N,),
            device=dev,
        )
        self.action_spec = Categorical(2, shape=(N,), dtype=torch.int64, device=dev)
        self.reward_spec = Unbounded(shape=(N, 1), dtype=torch.float32, device=dev)
        self.make_done_spec()
        self._set_seed(seed)

    def _out(self, reward=None, terminated=None, truncated=None) -> TensorDictBase:
        td = {
            keys.OBSERVATION: torch.nn.functional.one_hot(self._cell, self.length).float(),
            keys.CELL: self._cell,
            keys.INSTANCE: TensorDict._new_unsafe(
                {"goal": self._goal, "slip": self._slip}, batch_size=self.batch_size
            ),
        }
        return self.finish(td, reward, terminated, truncated)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        idx, key = self.next_episodes(tensordict, started=hasattr(self, "_cell"))
        inst = self.instances
        goal = (rng.draw_uniform(key, _C_GOAL) < inst.east_share).to(torch.int64)
        slip = inst.slip_low + (inst.slip_high - inst.slip_low) * rng.draw_uniform(key, _C_SLIP)
        cell = 1 + rng.draw_index(key, _C_START, self.length - 2)  # never at an end
        noise = key if self.noise_seed == 0 else rng.hash32(key ^ rng.hash32(self.noise_seed))
        state = {"_key": noise, "_t": torch.zeros_like(key), "_cell": cell, "_goal": goal}
        state["_slip"] = slip.to(torch.float32)
        if idx is not None:  # out of place: tensors already handed out stay valid
            state = {k: getattr(self, k).index_put((idx,), v) for k, v in state.items()}
        self.replace_state(state)
        return self._out()

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(keys.ACTION).reshape(-1)
        if self.validate_actions and bool(((action < 0) | (action > 1)).any()):
            raise ValueError(f"action must be 0 (west) or 1 (east), got {action.tolist()}")
        slipped = rng.draw_uniform(self._key, self._t) < self._slip
        direction = torch.where(slipped, 1 - action, action) * 2 - 1  # (N,) -1 west, +1 east
        cell = (self._cell + direction).clamp(0, self.length - 1)
        terminated = cell == self._goal * (self.length - 1)
        t = self._t + 1
        self.replace_state({"_cell": cell, "_t": t})
        truncated = (t >= self.horizon) & ~terminated
        reward = torch.full((self.num_envs, 1), -1.0, device=self.device)
        return self._out(reward, terminated.unsqueeze(-1), truncated.unsqueeze(-1))


class CorridorSubtasks(Subtasks):
    """``west`` and ``east``: walk to that end; initiable everywhere but there; -1 per step, and
    ``-horizon`` more where the episode ends at the other end (an option is credited with reaching
    *its* end only, not with the goal the instance happened to put elsewhere)."""

    names = ("west", "east")

    def __init__(self, length: int, horizon: int):
        self.length, self.horizon = int(length), int(horizon)

    def _ends(self, td: TensorDictBase) -> torch.Tensor:
        cell = td.get(keys.CELL)
        return torch.stack([cell == 0, cell == self.length - 1], -1)  # (B, 2)

    def initiation(self, td: TensorDictBase) -> torch.Tensor:
        return ~self._ends(td)

    def termination(self, td: TensorDictBase) -> torch.Tensor:
        return self._ends(td)

    def reward(self, td: TensorDictBase) -> torch.Tensor:
        nxt = td.get(keys.NEXT)
        ended = nxt.get(keys.TERMINATED).reshape(*td.batch_size, 1)  # (B, 1) the goal reached
        elsewhere = ended & ~self._ends(nxt)  # (B, 2) at the other option's end
        return -1.0 - self.horizon * elsewhere.to(torch.float32)


def _section(cfg: Any) -> CorridorConfig:
    return getattr(cfg.env, "corridor", None) or CorridorConfig()


def _fields(spec: Any) -> dict[str, Any]:
    inst = CorridorInstances.of(spec)
    return {"east_share": inst.east_share, "slip_low": inst.slip_low, "slip_high": inst.slip_high}


def family() -> Family:
    """The corridor :class:`Family` (this package's ``taskvar_torch.families`` entry point)."""
    return Family(
        name="corridor",
        description="a corridor whose goal end and slip are hidden (examples/corridor)",
        env_class=CorridorEnv,
        env_kwargs=lambda cfg: {
            "num_envs": cfg.env.num_envs,
            "length": _section(cfg).length,
            "horizon": _section(cfg).horizon,
            "instances": cfg.env.instances,
            "seed": cfg.seed,
            "device": cfg.device,
        },
        subtasks=lambda cfg, env: CorridorSubtasks(env.length, env.horizon),
        instance_names=CorridorInstances.NAMES,
        config_class=CorridorConfig,
        tests={
            "train": TestDistribution("fresh training instances"),
            "east": TestDistribution("the goal always at the east end", "east"),
            "slippery": TestDistribution("slip ~ U[0.3, 0.5] (trained on [0, 0.2])", "slippery"),
        },
        instance_fields=_fields,
        make_instances=CorridorInstances.of,
        cells=lambda cfg: _section(cfg).length,
    )
