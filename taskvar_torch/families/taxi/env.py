"""TorchRL ``EnvBase`` over the batched Taxi-v4 dynamics (``taxi.py``)."""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded

from taskvar_torch import keys, rng
from taskvar_torch.envs.batched import BatchedFamilyEnv
from taskvar_torch.envs.gym_checks import as_int
from taskvar_torch.families.taxi import dynamics as taxi
from taskvar_torch.families.taxi.dynamics import TaxiInstances, taxi_instances

OBS_ENCODINGS = ("onehot", "factored")
# reset counters after the instance's (taxi._C_*): the start state, then the fickle arming
_C_START, _C_ARMED = rng.RESET_COUNTER + 6, rng.RESET_COUNTER + 7
# step t draws its rain outcome from counter 2t and its fickle redraw from counter 2t + 1


def observation_table(encoding: str = "onehot") -> np.ndarray:
    """Observation of every Taxi-v4 state, ``(500, D)`` float32: ``onehot`` (D = 500) or
    ``factored`` (one-hot row, column, passenger, destination; D = 19). The instance is never in it.
    """
    if encoding == "onehot":
        return np.eye(taxi.NUM_STATES, dtype=np.float32)
    if encoding != "factored":
        raise ValueError(f"obs_encoding must be one of {list(OBS_ENCODINGS)}, got {encoding!r}")
    row, col, pas, dest = taxi.decode(np.arange(taxi.NUM_STATES))
    return np.concatenate(
        [np.eye(5)[row], np.eye(5)[col], np.eye(5)[pas], np.eye(4)[dest]], axis=1
    ).astype(np.float32)


def check_state(state: object, name: str = "start") -> int:
    """A Taxi-v4 state as an int in ``[0, 500)``; one-line ``ValueError`` otherwise."""
    s = as_int(state)
    if s is None or not 0 <= s < taxi.NUM_STATES:
        raise ValueError(
            f"{name} must be a Taxi-v4 state in [0, {taxi.NUM_STATES - 1}], got {state!r}"
        )
    return s


def instance_state(q: torch.Tensor, f: torch.Tensor, armed_bits: torch.Tensor) -> dict:
    """The env state an episode's instance fixes, each ``(n,)``: ``q``, ``f``, the rain's integer
    thresholds and the fickle arming (Bernoulli(f) from the ``_C_ARMED`` bits).
    """
    return dict(
        _q=q,
        _f=f,
        _thr_intended=rng.probability_threshold(q),
        _thr_left=rng.probability_threshold(0.5 * (1.0 + q.to(torch.float64))),
        _armed=(armed_bits >> 8) < rng.probability_threshold(f),
    )


