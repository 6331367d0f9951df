"""Network builders for the heads (SPEC §2: "network shapes are config").

Every head is a TorchRL :class:`~torchrl.modules.MLP` over the observation vector, wrapped in a
``TensorDictModule`` with the key and output shape of DESIGN.md. Sizes come from
:class:`taskvar_torch.config.HeadsConfig` (``hidden`` widths and ``activation``).

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


@torch.no_grad()
def init_output_bias(head: nn.Module, value: float) -> None:
    """Set the output bias of a head's MLP to ``value`` (e.g. a pessimistic initial value)."""
    last = [m for m in head_network(head).modules() if isinstance(m, nn.Linear)][-1]
    last.bias.fill_(value)
