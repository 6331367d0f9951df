"""Network builders for the heads (SPEC §2: "network shapes are config").

Every head is an MLP over the observation vector, wrapped in a ``TensorDictModule`` with the key
and output shape of DESIGN.md. Sizes come from :class:`taskvar_torch.config.HeadsConfig` (``hidden``
widths and ``activation``). The trainer builds the heads as members of one :class:`StackedMLP`
(independent weights, batched matmuls), so the learner runs every head in one pass;
:func:`make_head` builds a stand-alone TorchRL :class:`~torchrl.modules.MLP` head.

Examples:
    >>> net = make_mlp(25, (2, 4), hidden=(64, 64))
    >>> net(torch.zeros(3, 25)).shape
    torch.Size([3, 2, 4])
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import MLP

from taskvar_torch import keys

ACTIVATIONS: dict[str, type[nn.Module]] = {
    "elu": nn.ELU,
    "gelu": nn.GELU,
    "relu": nn.ReLU,
    "silu": nn.SiLU,
    "tanh": nn.Tanh,
}


def make_mlp(
    in_dim: int,
    out_shape: int | Sequence[int],
    hidden: Sequence[int] = (64, 64),
    activation: str = "relu",
) -> MLP:
    """An MLP ``(B, in_dim) -> (B, *out_shape)``; ``hidden=()`` gives a linear map."""
    if activation not in ACTIVATIONS:
        raise ValueError(f"activation must be one of {sorted(ACTIVATIONS)}, got {activation!r}")
    out = int(out_shape) if isinstance(out_shape, int) else tuple(int(s) for s in out_shape)
    return MLP(
        in_features=int(in_dim),
        out_features=out,
        num_cells=[int(h) for h in hidden],
        activation_class=ACTIVATIONS[activation],
    )


class StackedMLP(nn.Module):
    """K independent MLPs of the same hidden widths, run together with batched matmuls.

    Member ``k`` maps ``(..., in_dim) -> (..., out_sizes[k])``; its weights are slice ``k`` of
    stacked parameters ``weight_i (K, d_in, d_out)``, ``bias_i (K, 1, d_out)``, initialised as
    ``nn.Linear`` (uniform in ``+-1/sqrt(d_in)``). Outputs are padded to ``max(out_sizes)`` columns;
    the padding columns of a member never reach a loss, so they stay untouched.

    :meth:`forward` runs all members on one input ``(M, in_dim) -> (K, M, max_out)`` with one
    matmul per layer (how the learner fuses the heads); :meth:`forward_one` runs one member (how
    a head runs on its own, e.g. in a controller).
    """

    def __init__(
        self,
        in_dim: int,
        out_sizes: Sequence[int],
        hidden: Sequence[int] = (64, 64),
        activation: str = "relu",
    ):
        super().__init__()
        if activation not in ACTIVATIONS:
            raise ValueError(f"activation must be one of {sorted(ACTIVATIONS)}, got {activation!r}")
        self.out_sizes = tuple(int(o) for o in out_sizes)
        K = len(self.out_sizes)
        dims = [int(in_dim), *(int(h) for h in hidden), max(self.out_sizes)]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for d_in, d_out in zip(dims[:-1], dims[1:]):
            bound = 1.0 / d_in**0.5
            self.weights.append(nn.Parameter(torch.empty(K, d_in, d_out).uniform_(-bound, bound)))
            self.biases.append(nn.Parameter(torch.empty(K, 1, d_out).uniform_(-bound, bound)))
        self.activation = ACTIVATIONS[activation]()

    @property
    def num_members(self) -> int:
        return len(self.out_sizes)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """All members: ``(M, in_dim) -> (K, M, max_out)``."""
        h = x.unsqueeze(0).expand(self.num_members, *x.shape)  # (K, M, in_dim)
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            h = torch.baddbmm(b, h, w)  # (K, M, d_out)
            if i < last:
                h = self.activation(h)
        return h

    def forward_one(self, x: torch.Tensor, k: int) -> torch.Tensor:
        """Member ``k``: ``(..., in_dim) -> (..., out_sizes[k])``."""
        batch = x.shape[:-1]
        h = x.reshape(-1, x.shape[-1])  # (M, in_dim)
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            h = torch.addmm(b[k], h, w[k])  # (M, d_out)
            if i < last:
                h = self.activation(h)
        return h[:, : self.out_sizes[k]].reshape(*batch, self.out_sizes[k])


class StackedHead(nn.Module):
    """Member ``index`` of a :class:`StackedMLP`, reshaped to ``out_shape`` (a head on its own)."""

    def __init__(self, stack: StackedMLP, index: int, out_shape: Sequence[int]):
        super().__init__()
        self.stack = stack
        self.index = int(index)
        self.out_shape = tuple(int(s) for s in out_shape)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.stack.forward_one(x, self.index)  # (..., prod(out_shape))
        return out.reshape(*x.shape[:-1], *self.out_shape)


def make_stacked_heads(
    in_dim: int,
    specs: dict[str, tuple[str, Sequence[int]]],
    hidden: Sequence[int] = (64, 64),
    activation: str = "relu",
    in_key: str = keys.OBSERVATION,
) -> dict[str, TensorDictModule]:
    """One head per ``name: (out_key, out_shape)``, all members of one :class:`StackedMLP`.

    Each head is a ``TensorDictModule`` with its own key and shape (DESIGN.md), the networks are
    independent (no shared weights), and a learner can run all of them in one pass.
    """
    sizes = [int(torch.Size(shape).numel()) for _, shape in specs.values()]
    stack = StackedMLP(in_dim, sizes, hidden, activation)
    return {
        name: TensorDictModule(StackedHead(stack, k, shape), in_keys=[in_key], out_keys=[out_key])
        for k, (name, (out_key, shape)) in enumerate(specs.items())
    }


def make_head(
    out_key: str,
    in_dim: int,
    out_shape: int | Sequence[int],
    hidden: Sequence[int] = (64, 64),
    activation: str = "relu",
    in_key: str = keys.OBSERVATION,
) -> TensorDictModule:
    """A head: ``TensorDictModule(MLP, in_keys=[observation], out_keys=[out_key])``."""
    return TensorDictModule(
        make_mlp(in_dim, out_shape, hidden, activation), in_keys=[in_key], out_keys=[out_key]
    )


def head_network(head: nn.Module) -> nn.Module:
    """The plain ``nn.Module`` inside a head (``TensorDictModule.module``), for fused learners."""
    return head.module if isinstance(head, TensorDictModule) else head