class TaxiEnv(BatchedFamilyEnv):
    """Batched Taxi family (Gymnasium Taxi-v4 with hidden rain and fickle passenger) as a TorchRL
    env.

    ## Description Taxi-v4's dynamics exactly (tests/families/taxi/test_taxi_env.py); each
    sub-environment draws its hidden instance at every (partial) reset. docs/taxi.md#the-family.

    ## Action Space ``Categorical(6)``: 0 south, 1 north, 2 east, 3 west, 4 pickup, 5 dropoff.

    ## Observation Space ``observation`` (``onehot`` 500 or ``factored`` 19, float32); ``cell`` the
    Taxi-v4 state (int64); for analysis only ``("instance", "rainy_probability" |
    "fickle_probability" | "armed")``.

    ## Starting State Uniform over Taxi-v4's 300 initial states, or ``start``.

    ## Reward -1 per step, +20 for a delivery, -10 for an illegal pickup or dropoff.

    ## Episode End Terminated on delivery; truncated after ``horizon`` steps (200).

    ## Task parameters ``rainy_probability`` q (1 is dry) and ``fickle_probability`` f, drawn from
    ``instances``.

    Args:
        num_envs: batch size N.
        instances: a name, a dict of :class:`TaxiInstances` fields or one.
        horizon: steps before truncation.
        obs_encoding: ``onehot`` or ``factored``.
        start: optional fixed start state (0..499).
        seed: sub-environment ``i`` draws from key ``(seed, index_offset + i)``.
        index_offset: global index of sub-environment 0.
        noise_seed: salt of the per-step stream (rain, redraws): same ``seed`` and ``noise_seed``
            give common random numbers.
        validate_actions: check actions are in range (one host sync per step); ``None``: CPU only.
        device: torch device.
    """

    runtime_state = (
        "_base_key",
        "_episode",
        "_key32",
        "_thr_intended",
        "_thr_left",
        "_t",
        "_q",
        "_f",
        "_armed",
        "_state",
    )
    """Simulator state that changes as the env runs (saved for exact resume)."""

    def state_bounds(self) -> dict[str, tuple[float, float]]:
        return {
            **super().state_bounds(),
            "state": (0, taxi.NUM_STATES - 1),
            "t": (0, self.horizon),
            "q": (0.0, 1.0),
            "f": (0.0, 1.0),
            "thr_intended": (0, 1 << 24),
            "thr_left": (0, 1 << 24),
        }

    def __init__(
        self,
        num_envs: int = 1,
        instances: str | TaxiInstances | dict = "train",
        horizon: int = 200,
        obs_encoding: str = "onehot",
        start: int | None = None,
        seed: int = 0,
        index_offset: int = 0,
        noise_seed: int = 0,
        validate_actions: bool | None = None,
        device: torch.device | str = "cpu",
    ):
        if int(num_envs) < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        super().__init__(device=device, batch_size=torch.Size([int(num_envs)]))
        self.model = taxi.TaxiModel(self.device)
        self.instances = taxi_instances(instances)
        self.horizon = int(horizon)
        if self.horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        self.obs_encoding = obs_encoding
        self._obs_table = torch.as_tensor(observation_table(obs_encoding), device=self.device)
        self.start = None if start is None else check_state(start)
        self.index_offset = int(index_offset)
        self.noise_seed = int(noise_seed)
        self._noise_salt = rng.hash32(rng.hash32(self.noise_seed & rng.MASK32) ^ 0x5BD1E995)
        self.validate_actions = (
            self.device.type == "cpu" if validate_actions is None else bool(validate_actions)
        )
        counters = (*self.instances.counters, _C_START, _C_ARMED)
        self._reset_counters = torch.tensor(counters, device=self.device).unsqueeze(-1)  # (C, 1)
        self._pair = torch.tensor([[0], [1]], dtype=torch.int32, device=self.device)  # (2, 1)
        self._make_specs()
        self._set_seed(seed)

    def _make_specs(self) -> None:
        N, S, dev = self.num_envs, taxi.NUM_STATES, self.device
        D = self._obs_table.shape[1]
        prob = Bounded(0.0, 1.0, shape=(N,), dtype=torch.float32, device=dev)
        self.observation_spec = Composite(
            {
                keys.OBSERVATION: Bounded(0.0, 1.0, shape=(N, D), dtype=torch.float32, device=dev),
                keys.CELL: Categorical(S, shape=(N,), dtype=torch.int64, device=dev),
                keys.INSTANCE: Composite(
                    rainy_probability=prob,
                    fickle_probability=prob.clone(),
                    armed=Categorical(2, shape=(N,), dtype=torch.bool, device=dev),
                    shape=(N,),
                    device=dev,
                ),
            },
            shape=(N,),
            device=dev,
        )
        self.action_spec = Categorical(taxi.NUM_ACTIONS, shape=(N,), dtype=torch.int64, device=dev)
        self.reward_spec = Unbounded(shape=(N, 1), dtype=torch.float32, device=dev)
        self.make_done_spec()

    def _out(self, reward=None, terminated=None, truncated=None) -> TensorDictBase:
        instance = {
            "rainy_probability": self._q,
            "fickle_probability": self._f,
            "armed": self._armed,
        }
        td = {
            keys.OBSERVATION: self._obs_table.index_select(0, self._state),
            keys.CELL: self._state,
            keys.INSTANCE: TensorDict._new_unsafe(
                instance, batch_size=self.batch_size, device=self.device
            ),
        }
        return self.finish(td, reward, terminated, truncated)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        reset = None if tensordict is None else tensordict.get("_reset", None)
        self._start_episodes(reset if hasattr(self, "_state") else None)
        return self._out()

    def _start_episodes(self, reset: torch.Tensor | None) -> None:
        """Start the next episode of the sub-envs where ``reset`` (``(N,)`` or ``(N, 1)`` bool) is
        set, or of all of them (``None``): new instance, start state, arming, noise key, step 0."""
        idx, key = self.next_episodes_where(reset)
        bits = rng.draw_bits(key, self._reset_counters)  # (C, n): every reset draw in one pass
        q, f = self.instances.from_bits(bits[:-2])
        if self.start is None:
            starts = self.model.start_states
            state = starts.index_select(0, rng.index_of(bits[-2], starts.numel()))
        else:
            state = torch.full_like(key, self.start)
        noise_key = key if self.noise_seed == 0 else rng.hash32(key ^ self._noise_salt)
        key32 = rng.to_i32(noise_key)
        new = dict(
            _key32=key32, _t=torch.zeros_like(key32), _state=state, **instance_state(q, f, bits[-1])
        )
        if idx is not None:  # out-of-place updates: tensors already handed out are never mutated
            new = {k: getattr(self, k).index_put((idx,), v) for k, v in new.items()}
        self.replace_state(new)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(keys.ACTION).reshape(-1)
        reward, terminated, truncated = self._advance(action)
        return self._out(reward.unsqueeze(-1), terminated.unsqueeze(-1), truncated.unsqueeze(-1))

    def _advance(self, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One step of every sub-env with ``action (N,)``; returns ``(reward, terminated,
        truncated)``.
        """
        if self.validate_actions and bool(((action < 0) | (action >= taxi.NUM_ACTIONS)).any()):
            bad = action[(action < 0) | (action >= taxi.NUM_ACTIONS)][0].item()
            raise ValueError(f"action must be in [0, {taxi.NUM_ACTIONS - 1}], got {bad}")
        counters = torch.add(self._pair, self._t, alpha=2)  # (2, N): 2t rain, 2t + 1 redraw
        bits = rng.draw_bits_i32(self._key32, counters).bitwise_right_shift_(8)
        u, v = bits.bitwise_and_(0xFFFFFF)  # (N,) each, uniform on [0, 2^24)
        outcome = (u >= self._thr_intended).to(torch.int64).add_(u >= self._thr_left)  # (N,)
        redraw = v.mul(3).bitwise_right_shift_(24).to(torch.int64)  # (N,) uniform in {0, 1, 2}
        state, reward, terminated, armed = taxi.step(
            self.model, self._state, action, outcome, self._armed, redraw
        )
        self.replace_state({"_state": state, "_armed": armed, "_t": self._t + 1})
        truncated = (self._t >= self.horizon) & ~terminated
        return reward, terminated, truncated

    def render(self, index: int = 0, mode: str = "ansi"):
        """Render sub-environment ``index`` as text (``ansi``) or an image (``rgb_array``)."""
        state = int(self._state[index])
        if mode == "ansi":
            q, f = float(self._q[index]), float(self._f[index])
            return taxi.render_ansi(state, q, f)
        if mode == "rgb_array":
            return taxi.render_rgb(state)
        raise ValueError(f"render mode must be one of ['ansi', 'rgb_array'], got {mode!r}")
