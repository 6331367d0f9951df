"""Shared machinery of the controllers (paper §3.3-3.4): carried state, primer, kernels.

A controller is a ``TensorDictModuleBase`` that runs its heads, reads its carried state
``running_option (B,)`` int64 (-1 = none), decides, and writes ``action``, the traces
(``option``, ``interrupted``, ``hierarchy_level``) and ``("next", "running_option")``, like a
recurrent TorchRL module; :meth:`Controller.primer` resets that state on (partial) resets.

Each rule has one batched kernel (``decide_of``) over *option-first* tensors ``Q_mu (O, B)``,
``Q_o (O, A, B)`` that loops over the small option/action dimension with elementwise ops (a
reduction over a dimension of size 2-4 is 10-100x slower on CPU), and one scalar path for one
environment (:meth:`Controller.act_one`), tested equal to it (tests/test_decision_forms.py;
docs/benchmarks.md). docs/design.md#controllers.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torch import nn
from torchrl.data import Bounded, Composite
from torchrl.envs import TensorDictPrimer

from taskvar_torch import keys
from taskvar_torch.heads.bundle import HEAD_OUT_KEYS, Heads, with_given_policies
from taskvar_torch.subtasks.base import Hierarchy, Subtasks

Tensor = torch.Tensor

_LOOP_MAX = 16  # loop elementwise over at most this many options/actions; beyond, reduce


# ---- option-first kernels ---------------------------------------------------------------------


def argmax0(x: Tensor) -> Tensor:
    """``argmax`` over dim 0 of ``x (K, ...)``, the lowest index on ties (as ``torch.argmax``).

    A tournament of elementwise comparisons over the trailing (batch) dims, not a reduction.
    """
    K = x.shape[0]
    if K > _LOOP_MAX:
        return x.movedim(0, -1).argmax(-1)
    if K == 1:
        return torch.zeros(x.shape[1:], dtype=torch.int64, device=x.device)
    vals = [x[k] for k in range(K)]
    idx: list[Tensor | int] = list(range(K))
    while len(vals) > 1:
        last = len(vals) == 2
        nv, ni = [], []
        for j in range(0, len(vals) - 1, 2):
            right = vals[j + 1] > vals[j]  # strict: ties keep the left (lower) index
            if not last:
                nv.append(torch.maximum(vals[j], vals[j + 1]))
            ni.append(_pick(right, idx[j + 1], idx[j]))
        if len(vals) % 2:
            nv.append(vals[-1])
            ni.append(idx[-1])
        vals, idx = nv, ni
    out = idx[0]
    assert isinstance(out, Tensor)
    return out.to(torch.int64)


def _pick(cond: Tensor, a: Tensor | int, b: Tensor | int) -> Tensor:
    """``where(cond, a, b)`` as uint8 indices; cheap when ``a == b + 1`` are Python ints."""
    if isinstance(a, int) and isinstance(b, int):  # leaf pairs are consecutive: (b, b + 1)
        c = cond.to(torch.uint8)
        c = c if a - b == 1 else c * (a - b)
        return c + b if b else c
    return torch.where(cond, a, b)  # a Python int operand keeps the tensor's uint8 dtype


def max0(x: Tensor) -> Tensor:
    """``max`` over dim 0 of ``x (K, ...)`` (values)."""
    return x.amax(0)


def select0(x: Tensor, index: Tensor) -> Tensor:
    """``out[..., b] = x[index[b], ..., b]`` for ``x (K, ..., B)`` and ``index (B,)`` in ``[0, K)``."""
    K = x.shape[0]
    if K > 2 and (x.dim() > 2 or K > 4):  # measured: one gather beats K-1 masked selects here
        idx = index.view(1, *([1] * (x.dim() - 2)), -1).expand(1, *x.shape[1:])
        return x.gather(0, idx).squeeze(0)
    out = x[0]
    for k in range(1, K):
        out = torch.where(index == k, x[k], out)  # (B,) mask broadcasts over the middle dims
    return out


def lookup(table: Tensor, index: Tensor) -> Tensor:
    """``table[index]`` for a small 1-d table."""
    return table.index_select(0, index)


def option_first(x: Tensor) -> Tensor:
    """A ``(B, O[, A])`` head output as an option-first view ``(O[, A], B)`` (no copy)."""
    return x.movedim(0, -1)


def any0(mask: Tensor) -> Tensor:
    """``any`` over dim 0 of a bool ``mask (K, ...)``, elementwise over the batch (as :func:`argmax0`)."""
    K = mask.shape[0]
    if K > _LOOP_MAX:
        return mask.any(0)
    out = mask[0]
    for k in range(1, K):
        out = out | mask[k]
    return out


def last_true0(mask: Tensor) -> Tensor:
    """The highest ``k`` with ``mask[k]`` over dim 0 of a bool ``mask (K, B)`` (0 where none)."""
    K = mask.shape[0]
    if K > _LOOP_MAX:
        ks = torch.arange(K, device=mask.device).view(K, *([1] * (mask.dim() - 1)))
        return (mask * ks).amax(0)
    out = torch.zeros(mask.shape[1:], dtype=torch.int64, device=mask.device)
    for k in range(1, K):
        out = torch.where(mask[k], k, out)
    return out


def sample_categorical(probs: Tensor, u: Tensor, allowed: Tensor | None = None) -> Tensor:
    """Index ``k`` with ``cdf[k-1] <= u < cdf[k]`` for ``probs (K, B)`` and uniforms ``u (B,)``.

    A ``u`` past the rounded total returns the last (allowed, given ``allowed (K, B)``) index.
    """
    cdf = probs.cumsum(0)  # (K, B)
    k = (cdf <= u.to(cdf.dtype)).sum(0)
    if allowed is None:
        return k.clamp(max=probs.shape[0] - 1)
    return torch.minimum(k, last_true0(allowed))


def defines_initiation(subtasks: Subtasks | None) -> bool:
    """Whether ``subtasks`` define initiation sets (override :meth:`Subtasks.initiation` and do not
    declare ``initiable_everywhere``).
    """
    return (
        subtasks is not None
        and not subtasks.initiable_everywhere
        and type(subtasks).initiation is not Subtasks.initiation
    )


def first_argmax_where(values: Sequence[float], allowed: Sequence[bool] | None) -> int:
    """Python-scalar argmax over the ``allowed`` entries, the lowest index on ties; -1 if none."""
    if allowed is None:
        return first_argmax(values)
    idx = -1
    for k, ok in enumerate(allowed):
        if ok and (idx < 0 or values[k] > values[idx]):
            idx = k
    return idx


ROOT_POLICIES = ("averaging", "option")  # the composed root's pi: greedy in Q_avg, or its own head


def with_root_policy(q_opt: Tensor, q_avg: Tensor, root: int) -> Tensor:
    """``q_opt`` ``(O, A, B)`` with the root's row replaced by ``Q_avg`` ``(A, B)``: pi^root = pi^avg."""
    return torch.cat([q_opt[:root], q_avg.unsqueeze(0), q_opt[root + 1 :]])


