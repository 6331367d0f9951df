"""Network builders for the heads (sizes from :class:`taskvar_torch.config.HeadsConfig`).

Every head is an MLP over the observation in a ``TensorDictModule`` with the keys and shapes of
docs/design.md#the-heads-interface. The trainer builds the heads as members of one
:class:`StackedMLP` (independent weights, batched matmuls); ``heads.network=conv`` puts a per-head
conv trunk in front (:class:`StackedConvMLP`); :func:`make_head` builds a stand-alone TorchRL
:class:`~torchrl.modules.MLP` head.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import MLP

from taskvar_torch import keys
from taskvar_torch.contract import PatchLayout

ACTIVATIONS: dict[str, type[nn.Module]] = {
    "elu": nn.ELU,
    "gelu": nn.GELU,
    "relu": nn.ReLU,
    "silu": nn.SiLU,
    "tanh": nn.Tanh,
}
NETWORKS = ("mlp", "conv")


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

    Member ``k`` maps ``(..., in_dim) -> (..., out_sizes[k])`` with weights ``weight_i[k]`` of ``(K,
    d_in, d_out)`` (``nn.Linear`` init); outputs are padded to ``max(out_sizes)`` columns.
    :meth:`forward` runs all members ``(M, in_dim) -> (K, M, max_out)``, :meth:`forward_one` one
    member, :meth:`forward_snapshots` ``G`` frozen weight copies on ``G`` row groups.

    ``input_mask (K, in_dim)`` (0/1, a non-persistent buffer) multiplies member ``k``'s input by row
    ``k`` (``heads.option_inputs=subtask``). ``seeds`` ``S``
    (:func:`taskvar_torch.heads.seeds.stack_seeds`) holds ``S`` seed-major copies of the ``K``
    members; rows are read as ``S`` equal groups, group ``s`` through copy ``s``.
    """

    seeds: int = 1

    def __init__(
        self,
        in_dim: int,
        out_sizes: Sequence[int],
        hidden: Sequence[int] = (64, 64),
        activation: str = "relu",
        input_mask: torch.Tensor | None = None,
    ):
        super().__init__()
        if activation not in ACTIVATIONS:
            raise ValueError(f"activation must be one of {sorted(ACTIVATIONS)}, got {activation!r}")
        self.out_sizes = tuple(int(o) for o in out_sizes)
        K = len(self.out_sizes)
        if input_mask is not None and tuple(input_mask.shape) != (K, int(in_dim)):
            raise ValueError(
                f"input_mask must have shape ({K}, {int(in_dim)}), got {tuple(input_mask.shape)}"
            )
        mask = None if input_mask is None else input_mask.to(torch.float32)
        self.register_buffer("input_mask", mask, persistent=False)
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

    def member_inputs(
        self, x: torch.Tensor, members: tuple[int, int] | None = None
    ) -> torch.Tensor:
        """Every member's input: ``(..., in_dim) -> (K, ..., in_dim)`` (masked if ``input_mask``);
        ``members=(lo, hi)``: members ``lo .. hi - 1`` only, ``(hi - lo, ..., in_dim)``."""
        lo, hi = members or (0, self.num_members)
        h = x.unsqueeze(0).expand(hi - lo, *x.shape)
        if self.input_mask is None:
            return h
        return h * self.input_mask[lo:hi].view(hi - lo, *(1,) * (x.dim() - 1), x.shape[-1])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """All members: ``(M, in_dim) -> (K, M, max_out)`` (``seeds = S``: rows in ``S``
        seed-major groups, each through its own copy)."""
        if self.seeds > 1:
            out = self.forward_snapshots(x)  # (S, K, M / S, max_out)
            return out.transpose(0, 1).reshape(self.num_members, x.shape[0], out.shape[-1])
        return self._layers(self.member_inputs(x))

    def _layers(self, h: torch.Tensor) -> torch.Tensor:
        """The stacked layers on per-member inputs: ``(K, M, in_dim) -> (K, M, max_out)``."""
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            h = torch.baddbmm(b, h, w)  # (K, M, d_out)
            if i < last:
                h = self.activation(h)
        return h

    def forward_one(self, x: torch.Tensor, k: int) -> torch.Tensor:
        """Member ``k``: ``(..., in_dim) -> (..., out_sizes[k])``."""
        batch = x.shape[:-1]
        if self.seeds > 1:  # (S, 1, M / S, max_out): each seed's rows through its own member k
            out = self.forward_snapshots(x.reshape(-1, x.shape[-1]), members=(k, k + 1))
            out = out.reshape(-1, out.shape[-1])
            return out[:, : self.out_sizes[k]].reshape(*batch, self.out_sizes[k])
        if self.input_mask is not None:
            x = x * self.input_mask[k]
        out = self._layers_one(x.reshape(-1, x.shape[-1]), k)  # (M, max_out)
        return out[:, : self.out_sizes[k]].reshape(*batch, self.out_sizes[k])

    def _layers_one(self, h: torch.Tensor, k: int) -> torch.Tensor:
        """Member ``k``'s layers: ``(M, in_dim) -> (M, max_out)``."""
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            h = torch.addmm(b[k], h, w[k])  # (M, d_out)
            if i < last:
                h = self.activation(h)
        return h

    def snapshot(self) -> list[torch.Tensor]:
        """A frozen copy of the parameters for :meth:`forward_snapshots`: ``[weight_0, ..., bias_0,
        ...]``.
        """
        return [p.detach().clone() for p in (*self.weights, *self.biases)]

    def forward_snapshots(
        self,
        x: torch.Tensor,
        params: Sequence[torch.Tensor] | None = None,
        members: tuple[int, int] | None = None,
    ) -> torch.Tensor:
        """:meth:`forward` of ``G`` weight copies on ``G`` row groups: ``(B, in_dim) -> (G, K, B /
        G, max_out)``; ``members=(lo, hi)`` runs those members only.

        ``params``: ``G`` :meth:`snapshot` s stacked along a new first dim; rows ``[g R, (g + 1)
        R)`` run through copy ``g``. ``None``: the live weights (a stack of ``S`` seeds runs them as
        ``G = S``).
        """
        n = len(self.weights)
        lo, hi = members or (0, self.num_members)
        K = hi - lo
        if params is None:
            S = self.seeds  # (S, K, d_in, d_out), (S, K, 1, d_out): seed-major members
            ws = [w.view(S, -1, *w.shape[1:]) for w in self.weights]
            bs = [b.view(S, -1, *b.shape[1:]) for b in self.biases]
        elif self.seeds > 1:
            raise ValueError("a stack of several seeds runs its own weights only (params=None)")
        else:
            ws, bs = list(params[:n]), list(params[n:])  # (G, K, d_in, d_out), (G, K, 1, d_out)
        if K != self.num_members:
            ws, bs = [w[:, lo:hi] for w in ws], [b[:, lo:hi] for b in bs]
        G = ws[0].shape[0]
        R = x.shape[0] // G
        h = self.member_inputs(x.view(G, R, -1), (lo, hi)).transpose(0, 1).reshape(G * K, R, -1)
        for i, (w, b) in enumerate(zip(ws, bs)):
            h = torch.baddbmm(b.reshape(G * K, 1, -1), h, w.reshape(G * K, *w.shape[2:]))
            if i < n - 1:
                h = self.activation(h)
        return h.view(G, K, R, -1)


