"""The observation encoder: a batch of Gymnasium observations -> the family's ``observation``
(docs/gymnasium.md). Yours is any ``space -> encoder`` whose result has ``size`` and maps a batch to
a ``(N, size)`` float tensor.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from gymnasium import spaces
from gymnasium.spaces.utils import flatten_space


def _check(space: spaces.Space, where: str) -> None:
    """A one-line ``ValueError`` for a space with no fixed-length flat encoding."""
    if isinstance(space, spaces.Dict):
        for k, sub in space.spaces.items():
            _check(sub, f"{where}[{k!r}]")
    elif isinstance(space, spaces.Tuple):
        for i, sub in enumerate(space.spaces):
            _check(sub, f"{where}[{i}]")
    elif not isinstance(
        space, (spaces.Box, spaces.Discrete, spaces.MultiDiscrete, spaces.MultiBinary)
    ):
        raise ValueError(
            f"observation space {where} is {type(space).__name__}, which has no fixed-length "
            "encoding: keep the other parts with SpaceEncoder(space, keys=(...)) or pass an encoder "
            "of your own (docs/gymnasium.md)"
        )


def _encode(space: spaces.Space, obs, n: int) -> list[torch.Tensor]:
    """The parts of the flat encoding of a batch ``obs`` of ``n`` rows, each ``(n, d)``."""
    if isinstance(space, spaces.Dict):
        return [part for k, sub in space.spaces.items() for part in _encode(sub, obs[k], n)]
    if isinstance(space, spaces.Tuple):
        return [part for i, sub in enumerate(space.spaces) for part in _encode(sub, obs[i], n)]
    x = torch.as_tensor(np.asarray(obs)).reshape(n, -1)
    if isinstance(space, spaces.Discrete):
        return [torch.nn.functional.one_hot(x[:, 0].long() - int(space.start), int(space.n))]
    if isinstance(space, spaces.MultiDiscrete):
        nvec, start = space.nvec.reshape(-1), space.start.reshape(-1)
        return [
            torch.nn.functional.one_hot(x[:, j].long() - int(start[j]), int(nvec[j]))
            for j in range(nvec.size)
        ]
    return [x]  # Box (images included), MultiBinary: the values, flat


class SpaceEncoder:
    """``gymnasium.spaces.flatten`` of every row of a batch, as a float32 ``(N, size)`` tensor, with
    ``low``, ``high`` from ``flatten_space``; ``keys``: a ``Dict`` space's entries to keep
    (MiniGrid: ``("image", "direction")``).
    """

    def __init__(self, space: spaces.Space, keys: Sequence[str] | None = None):
        if keys is not None:
            if not isinstance(space, spaces.Dict):
                raise ValueError(
                    f"SpaceEncoder keys need a Dict observation space, got {type(space).__name__}"
                )
            unknown = [k for k in keys if k not in space.spaces]
            if unknown:
                raise ValueError(
                    f"SpaceEncoder keys must be among {sorted(space.spaces)}, got {unknown}"
                )
            space = spaces.Dict({k: space.spaces[k] for k in keys})  # in Gymnasium's order
        _check(space, "observation")
        self.space = space
        flat = flatten_space(space)
        self.size = int(flat.shape[0])
        self.low = torch.as_tensor(flat.low, dtype=torch.float32)
        self.high = torch.as_tensor(flat.high, dtype=torch.float32)

    def __call__(self, obs) -> torch.Tensor:
        """A batch of observations (the vector env's) -> ``(N, size)`` float32."""
        first = obs
        while isinstance(first, (dict, tuple)):
            first = next(iter(first.values())) if isinstance(first, dict) else first[0]
        n = int(np.asarray(first).shape[0])
        return torch.cat([p.to(torch.float32) for p in _encode(self.space, obs, n)], dim=1)


__all__ = ["SpaceEncoder"]