def first_argmax(values: Sequence[float]) -> int:
    """Python-scalar argmax, the lowest index on ties."""
    best, idx = values[0], 0
    for k in range(1, len(values)):
        if values[k] > best:
            best, idx = values[k], k
    return idx


# ---- fused heads for one-environment latency -----------------------------------------------------

_INPLACE_ACT: dict[type, Any] = {
    nn.ReLU: torch.relu_,
    nn.Tanh: torch.tanh_,
    nn.ELU: nn.functional.elu_,
    nn.SiLU: lambda x: nn.functional.silu(x, inplace=True),
}


class FusedHeads(nn.Module):
    """Several MLP heads over one input as a single block-structured MLP (inference fast path).

    Layer 1 stacks the heads' first layers, deeper layers are block-diagonal, the output
    concatenates the heads' flattened outputs. ``heads``: ``TensorDictModule`` heads over
    ``nn.Sequential`` MLPs of the same structure with one common in-key.
    """

    def __init__(self, heads: Sequence[TensorDictModule]):
        super().__init__()
        mlps = [h.module for h in heads]
        self.in_key = heads[0].in_keys[0]
        self.out_keys = [h.out_keys[0] for h in heads]
        kinds = [[type(m) for m in mlp] for mlp in mlps]
        linears = [[m for m in mlp if isinstance(m, nn.Linear)] for mlp in mlps]
        d_in = linears[0][0].in_features
        self.out_shapes = [tuple(mlp(torch.zeros(1, d_in)).shape[1:]) for mlp in mlps]
        layers: list[nn.Module] = []
        n_lin = len(linears[0])
        li = 0
        for mod in mlps[0]:
            if not isinstance(mod, nn.Linear):
                layers.append(mod)
                continue
            ws = [lin[li] for lin in linears]
            if li == 0:
                weight = torch.cat([w.weight for w in ws], 0)
            else:
                weight = torch.block_diag(*[w.weight for w in ws])
            bias = torch.cat([w.bias for w in ws])
            fused = nn.Linear(weight.shape[1], weight.shape[0])
            with torch.no_grad():
                fused.weight.copy_(weight)
                fused.bias.copy_(bias)
            layers.append(fused)
            li += 1
        assert li == n_lin and all(k == kinds[0] for k in kinds)
        self.net = nn.Sequential(*layers)
        self.sizes = [math.prod(s) for s in self.out_shapes]
        # the forward as a flat list of functional calls (no nn.Module dispatch per layer)
        self._steps: list[tuple[str, Any]] = []
        for layer in layers:
            if isinstance(layer, nn.Linear):
                self._steps.append(("linear", layer))
            else:
                self._steps.append(("act", _INPLACE_ACT.get(type(layer), layer)))

    @staticmethod
    def supports(heads: Sequence[nn.Module]) -> bool:
        """Whether ``heads`` can be fused (same in-key, same MLP structure, plain layers)."""
        if not heads or not all(isinstance(h, TensorDictModule) for h in heads):
            return False
        if len({tuple(h.in_keys) for h in heads}) != 1 or len(heads[0].in_keys) != 1:
            return False
        structures = []
        for h in heads:
            m = h.module
            if not isinstance(m, nn.Sequential) or len(h.out_keys) != 1:
                return False
            for layer in m:
                if not isinstance(layer, nn.Linear) and any(True for _ in layer.parameters()):
                    return False
            structures.append(tuple(type(x) for x in m))
        return len(set(structures)) == 1

    def forward(self, x: Tensor) -> Tensor:  # (B, D) -> (B, sum of head output sizes)
        for kind, f in self._steps:
            x = nn.functional.linear(x, f.weight, f.bias) if kind == "linear" else f(x)
        return x

    def split(self, y: Tensor) -> dict[str, Tensor]:
        """The fused output ``(B, K)`` as ``{out_key: (B, *shape)}``."""
        parts = y.split(self.sizes, dim=-1)
        return {
            k: p.reshape(y.shape[0], *s) for k, p, s in zip(self.out_keys, parts, self.out_shapes)
        }


