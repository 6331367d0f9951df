"""TorchRL ``EnvBase`` over the batched Wargus dynamics (paper §3.5)."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded

from taskvar_torch import keys, rng
from taskvar_torch.compiling import Compiled
from taskvar_torch.envs import gym_checks
from taskvar_torch.envs.batched import BatchedFamilyEnv
from taskvar_torch.families.wargus import dynamics as wargus
from taskvar_torch.families.wargus import render as wargus_render
from taskvar_torch.families.wargus.dynamics import WargusConfig, WargusInstances, WargusState


def _dynamics_step(
    model: wargus.WargusModel,
    state: WargusState,
    action: torch.Tensor,  # (N,) int64
    key: torch.Tensor,  # (N,) int64 instance keys
    item_seen: torch.Tensor,  # (N,) bool, before the step
) -> tuple[WargusState, torch.Tensor, torch.Tensor, tuple, torch.Tensor]:
    """One step's pure dynamics: ``(state, picked, destroyed, observe(state), item_lost)``."""
    state, picked, destroyed = wargus.step(model, state, action, key)
    observed = wargus.observe(model, state)
    return state, picked, destroyed, observed, wargus.item_lost(item_seen, observed[1], picked)


_COMPILED_DYNAMICS: Compiled | None = None  # shared by every env of the process