class StackedConvMLP(StackedMLP):
    """K independent conv + MLP networks over a coordinates-plus-patch observation, run together.

    Member ``k`` runs 3x3 convolutions over the patch (:class:`PatchLayout`), appends the
    coordinates and runs its :class:`StackedMLP` member; every member's layer is one grouped
    convolution.
    """

    def __init__(
        self,
        in_dim: int,
        out_sizes: Sequence[int],
        patch: PatchLayout,
        conv_channels: Sequence[int] = (16, 32),
        hidden: Sequence[int] = (64, 64),
        activation: str = "relu",
    ):
        if int(in_dim) != patch.obs_dim:
            raise ValueError(
                f"observation has {in_dim} values but the patch layout {patch} needs {patch.obs_dim}"
            )
        if not conv_channels or min(conv_channels) < 1:
            raise ValueError(f"conv_channels must be >= 1 channels per layer, got {conv_channels}")
        P = patch.size
        super().__init__(
            patch.coords_dim + conv_channels[-1] * P * P, out_sizes, hidden, activation
        )
        self.patch = patch
        K = self.num_members
        self.conv_weights = nn.ParameterList()
        self.conv_biases = nn.ParameterList()
        c_in = patch.channels
        for c_out in (int(c) for c in conv_channels):
            bound = 1.0 / (c_in * 9) ** 0.5  # nn.Conv2d's default init
            w = torch.empty(K, c_out, c_in, 3, 3).uniform_(-bound, bound)
            self.conv_weights.append(nn.Parameter(w))
            self.conv_biases.append(nn.Parameter(torch.empty(K, c_out).uniform_(-bound, bound)))
            c_in = c_out

    def _split(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(M, in_dim)`` -> coordinates ``(M, coords_dim)``, patch ``(M, C * P * P)``."""
        return x[:, : self.patch.coords_dim], x[:, self.patch.coords_dim :]

    def _trunk(self, x: torch.Tensor) -> torch.Tensor:
        """Every member's features: ``(M, in_dim) -> (K, M, coords_dim + c_last * P * P)``."""
        K, M, (C, P) = self.num_members, x.shape[0], (self.patch.channels, self.patch.size)
        coords, patch = self._split(x)
        h = patch.unsqueeze(1).expand(M, K, C * P * P).reshape(M, K * C, P, P)
        for w, b in zip(self.conv_weights, self.conv_biases):  # (K, c_out, c_in, 3, 3), (K, c_out)
            h = self.activation(F.conv2d(h, w.flatten(0, 1), b.flatten(), padding=1, groups=K))
        h = h.reshape(M, K, -1).transpose(0, 1)  # (K, M, c_last * P * P)
        return torch.cat([coords.unsqueeze(0).expand(K, M, coords.shape[-1]), h], dim=-1)

    def _trunk_one(self, x: torch.Tensor, k: int) -> torch.Tensor:
        """Member ``k``'s features: ``(M, in_dim) -> (M, coords_dim + c_last * P * P)``."""
        coords, patch = self._split(x)
        h = patch.reshape(x.shape[0], self.patch.channels, self.patch.size, self.patch.size)
        for w, b in zip(self.conv_weights, self.conv_biases):
            h = self.activation(F.conv2d(h, w[k], b[k], padding=1))  # (M, c_out, P, P)
        return torch.cat([coords, h.flatten(1)], dim=-1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """All members: ``(M, in_dim) -> (K, M, max_out)``."""
        return self._layers(self._trunk(x))

    def forward_one(self, x: torch.Tensor, k: int) -> torch.Tensor:
        """Member ``k``: ``(..., in_dim) -> (..., out_sizes[k])``."""
        batch = x.shape[:-1]
        out = self._layers_one(self._trunk_one(x.reshape(-1, x.shape[-1]), k), k)
        return out[:, : self.out_sizes[k]].reshape(*batch, self.out_sizes[k])

    def snapshot(self) -> list[torch.Tensor]:
        """Not supported: snapshots cover the MLP layers only, not the conv trunk."""
        raise NotImplementedError("StackedConvMLP has no snapshots (the conv trunk is not covered)")

    def forward_snapshots(
        self,
        x: torch.Tensor,
        params: Sequence[torch.Tensor] | None = None,
        members: tuple[int, int] | None = None,
    ) -> torch.Tensor:
        """The live weights only (snapshots cover the MLP layers, not the conv trunk: ``params`` is
        refused).
        """
        if params is not None:
            raise NotImplementedError(
                "StackedConvMLP has no snapshots (the conv trunk is not covered)"
            )
        out = self.forward(x)
        if members is not None:
            out = out[members[0] : members[1]]
        return out.unsqueeze(0)


class StackedHead(nn.Module):
    """Members ``index .. index + members - 1`` of a :class:`StackedMLP` as one head of shape
    ``out_shape``, several members stacked along its first output dimension.
    """

    def __init__(self, stack: StackedMLP, index: int, out_shape: Sequence[int], members: int = 1):
        super().__init__()
        self.stack = stack
        self.index = int(index)
        self.out_shape = tuple(int(s) for s in out_shape)
        self.members = int(members)
        if self.members > 1 and self.out_shape[0] != self.members:
            raise ValueError(
                f"a head of {self.members} members needs out_shape[0] == {self.members}, "
                f"got {self.out_shape}"
            )

    @property
    def member_size(self) -> int:
        """Output values per member."""
        return int(torch.Size(self.out_shape).numel()) // self.members

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.members == 1:
            out = self.stack.forward_one(x, self.index)  # (..., prod(out_shape))
            return out.reshape(*x.shape[:-1], *self.out_shape)
        parts = [self.stack.forward_one(x, self.index + j) for j in range(self.members)]
        return torch.stack(parts, -2).reshape(*x.shape[:-1], *self.out_shape)

    def select(self, out: torch.Tensor, dim: int = 0, first: int = 0) -> torch.Tensor:
        """This head's values ``(..., B, prod(out_shape))`` from a stacked output whose member axis
        is ``dim`` (starting at member ``first``).
        """
        size = self.member_size
        if self.members == 1:
            return out.select(dim, self.index - first)[..., :size]
        y = out.narrow(dim, self.index - first, self.members)[..., :size]  # (.., m, .., B, size)
        return y.movedim(dim, -2).flatten(-2)  # (.., B, m * size)


def make_stacked_heads(
    in_dim: int,
    specs: dict[str, tuple[str, Sequence[int]]],
    hidden: Sequence[int] = (64, 64),
    activation: str = "relu",
    in_key: str = keys.OBSERVATION,
    network: str = "mlp",
    patch: PatchLayout | None = None,
    conv_channels: Sequence[int] = (16, 32),
    input_masks: dict[str, torch.Tensor] | None = None,
) -> dict[str, TensorDictModule]:
    """One head per ``name: (out_key, out_shape)``, all members of one :class:`StackedMLP`.

    ``network="conv"`` makes them :class:`StackedConvMLP` members; ``input_masks[name]`` ``(m,
    in_dim)`` splits head ``name`` into ``m`` members, member ``j`` seeing the observation times row
    ``j``.
    """
    if network not in NETWORKS:
        raise ValueError(f"network must be one of {list(NETWORKS)}, got {network!r}")
    input_masks = dict(input_masks or {})
    unknown = sorted(set(input_masks) - set(specs))
    if unknown:
        raise ValueError(f"input_masks for unknown heads {unknown}; heads: {list(specs)}")
    sizes, masks, layout = [], [], {}
    for name, (_, shape) in specs.items():
        numel = int(torch.Size(shape).numel())
        mask = input_masks.get(name)
        m = 1 if mask is None else int(mask.shape[0])
        if mask is not None and (tuple(shape)[:1] != (m,) or mask.shape[-1] != int(in_dim)):
            raise ValueError(
                f"input_masks[{name!r}] must have shape ({tuple(shape)[0]}, {int(in_dim)}), "
                f"got {tuple(mask.shape)}"
            )
        layout[name] = (len(sizes), m)
        sizes += [numel // m] * m
        masks.append(torch.ones(1, int(in_dim)) if mask is None else mask.to(torch.float32))
    input_mask = torch.cat(masks) if input_masks else None
    if network == "conv":
        if patch is None:
            raise ValueError("network='conv' needs the observation's patch layout (patch=...)")
        if input_mask is not None:
            raise ValueError("input_masks need network='mlp' (a conv trunk reads the whole patch)")
        stack = StackedConvMLP(in_dim, sizes, patch, conv_channels, hidden, activation)
    else:
        stack = StackedMLP(in_dim, sizes, hidden, activation, input_mask=input_mask)
    return {
        name: TensorDictModule(
            StackedHead(stack, layout[name][0], shape, members=layout[name][1]),
            in_keys=[in_key],
            out_keys=[out_key],
        )
        for name, (out_key, shape) in specs.items()
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
