"""Shared machinery of the controllers (SPEC §3): carried state, primer, batched kernels, Gymnasium.

A controller is a ``TensorDictModuleBase`` that runs the heads it needs on the tensordict, reads
its carried state ``running_option`` ``(B,)`` int64 (-1 = none), decides, and writes ``action``,
the decision traces (``option``, ``interrupted``, ``hierarchy_level``) and the next state under
``("next", "running_option")`` -- exactly like a recurrent TorchRL module (``LSTMModule`` writes
``("next", "recurrent_state")``). :meth:`Controller.primer` returns the ``TensorDictPrimer`` that
puts the state in the env's specs and resets it to -1 per sub-environment on (partial) resets, so
``env.rollout`` and TorchRL ``Collector``s carry it with no further code.

The decision kernels are pure tensor functions over the batch. Reductions over a tiny last
dimension (argmax over 2 options or 4 actions) are slow on CPU for large batches, so for
``B >= LARGE_BATCH`` the kernels use elementwise loops over the option/action dimension instead
(same result, lowest index on ties); below it they use ``argmax``/``gather`` (fewer kernel launches).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torchrl.data import Bounded, Composite
from torchrl.envs import TensorDictPrimer

from taskvar_torch import keys
from taskvar_torch.heads.bundle import HEAD_OUT_KEYS, Heads
from taskvar_torch.subtasks.base import Subtasks

Tensor = torch.Tensor

LARGE_BATCH = 256
"""From this batch size on, the kernels use elementwise loops over the small dimensions."""
_LOOP_MAX = 16  # loop over at most this many options/actions; beyond, reductions are fine


def argmax_last(x: Tensor) -> Tensor:
    """``argmax`` over the last dim (lowest index on ties, as ``torch.argmax``), batched.

    Large batches loop elementwise over the (small) last dimension: ~10x faster on CPU than a
    reduction over a dimension of size 2-4.
    """
    n = x.shape[-1]
    if n > _LOOP_MAX or x.numel() < LARGE_BATCH * n:
        return x.argmax(-1)
    best = x[..., 0]
    idx = torch.zeros(best.shape, dtype=torch.int64, device=x.device)
    for k in range(1, n):
        xk = x[..., k]
        better = xk > best  # strict: the first maximum wins
        idx.masked_fill_(better, k)
        if k + 1 < n:
            best = torch.maximum(best, xk)
    return idx


def max_last(x: Tensor) -> Tensor:
    """``max`` over the last dim (values only), batched like :func:`argmax_last`."""
    n = x.shape[-1]
    if n > _LOOP_MAX or x.numel() < LARGE_BATCH * n:
        return x.amax(-1)
    best = x[..., 0]
    for k in range(1, n):
        best = torch.maximum(best, x[..., k])
    return best


def take_row(x: Tensor, index: Tensor) -> Tensor:
    """``x[b, index[b], ...]`` for ``x (B, K, ...)`` and ``index (B,)`` in ``[0, K)``."""
    B, K = x.shape[0], x.shape[1]
    if K <= _LOOP_MAX and B >= LARGE_BATCH:
        out = x[:, 0]
        for k in range(1, K):
            mask = (index == k).view(B, *([1] * (x.dim() - 2)))
            out = torch.where(mask, x[:, k], out)
        return out
    idx = index.view(B, 1, *([1] * (x.dim() - 2))).expand(B, 1, *x.shape[2:])
    return x.gather(1, idx).squeeze(1)


def sample_categorical(probs: Tensor, u: Tensor) -> Tensor:
    """Index ``k`` with ``cdf[k-1] <= u < cdf[k]`` for ``probs (B, K)`` and uniforms ``u (B,)``."""
    cdf = probs.cumsum(-1)  # (B, K)
    k = (cdf <= u.unsqueeze(-1).to(cdf.dtype)).sum(-1)
    return k.clamp(max=probs.shape[-1] - 1)


class Controller(TensorDictModuleBase):
    """Base class: a batched controller over a :class:`Heads` bundle (paper §3.3-3.4, SPEC §3).

    Subclasses set ``name``, ``required_heads`` and implement :meth:`decide` (pure tensors).

    Args:
        heads: the head bundle (networks or the oracle's tables).
        subtasks: options' termination ``beta(s)`` (``Subtasks.termination``); ``None``: options
            run until the episode ends (the windy exits terminate only there).
        seed: seed of the controller's own ``torch.Generator`` (softmax mu_bar draws only).
    """

    name: str = "controller"
    required_heads: tuple[str, ...] = ()
    trace_keys: tuple[str, ...] = ()
    stateful: bool = True

    def __init__(self, heads: Heads, subtasks: Subtasks | None = None, seed: int = 0):
        super().__init__()
        missing = [h for h in self.required_heads if not heads.has(h)]
        if missing:
            raise ValueError(
                f"controller {self.name!r} needs head(s) {missing}; the bundle has {list(heads.heads)}"
            )
        self.heads = heads
        self.subtasks = subtasks
        self.num_options = len(heads.option_names)
        self.seed = int(seed)
        self._generators: dict[torch.device, torch.Generator] = {}
        in_keys: list[Any] = []
        for h in self.required_heads:
            for k in heads.heads[h].in_keys:
                if k not in in_keys:
                    in_keys.append(k)
        if self.stateful:
            in_keys.append(keys.RUNNING_OPTION)
        if subtasks is not None and self.stateful and keys.CELL not in in_keys:
            in_keys.append(keys.CELL)
        self.in_keys = in_keys
        out = [keys.ACTION, *self.trace_keys]
        if self.stateful:
            out.append((keys.NEXT, keys.RUNNING_OPTION))
        self.out_keys = [*(HEAD_OUT_KEYS[h] for h in self.required_heads), *out]

    # ---- state -------------------------------------------------------------------------------

    def primer(self) -> TensorDictPrimer:
        """The ``TensorDictPrimer`` for ``running_option`` (-1 at every (partial) reset).

        Use it as ``TransformedEnv(env, controller.primer())``; every controller installs the same
        key, so one transformed env serves all four.
        """
        spec = Bounded(-1, max(self.num_options - 1, 0), shape=(), dtype=torch.int64)
        return TensorDictPrimer(
            Composite({keys.RUNNING_OPTION: spec}), default_value=-1, expand_specs=True
        )

    env_transform = primer

    def make_tensordict_primer(self) -> TensorDictPrimer:
        """TorchRL's hook (as ``LSTMModule``): lets ``get_primers_from_module`` and
        ``Collector(..., auto_register_policy_transforms=True)`` find :meth:`primer`."""
        return self.primer()

    def initial_state(self, batch_size: int, device: torch.device | str = "cpu") -> Tensor:
        """``running_option`` of a fresh episode: ``(B,)`` of -1."""
        return torch.full((batch_size,), -1, dtype=torch.int64, device=device)

    def generator(self, device: torch.device) -> torch.Generator:
        """The controller's own random stream on ``device`` (seeded with ``seed``)."""
        g = self._generators.get(device)
        if g is None:
            g = torch.Generator(device=device)
            g.manual_seed(self.seed)
            self._generators[device] = g
        return g

    # ---- decisions -----------------------------------------------------------------------------

    def decide(
        self, values: Mapping[str, Tensor], running: Tensor, terminated: Tensor | None
    ) -> dict[str, Tensor]:
        """Pure batched decision from head outputs ``values`` (by out key) and ``running (B,)``.

        Returns ``{"action", "option", ...traces}``; ``option`` is the next ``running_option``.
        """
        raise NotImplementedError

    def _terminated(self, td: TensorDictBase, running: Tensor) -> Tensor | None:
        """``beta_{o_run}(s_t)`` ``(B,)`` bool from ``subtasks`` (None without subtasks)."""
        if self.subtasks is None:
            return None
        beta = self.subtasks.termination(td)  # (B, O)
        return take_row(beta, running.clamp(min=0))

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        for h in self.required_heads:
            td = self.heads.heads[h](td)
        values = {HEAD_OUT_KEYS[h]: td.get(HEAD_OUT_KEYS[h]) for h in self.required_heads}
        running = None
        if self.stateful:
            running = td.get(keys.RUNNING_OPTION, None)
            if running is None:
                raise KeyError(
                    f"controller {self.name!r}: the tensordict has no {keys.RUNNING_OPTION!r}; add "
                    "the controller's primer to the env: TransformedEnv(env, controller.primer())"
                )
        terminated = self._terminated(td, running) if running is not None else None
        out = self.decide(values, running, terminated)
        td.set(keys.ACTION, out["action"])
        for k in self.trace_keys:
            td.set(k, out[k])
        if self.stateful:
            td.set((keys.NEXT, keys.RUNNING_OPTION), out["option"])
        return td

    # ---- fast path (no TensorDict) ------------------------------------------------------------

    def head_values(self, inputs: Mapping[Any, Tensor]) -> dict[str, Tensor]:
        """Head outputs from plain input tensors, calling each head's inner module directly."""
        values = {}
        for h in self.required_heads:
            m = self.heads.heads[h]
            out_key = HEAD_OUT_KEYS[h]
            if isinstance(m, TensorDictModule) and len(m.out_keys) == 1:
                values[out_key] = m.module(*(inputs[k] for k in m.in_keys))
            else:  # a generic TensorDict head
                B = next(iter(inputs.values())).shape[0]
                values[out_key] = m(TensorDict(dict(inputs), batch_size=[B])).get(out_key)
        return values

    def act(self, inputs: Mapping[Any, Tensor], running: Tensor | None = None) -> dict[str, Tensor]:
        """One decision without TensorDicts: ``inputs`` maps head in-keys to ``(B, ...)`` tensors.

        Termination comes from ``subtasks`` only if given (then ``inputs`` needs ``cell``).
        """
        values = self.head_values(inputs)
        terminated = None
        if self.subtasks is not None and running is not None:
            B = running.shape[0]
            td = TensorDict(dict(inputs), batch_size=[B])
            terminated = self._terminated(td, running)
        return self.decide(values, running, terminated)


class GymnasiumPolicy:
    """Drive a controller on one Gymnasium env (``gymnasium.make("taskvar/WindyGrid-v0")``).

    ``reset()`` at each episode start, then ``action = policy(obs, info)``. The carried state and
    the last decision traces are kept in ``self.state`` / ``self.trace``.

    Args:
        controller: any :class:`Controller`.
        width: grid width, to turn ``info["cell"] = (row, col)`` into the flat ``cell`` index heads
            and subtasks may read (``None``: no ``cell`` input).
    """

    def __init__(self, controller: Controller, width: int | None = None):
        self.controller = controller
        self.width = width
        self.state = controller.initial_state(1)
        self.trace: dict[str, Tensor] = {}

    def reset(self) -> None:
        self.state = self.controller.initial_state(1)

    @torch.inference_mode()
    def __call__(self, obs: Any, info: Mapping[str, Any] | None = None) -> int:
        inputs: dict[Any, Tensor] = {keys.OBSERVATION: torch.as_tensor(obs).reshape(1, -1)}
        if self.width is not None and info is not None and "cell" in info:
            r, c = info["cell"]
            inputs[keys.CELL] = torch.tensor([int(r) * self.width + int(c)])
        out = self.controller.act(inputs, self.state if self.controller.stateful else None)
        if self.controller.stateful:
            self.state = out["option"]
        self.trace = out
        return int(out["action"][0])