class WargusEnv(BatchedFamilyEnv):
    """Batched Wargus resource-gathering family (paper §3.5) as a TorchRL environment.

    Each sub-env draws a hidden instance seed at every (partial) reset; dynamics, step order and the
    ``observation (N, 24)`` layout are in ``families/wargus/dynamics.py``. Actions
    ``Categorical(8)`` (0 N, 1 NE, ..., 7 NW; 9 with ``noop``); reward +1 per item; terminated when
    destroyed, truncated at ``horizon``. Integer state for the subtasks: ``agent_pos``,
    ``item_seen``, ``patrol_seen``, ``picked``, ``item_lost``; hidden (analysis only):
    ``("instance", "seed" | "patrol_pos" | "item_pos")``.

    Args:
        num_envs: batch size N.
        config: a :class:`WargusConfig` or dict; its fields as keywords override it.
        instances: ``train``, ``test``, ``nominal`` or a :class:`WargusInstances`.
        start: optional fixed agent start ``(row, col)``.
        seed: sub-env ``i`` draws from ``(seed, index_offset + i)`` (any split reproduces).
        index_offset: global index of sub-env 0.
        noise_seed: must be 0 (the instance seed fixes the whole episode).
        validate_actions: one-line error on an out-of-range action; ``None``: on CPU only.
        device: torch device.
    """

    def __init__(
        self,
        num_envs: int = 1,
        config: WargusConfig | dict | None = None,
        *,
        size: int | None = None,
        num_patrols: int | None = None,
        num_items: int | None = None,
        sight: int | None = None,
        shoot_range: int | None = None,
        hit_prob: float | None = None,
        patrol_speed: float | None = None,
        horizon: int | None = None,
        noop: bool | None = None,
        instances: str | WargusInstances | dict = "train",
        start: tuple[int, int] | None = None,
        seed: int = 0,
        index_offset: int = 0,
        noise_seed: int = 0,
        validate_actions: bool | None = None,
        device: torch.device | str = "cpu",
    ):
        if int(num_envs) < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if int(noise_seed) != 0:
            raise ValueError(
                f"noise_seed must be 0 for Wargus, got {noise_seed}: its instance seed fixes the "
                "whole episode, so there is no per-step noise to redraw"
            )
        self.config = WargusConfig.from_any(
            config,
            size=size,
            num_patrols=num_patrols,
            num_items=num_items,
            sight=sight,
            shoot_range=shoot_range,
            hit_prob=hit_prob,
            patrol_speed=patrol_speed,
            horizon=horizon,
            noop=noop,
        )
        super().__init__(device=device, batch_size=torch.Size([int(num_envs)]))
        self.model = wargus.WargusModel(self.config, self.device)
        self.instances = wargus.wargus_instances(instances)
        self.horizon = self.config.horizon
        self.start = None
        if start is not None:
            cell = gym_checks.check_cell(start, self.config.size, self.config.size)
            self.start = torch.tensor(cell, dtype=torch.int64, device=self.device)
        self.index_offset = int(index_offset)
        self.validate_actions = (
            self.device.type == "cpu" if validate_actions is None else bool(validate_actions)
        )
        self._make_specs()
        self._index = torch.arange(self.num_envs, device=self.device) + self.index_offset  # (N,)
        self._set_seed(seed)

    def _make_specs(self) -> None:
        N, K, M = self.num_envs, self.config.num_patrols, self.config.num_items
        n, dev = self.config.size, self.device

        def pos(*shape: int) -> Bounded:
            return Bounded(0, n - 1, shape=shape, dtype=torch.int64, device=dev)

        flag = Categorical(2, shape=(N,), dtype=torch.bool, device=dev)
        self.observation_spec = Composite(
            {
                # scalar bounds: per-element ones (m.obs_low / m.obs_high, used by the Gymnasium
                # Box) would be materialised by TorchRL as two (N, 24) tensors
                keys.OBSERVATION: Bounded(
                    -1.0, 1.0, shape=(N, wargus.OBS_DIM), dtype=torch.float32, device=dev
                ),
                wargus.AGENT_POS: pos(N, 2),
                wargus.ITEM_SEEN: flag.clone(),
                wargus.PATROL_SEEN: flag.clone(),
                wargus.PICKED: Bounded(0, M, shape=(N,), dtype=torch.int64, device=dev),
                wargus.ITEM_LOST: flag.clone(),
                keys.INSTANCE: Composite(
                    {
                        wargus.INSTANCE_SEED: Bounded(
                            0, rng.MASK32, shape=(N,), dtype=torch.int64, device=dev
                        ),
                        wargus.PATROL_POS: pos(N, K, 2),
                        wargus.ITEM_POS: pos(N, M, 2),
                    },
                    shape=(N,),
                    device=dev,
                ),
            },
            shape=(N,),
            device=dev,
        )
        self.action_spec = Categorical(
            self.config.num_actions, shape=(N,), dtype=torch.int64, device=dev
        )
        self.reward_spec = Unbounded(shape=(N, 1), dtype=torch.float32, device=dev)
        self.make_done_spec()

    runtime_state = ("_base_key", "_episode", "_iseed", "_ikey", "_picked", "_item_lost")

    def state_bounds(self) -> dict[str, tuple[float, float]]:
        side = self.config.size - 1
        return {
            **super().state_bounds(),
            "state_agent": (0, side),
            "state_patrols": (0, side),
            "state_items": (0, side),
            "state_t": (0, self.horizon),
            "iseed": (0, rng.MASK32),
        }

    def get_runtime_state(self) -> dict[str, torch.Tensor]:
        """The base's, and each ``WargusState`` field as ``state_FIELD``."""
        state = super().get_runtime_state()
        if hasattr(self, "_state"):
            state.update({f"state_{k}": v for k, v in self._state._asdict().items()})
        return state

    def set_runtime_state(self, state: dict[str, torch.Tensor]) -> None:
        """The base's, the ``WargusState`` back from its fields, and what is a function of it."""
        super().set_runtime_state(state)
        fields = WargusState._fields
        if all(f"state_{k}" in state for k in fields):
            self._state = WargusState(*(state[f"state_{k}"] for k in fields))
            self._item_seen = wargus.observe(self.model, self._state)[1]  # a function of the state
            if "item_lost" not in state:  # saved before the event existed
                self._item_lost = torch.zeros_like(self._item_seen)

    def _out(
        self,
        picked: torch.Tensor,  # (N,) int64
        item_lost: torch.Tensor,  # (N,) bool
        reward: torch.Tensor | None = None,  # (N, 1) float32
        terminated: torch.Tensor | None = None,  # (N, 1) bool
        truncated: torch.Tensor | None = None,  # (N, 1) bool
        observed: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
    ) -> TensorDictBase:
        """The env's tensordict at the current state; ``observed``: ``wargus.observe`` of it, if known."""
        state = self._state
        if observed is None:
            observed = wargus.observe(self.model, state)
        obs, item_seen, patrol_seen = observed
        self._item_seen = item_seen  # read by the next step's item_lost (never mutated)
        td = {
            keys.OBSERVATION: obs,
            wargus.AGENT_POS: state.agent,
            wargus.ITEM_SEEN: item_seen,
            wargus.PATROL_SEEN: patrol_seen,
            wargus.PICKED: picked,
            wargus.ITEM_LOST: item_lost,
            keys.INSTANCE: TensorDict._new_unsafe(
                {
                    wargus.INSTANCE_SEED: self._iseed,
                    wargus.PATROL_POS: state.patrols,
                    wargus.ITEM_POS: state.items,
                },
                batch_size=self.batch_size,
                device=self.device,
            ),
        }
        return self.finish(td, reward, terminated, truncated)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        idx, ekey = self.next_episodes(tensordict, started=hasattr(self, "_state"))  # (n,) keys
        index = self._index if idx is None else self._index[idx]
        ep = self._episode if idx is None else self._episode[idx]
        iseed = self.instances.sample(ekey, index, ep)  # (n,) instance seeds
        ikey = wargus.instance_key(iseed)  # (n,)
        st = wargus.reset(self.model, ikey, self.start)
        if idx is None:
            self._iseed, self._ikey, self._state = iseed, ikey, st
            self._picked = torch.zeros_like(iseed)
            self._item_lost = torch.zeros_like(iseed, dtype=torch.bool)
        else:  # out-of-place updates: tensors already handed out are never mutated
            self._iseed = self._iseed.index_put((idx,), iseed)
            self._ikey = self._ikey.index_put((idx,), ikey)
            old = self._state
            self._state = WargusState(
                old.agent.index_put((idx,), st.agent),
                old.patrols.index_put((idx,), st.patrols),
                old.items.index_put((idx,), st.items),
                old.t.index_put((idx,), st.t),
            )
            self._picked = self._picked.index_put((idx,), torch.zeros_like(iseed))
            self._item_lost = self._item_lost.index_put(
                (idx,), torch.zeros_like(iseed, dtype=torch.bool)
            )
        return self._out(self._picked, self._item_lost)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self.step_all(tensordict.get(keys.ACTION).reshape(-1))

    def reset_all(self) -> TensorDictBase:
        """Start a new episode in every sub-env and return their data: ``reset()``'s draws without
        ``EnvBase``'s checks and transforms (the Figure 4 fast loop).
        """
        return self._reset(None)

    def step_all(self, action: torch.Tensor) -> TensorDictBase:
        """One step of every sub-env with ``action (N,)``: what ``step()`` writes under ``"next"``,
        without ``EnvBase``'s checks and transforms and without automatic reset."""
        if self.validate_actions:
            wargus.check_actions(self.model, action)
        state, picked, destroyed, observed, item_lost = self._dynamics(
            self.model, self._state, action, self._ikey, self._item_seen
        )
        self._state, self._picked, self._item_lost = state, picked, item_lost
        terminated = destroyed.unsqueeze(-1)  # (N, 1)
        truncated = (state.t >= self.horizon).unsqueeze(-1) & ~terminated  # (N, 1)
        reward = picked.to(torch.float32).unsqueeze(-1)  # (N, 1)
        return self._out(picked, self._item_lost, reward, terminated, truncated, observed)

    _dynamics = staticmethod(_dynamics_step)  # the pure step of step_all (compile_dynamics)

    def compile_dynamics(self) -> None:
        """Run :meth:`step_all`'s pure dynamics through ``torch.compile`` (``train.compile``;
        :class:`~taskvar_torch.compiling.Compiled`): the same bits, one compile per batch size.
        """
        global _COMPILED_DYNAMICS
        if _COMPILED_DYNAMICS is None:
            _COMPILED_DYNAMICS = Compiled(_dynamics_step, "the Wargus dynamics")
        self._dynamics = _COMPILED_DYNAMICS

    def render(self, index: int = 0, mode: str = "ansi"):
        """Render sub-environment ``index`` as text (``ansi``) or an image (``rgb_array``)."""

        if not 0 <= index < self.num_envs:
            raise ValueError(f"index must be in [0, {self.num_envs - 1}], got {index}")
        s = self._state
        frame = wargus_render.Frame.from_tensors(
            self.config,
            s.agent[index],
            s.patrols[index],
            s.items[index],
            t=int(s.t[index]),
            seed=int(self._iseed[index]),
        )
        return wargus_render.render(frame, mode)
