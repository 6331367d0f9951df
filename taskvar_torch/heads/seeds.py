"""Seeds as a batch dimension: ``S`` independent training runs' heads as one bundle (docs/seeds.md).

:func:`stack_seeds` concatenates ``S`` runs' :class:`~taskvar_torch.heads.networks.StackedMLP` s
seed-major (``seeds = S``), so every pass reads its rows as ``S`` groups, each through its own run's
weights, and one optimiser step on the summed losses is ``S`` independent steps. :func:`split_seed`
cuts run ``s`` back out; :func:`load_seed` copies one back in.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence

import torch
from torch import nn

from taskvar_torch.heads.bundle import Heads
from taskvar_torch.heads.max_value import OptimismGapHead
from taskvar_torch.heads.networks import ACTIVATIONS, StackedHead, StackedMLP, head_network


def _stacks(heads: Heads) -> list[StackedMLP]:
    """The :class:`StackedMLP` s of a bundle's heads, each once (in head order)."""
    seen: dict[int, StackedMLP] = {}
    for module in heads.modules():
        if isinstance(module, StackedMLP):
            seen.setdefault(id(module), module)
    return list(seen.values())


def _loose(heads: Heads) -> list[tuple[nn.Module, str]]:
    """The plain MLPs of a bundle outside its stack, as ``(owner, attribute)``: the instance
    estimator's critic inside the max-value head."""
    out = []
    if heads.has("max_value"):
        net = head_network(heads.heads["max_value"])
        if isinstance(net, OptimismGapHead) and net.critic is not None:
            out.append((net, "critic"))
    return out


def _linears(mlp: nn.Module) -> list[nn.Linear]:
    return [m for m in mlp.modules() if isinstance(m, nn.Linear)]


def _activation(mlp: nn.Module) -> str:
    """The activation name of a plain MLP (its first non-linear layer)."""
    for m in mlp.modules():
        for name, cls in ACTIVATIONS.items():
            if type(m) is cls:
                return name
    raise ValueError(f"no known activation in {type(mlp).__name__}")


def _seeded_critic(critics: Sequence[nn.Module]) -> StackedHead:
    """``S`` plain MLP critics ``(..., D + F) -> (..., O)`` as one member of a ``seeds = S`` stack."""
    layers = [_linears(c) for c in critics]
    first = layers[0]
    stack = StackedMLP(
        first[0].in_features,
        [first[-1].out_features],
        hidden=[lin.out_features for lin in first[:-1]],
        activation=_activation(critics[0]),
    ).to(first[0].weight.device)
    with torch.no_grad():
        for i in range(len(first)):
            stack.weights[i] = nn.Parameter(torch.stack([ls[i].weight.t() for ls in layers]))
            stack.biases[i] = nn.Parameter(torch.stack([ls[i].bias.unsqueeze(0) for ls in layers]))
    stack.seeds = len(critics)
    return StackedHead(stack, 0, (first[-1].out_features,))


def stack_seeds(bundles: Sequence[Heads]) -> Heads:
    """One bundle running ``S = len(bundles)`` independent runs' heads (same config) at once.

    Raises:
        ValueError: heads not stored in one :class:`StackedMLP` (``heads.network=conv``), or bundles
            of different shapes.
    """
    if not bundles:
        raise ValueError("stack_seeds needs at least one bundle")
    out = copy.deepcopy(bundles[0])  # the module tree once: shared stacks stay shared
    if len(bundles) == 1:
        return out
    per_run = [_stacks(b) for b in bundles]
    targets = _stacks(out)
    if any(type(st) is not StackedMLP for st in targets):
        raise ValueError(
            "train.seeds > 1 needs heads.network=mlp (the conv trunk has no seed axis yet)"
        )
    with torch.no_grad():
        for j, stack in enumerate(targets):
            runs = [stacks[j] for stacks in per_run]
            for i in range(len(stack.weights)):
                stack.weights[i] = nn.Parameter(torch.cat([r.weights[i] for r in runs]))
                stack.biases[i] = nn.Parameter(torch.cat([r.biases[i] for r in runs]))
            stack.seeds = len(bundles)
    per_bundle = [_loose(b) for b in bundles]
    for j, (owner, attr) in enumerate(_loose(out)):
        setattr(owner, attr, _seeded_critic([getattr(*loose[j]) for loose in per_bundle]))
    stacked = {id(p) for st in _stacks(out) for p in st.parameters()}
    loose = [n for n, p in out.named_parameters() if id(p) not in stacked]
    if loose:
        raise ValueError(f"train.seeds > 1: parameters outside a stacked network: {loose[:3]}")
    out.seeds = len(bundles)
    return out


def split_seed(batch: Heads, s: int, template: Heads) -> Heads:
    """Run ``s`` of a :func:`stack_seeds` bundle, copied into ``template`` (a fresh single-seed
    bundle of the same config, e.g. ``build_heads``), which is returned."""
    S = int(getattr(batch, "seeds", 1))
    if not 0 <= s < S:
        raise ValueError(f"seed index must be in [0, {S}), got {s}")
    with torch.no_grad():
        for src, dst in zip(_stacks_without_critic(batch), _stacks(template)):
            for i in range(len(dst.weights)):
                dst.weights[i].copy_(src.weights[i].view(S, -1, *src.weights[i].shape[1:])[s])
                dst.biases[i].copy_(src.biases[i].view(S, -1, *src.biases[i].shape[1:])[s])
        for (owner, attr), (src_owner, src_attr) in zip(_loose(template), _loose(batch)):
            seeded = getattr(src_owner, src_attr).stack
            for i, lin in enumerate(_linears(getattr(owner, attr))):
                lin.weight.copy_(seeded.weights[i][s].t())
                lin.bias.copy_(seeded.biases[i][s, 0])
    return template


def load_seed(batch: Heads, s: int, run: Heads) -> Heads:
    """Copy ``run``'s weights (a single-seed bundle) into run ``s`` of ``batch`` in place; returns
    ``batch``.
    """
    S = int(getattr(batch, "seeds", 1))
    if not 0 <= s < S:
        raise ValueError(f"seed index must be in [0, {S}), got {s}")
    with torch.no_grad():
        for dst, src in zip(_stacks_without_critic(batch), _stacks(run)):
            for i in range(len(src.weights)):
                dst.weights[i].view(S, -1, *dst.weights[i].shape[1:])[s].copy_(src.weights[i])
                dst.biases[i].view(S, -1, *dst.biases[i].shape[1:])[s].copy_(src.biases[i])
        for (owner, attr), (dst_owner, dst_attr) in zip(_loose(run), _loose(batch)):
            seeded = getattr(dst_owner, dst_attr).stack
            for i, lin in enumerate(_linears(getattr(owner, attr))):
                seeded.weights[i][s].copy_(lin.weight.t())
                seeded.biases[i][s, 0].copy_(lin.bias)
    return batch


def _stacks_without_critic(heads: Heads) -> list[StackedMLP]:
    """:func:`_stacks` minus the seeded one-member stacks of the loose MLPs (:func:`_loose`;
    plain MLPs when unseeded)."""
    loose = [getattr(owner, attr) for owner, attr in _loose(heads)]
    skip = {id(m.stack) for m in loose if isinstance(m, StackedHead)}
    return [st for st in _stacks(heads) if id(st) not in skip]


def num_seeds(heads: Heads) -> int:
    """How many runs a bundle holds (1 unless made by :func:`stack_seeds`)."""
    return int(getattr(heads, "seeds", 1))


__all__ = ["load_seed", "num_seeds", "split_seed", "stack_seeds"]