# ---- the controller base class ------------------------------------------------------------------


class Controller(TensorDictModuleBase):
    """Base class: a batched controller over a :class:`Heads` bundle (paper §3.3-3.4).

    Subclasses set ``name``, ``required_heads`` and implement :meth:`decide_of` and
    :meth:`decide_scalar`.

    Args:
        heads: the head bundle (networks or the oracle's tables).
        subtasks: options' termination ``beta(s)`` and, for controllers that ``reads_initiation``,
            initiation sets ``I_o`` (where no option is initiable the averaging head acts).
            ``None``: options run until the episode ends and may start anywhere.
        seed: seed of the controller's own ``torch.Generator`` (softmax mu_bar draws only).
        root_policy: the composition hierarchy root's policy: ``"option"`` (its own option head) or
            ``"averaging"`` (the averaging head, paper §3.4.2); no effect without a hierarchy.
        hierarchy: the composition tree whose root ``root_policy`` names (default: the subtasks').
    """

    name: str = "controller"
    required_heads: tuple[str, ...] = ()
    trace_keys: tuple[str, ...] = ()
    stateful: bool = True
    reads_initiation: bool = False  # option picks honour I_o (options, interruption)

    def __init__(
        self,
        heads: Heads,
        subtasks: Subtasks | None = None,
        seed: int = 0,
        root_policy: str = "option",
        hierarchy: Hierarchy | None = None,
    ):
        super().__init__()
        if root_policy not in ROOT_POLICIES:
            raise ValueError(
                f"root_policy must be one of {list(ROOT_POLICIES)}, got {root_policy!r}"
            )
        self.root_policy = root_policy
        tree = hierarchy if hierarchy is not None else getattr(subtasks, "hierarchy", None)
        self.root_index: int | None = None  # the option that acts by the averaging head
        if root_policy == "averaging" and tree is not None and "options" in self.required_heads:
            self.root_index = list(heads.option_names).index(tree.root)
            if "averaging" not in self.required_heads:
                self.required_heads = ("averaging", *self.required_heads)
        # the option controllers with initiation sets: where no option is initiable the averaging
        # policy acts (the fallback of InterruptionController), so they need its head
        self.honours_initiation = self.reads_initiation and defines_initiation(subtasks)
        if self.honours_initiation and "averaging" not in self.required_heads:
            self.required_heads = ("averaging", *self.required_heads)
        missing = [h for h in self.required_heads if not heads.has(h)]
        if missing:
            why = ""
            if self.honours_initiation and "averaging" in missing:
                why = " (the averaging head acts where no option is initiable)"
            raise ValueError(
                f"controller {self.name!r} needs head(s) {missing}{why}; the bundle has "
                f"{list(heads.heads)}"
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
        self._fused: FusedHeads | None = None

    # ---- state -------------------------------------------------------------------------------

    def primer(self) -> TensorDictPrimer:
        """The ``TensorDictPrimer`` for ``running_option`` (-1 at every (partial) reset); use it as
        ``TransformedEnv(env, controller.primer())``.
        """
        spec = Bounded(-1, max(self.num_options - 1, 0), shape=(), dtype=torch.int64)
        return TensorDictPrimer(
            Composite({keys.RUNNING_OPTION: spec}), default_value=-1, expand_specs=True
        )

    def make_tensordict_primer(self) -> TensorDictPrimer:
        """TorchRL's hook (as ``LSTMModule``): lets ``get_primers_from_module`` and
        ``Collector(..., auto_register_policy_transforms=True)`` find :meth:`primer`."""
        return self.primer()

    def generator(self, device: torch.device) -> torch.Generator:
        """The controller's own random stream on ``device`` (seeded with ``seed``)."""
        g = self._generators.get(device)
        if g is None:
            g = torch.Generator(device=device)
            g.manual_seed(self.seed)
            self._generators[device] = g
        return g

    # ---- batched decisions -------------------------------------------------------------------

    def decide_of(
        self, values: Mapping[str, Tensor], running: Tensor | None, terminated: Tensor | None
    ) -> dict[str, Tensor]:
        """Batched decision from *option-first* head outputs (``(O, B)``, ``(O, A, B)``, ``(A, B)``).

        Returns ``{"action", "option", ...traces}`` (each ``(B,)``); ``option`` is the next
        ``running_option``.
        """
        raise NotImplementedError

    def decide(
        self, values: Mapping[str, Tensor], running: Tensor | None, terminated: Tensor | None
    ) -> dict[str, Tensor]:
        """Batched decision from head outputs in the bundle layout (``(B, O)``, ``(B, O, A)``);
        a given-policy option's row of ``Q_o`` is its controller's action (:func:`with_given_policies`)."""
        values = dict(values)
        given = values.pop(keys.GIVEN_ACTION, None)
        if given is not None and keys.OPTION_ACTION_VALUE in values:
            values[keys.OPTION_ACTION_VALUE] = with_given_policies(
                values[keys.OPTION_ACTION_VALUE], given
            )
        of = {k: option_first(v) for k, v in values.items()}
        if self.root_index is not None:  # pi^root = pi^avg (paper §3.4.2)
            of[keys.OPTION_ACTION_VALUE] = with_root_policy(
                of[keys.OPTION_ACTION_VALUE], of[keys.ACTION_VALUE], self.root_index
            )
        return self.decide_of(of, running, terminated)

    def extra_inputs(self, td: TensorDictBase) -> dict[str, Tensor]:
        """Decision inputs besides the heads, batch first, read from ``td`` (the given policies'
        actions; subclasses add theirs).
        """
        given = None if self.subtasks is None else self.subtasks.given_actions(td)
        return {} if given is None else {keys.GIVEN_ACTION: given}

    def _terminated(self, td: TensorDictBase, running: Tensor) -> Tensor | None:
        """``beta_{o_run}(s_t)`` ``(B,)`` bool from ``subtasks`` (None without subtasks)."""
        if self.subtasks is None:
            return None
        beta = self.subtasks.termination(td)  # (B, O)
        return select0(option_first(beta), running.clamp(min=0))

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
        values.update(self.extra_inputs(td))
        out = self.decide(values, running, terminated)
        td.set(keys.ACTION, out["action"])
        for k in self.trace_keys:
            td.set(k, out[k])
        if self.stateful:
            td.set((keys.NEXT, keys.RUNNING_OPTION), out["option"])
        return td

    # ---- fast paths (no TensorDict) ------------------------------------------------------------

    def head_values(self, inputs: Mapping[Any, Tensor]) -> dict[str, Tensor]:
        """Head outputs ``{out_key: (B, ...)}`` from plain input tensors (each head's inner module)."""
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
        """One batched decision without TensorDicts: ``inputs`` maps head in-keys to tensors (and
        ``cell`` when ``subtasks`` are given).
        """
        values = self.head_values(inputs)
        terminated = None
        if self.subtasks is not None and running is not None:
            td = TensorDict(dict(inputs), batch_size=[running.shape[0]])
            terminated = self._terminated(td, running)
            values.update(self.extra_inputs(td))
        return self.decide(values, running, terminated)

    def fuse(self) -> FusedHeads | None:
        """Fuse this controller's heads for :meth:`act_one` (None if not fusable); call again after
        the weights change.
        """
        mods = [self.heads.heads[h] for h in self.required_heads]
        self._fused = FusedHeads(mods) if FusedHeads.supports(mods) else None
        return self._fused

    def decide_scalar(
        self, values: Mapping[str, list], running: int, terminated: bool
    ) -> dict[str, Any]:
        """One environment's decision on Python floats (``values[k]``: nested lists, no batch)."""
        raise NotImplementedError

    def act_one(
        self, inputs: Mapping[Any, Tensor], running: int = -1, terminated: bool = False
    ) -> dict[str, Any]:
        """Real-time decision for one environment: ``inputs`` map in-keys to ``(1, ...)`` tensors.

        Returns Python ints/bools: ``action``, ``option``, traces.
        """
        with torch.inference_mode():
            if self._fused is not None:
                y = self._fused(inputs[self._fused.in_key])[0].tolist()  # one host transfer
                values: dict[str, list] = {}
                start = 0
                for k, n, shape in zip(
                    self._fused.out_keys, self._fused.sizes, self._fused.out_shapes
                ):
                    flat = y[start : start + n]
                    start += n
                    values[k] = _nest(flat, shape)
            else:
                values = {k: v[0].tolist() for k, v in self.head_values(inputs).items()}
            if self.subtasks is not None:
                td = TensorDict(dict(inputs), batch_size=[1])
                values.update({k: v[0].tolist() for k, v in self.extra_inputs(td).items()})
        given = values.pop(keys.GIVEN_ACTION, None)
        if given is not None and keys.OPTION_ACTION_VALUE in values:  # a given controller acts
            low = float(torch.finfo(torch.float32).min)
            values[keys.OPTION_ACTION_VALUE] = [
                row if g < 0 else [v if a == g else low for a, v in enumerate(row)]
                for row, g in zip(values[keys.OPTION_ACTION_VALUE], given)
            ]
        if self.root_index is not None:  # pi^root = pi^avg (paper §3.4.2)
            q = list(values[keys.OPTION_ACTION_VALUE])
            q[self.root_index] = values[keys.ACTION_VALUE]
            values[keys.OPTION_ACTION_VALUE] = q
        return self.decide_scalar(values, running, terminated)


def _nest(flat: list, shape: tuple[int, ...]) -> list:
    """A flat list reshaped to nested lists of ``shape`` (1-d or 2-d)."""
    if len(shape) <= 1:
        return flat
    n = shape[-1]
    return [flat[i : i + n] for i in range(0, len(flat), n)]


class GymnasiumPolicy:
    """Drive a controller on one Gymnasium env: ``reset()`` per episode, then ``policy(obs, info)``.

    Uses :meth:`Controller.act_one`; keeps the carried state and last traces in ``self.state`` and
    ``self.trace``. ``width`` turns ``info["cell"] = (row, col)`` into the flat ``cell`` index heads
    and subtasks may read (``None``: no ``cell`` input).
    """

    def __init__(self, controller: Controller, width: int | None = None):
        self.controller = controller
        self.width = width
        self.state = -1
        self.trace: dict[str, Any] = {}
        controller.fuse()

    def reset(self) -> None:
        self.state = -1

    def __call__(self, obs: Any, info: Mapping[str, Any] | None = None) -> int:
        inputs: dict[Any, Tensor] = {keys.OBSERVATION: torch.as_tensor(obs).reshape(1, -1)}
        if self.width is not None and info is not None and "cell" in info:
            r, c = info["cell"]
            inputs[keys.CELL] = torch.tensor([int(r) * self.width + int(c)])
        terminated = False
        ctrl = self.controller
        if ctrl.subtasks is not None and ctrl.stateful and self.state >= 0:
            td = TensorDict(inputs, batch_size=[1])
            terminated = bool(ctrl.subtasks.termination(td)[0, self.state])
        out = ctrl.act_one(inputs, self.state, terminated)
        if ctrl.stateful:
            self.state = out["option"]
        self.trace = out
        return int(out["action"])
