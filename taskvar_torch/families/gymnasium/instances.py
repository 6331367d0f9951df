"""Named instance distributions of a Gymnasium family (paper §2; CARL's contexts): any object with
``sample(rng) -> dict`` of numbers by name, drawn per episode from the episode key's generator
(docs/gymnasium.md).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from taskvar_torch import rng
from taskvar_torch.guest import guest, short, user_error

_SALT = 0x1A57A11CE  # the instance generator's stream, apart from the env's reset seed


class Instances:
    """A family's named distributions (``train`` required) and the parameter names they draw;
    ``family`` is named in a failure of ``sample``.
    """

    def __init__(self, named: Mapping[str, Any], family: str = "gymnasium"):
        self.named, self.family = dict(named), family
        if "train" not in self.named:
            raise ValueError(f"instances must name a 'train' distribution, got {sorted(named)}")
        for name, dist in self.named.items():
            if not callable(getattr(dist, "sample", None)):
                raise ValueError(f"instances[{name!r}] must have sample(rng) -> dict")
        self.names = tuple(self.named)
        self.keys = tuple(self.draw(self.named["train"], 0))
        classes = {type(d) for d in self.named.values()}
        one = next(iter(classes))
        self.fields_class = one if len(classes) == 1 and dataclasses.is_dataclass(one) else None

    def of(self, spec: Any) -> Any:
        """A distribution from a name, the fields of one (a dict) or a distribution."""
        if isinstance(spec, str):
            if spec not in self.named:
                raise ValueError(f"instances must be one of {list(self.names)}, got {spec!r}")
            return self.named[spec]
        if isinstance(spec, Mapping):
            return self.make(dict(spec))
        if not callable(getattr(spec, "sample", None)):
            raise ValueError(f"instances must be a name, fields or a distribution, got {spec!r}")
        return spec

    def fields(self, spec: Any) -> dict[str, Any]:
        """A distribution's dataclass fields (``--shift env.instances.FIELD``)."""
        return dataclasses.asdict(self.of(spec))

    def make(self, fields: dict[str, Any]) -> Any:
        """The distribution of these dataclass fields (a one-line ``ValueError`` naming an unknown
        field)."""
        cls = self.fields_class
        if cls is None:
            raise ValueError("these instances are not one dataclass: they have no fields to set")
        allowed = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(fields) - set(allowed))
        if unknown:
            raise ValueError(f"instance fields must be among {allowed}, got {unknown}")
        return cls(**fields)

    def draw(self, dist: Any, key: int) -> dict[str, Any]:
        """One instance of ``dist`` from the episode key ``key`` (a uint32): a one-line
        :class:`~taskvar_torch.guest.UserCodeError` where ``sample`` fails or returns anything but
        a non-empty dict of numbers with the parameters of the first draw of ``train``."""
        name = next((f"instances[{n!r}]" for n, d in self.named.items() if d is dist), "instances")
        what, where = f"{name}.sample(rng)", f"episode key {int(key)}"
        gen = np.random.default_rng([int(key), _SALT])
        instance = guest(self.family, what, dist.sample, gen, where=where)
        if not isinstance(instance, Mapping) or not instance:
            problem = f"{short(instance, 48)}, not a non-empty dict"
            raise user_error(self.family, what, f"returned {problem}", where)
        bad = [k for k, v in instance.items() if not isinstance(v, (bool, int, float, np.number))]
        if bad:
            problem = f"{bad[0]!r}={short(instance[bad[0]], 48)}, not a number (bool, int, float)"
            raise user_error(self.family, what, f"returned {problem}", where)
        if hasattr(self, "keys") and tuple(instance) != self.keys:
            problem = (
                f"the parameters {list(instance)}, not {list(self.keys)} (those of the first draw "
                "of 'train': every draw must give the same names, in the same order)"
            )
            raise user_error(self.family, what, f"returned {problem}", where)
        return dict(instance)


def reset_seed(key: int) -> int:
    """The Gymnasium ``reset(seed=...)`` of the episode of key ``key`` (a uint32)."""
    return int(rng.draw_bits(int(key), rng.RESET_COUNTER + 1))


__all__ = ["Instances", "reset_seed"]
