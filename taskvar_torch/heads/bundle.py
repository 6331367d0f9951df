"""The one interface controllers see: a bundle of heads, each a ``TensorDictModule`` with explicit
keys and shapes (docs/design.md#the-heads-interface). Trained networks and the oracle's tables both
build a :class:`Heads`.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn

from taskvar_torch import keys

HEAD_NAMES = ("averaging", "options", "switching", "max_value", "robustness")
HEAD_OUT_KEYS = {
    "averaging": keys.ACTION_VALUE,
    "options": keys.OPTION_ACTION_VALUE,
    "switching": keys.OPTION_VALUE,
    "max_value": keys.MAX_VALUE,
    "robustness": keys.ROBUSTNESS,
}


def with_root_row(q_options: torch.Tensor, q_avg: torch.Tensor, root: int) -> torch.Tensor:
    """``Q_o`` ``(B, O, A)`` with the composed root's row replaced by ``Q_avg`` ``(B, A)``: the
    root's policy is the full-task averaging policy (paper §3.4.2)."""
    return torch.cat([q_options[:, :root], q_avg.unsqueeze(1), q_options[:, root + 1 :]], 1)


def with_given_policies(q_options: torch.Tensor, given: torch.Tensor | None) -> torch.Tensor:
    """``Q_o (B, O, A)`` where option o acts by a given policy (``given (B, O)`` its action, -1 for
    a learnt option): every other action's value is the dtype's lowest; ``given=None``:
    ``q_options``.
    """
    if given is None:
        return q_options
    hot = torch.nn.functional.one_hot(given.clamp_min(0), q_options.shape[-1]).bool()  # (B, O, A)
    keep = hot | (given < 0).unsqueeze(-1)
    return q_options.masked_fill(~keep, torch.finfo(q_options.dtype).min)


class Heads(TensorDictModuleBase):
    """A bundle of heads; calling it writes every present head's output into the tensordict.

    Args:
        option_names: names of the O options, in the order of the option dimension.
        averaging, options, switching, max_value, robustness: ``TensorDictModule``s (any may be
            ``None`` when a family or method does not need it).
        softmax_temperature: ``None`` for a greedy mu_bar, else the temperature of a softmax mu_bar.
    """

    def __init__(
        self,
        option_names: Sequence[str],
        averaging: nn.Module | None = None,
        options: nn.Module | None = None,
        switching: nn.Module | None = None,
        max_value: nn.Module | None = None,
        robustness: nn.Module | None = None,
        softmax_temperature: float | None = None,
    ):
        super().__init__()
        self.option_names = tuple(option_names)
        self.softmax_temperature = softmax_temperature
        mods = dict(
            averaging=averaging,
            options=options,
            switching=switching,
            max_value=max_value,
            robustness=robustness,
        )
        self.heads = nn.ModuleDict({k: m for k, m in mods.items() if m is not None})
        in_keys: list = []
        for m in self.paper_heads().values():
            for k in m.in_keys:
                if k not in in_keys:
                    in_keys.append(k)
        self.in_keys = in_keys
        self.out_keys = [HEAD_OUT_KEYS[k] for k in self.paper_heads()]

    def has(self, name: str) -> bool:
        return name in self.heads

    def paper_heads(self) -> dict[str, nn.Module]:
        """The heads of the paper, in order (every head of the bundle)."""
        return {k: m for k, m in self.heads.items() if k in HEAD_NAMES}

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        for m in self.paper_heads().values():
            td = m(td)
        return td

    def mu_bar(self, option_value: torch.Tensor) -> torch.Tensor:
        """mu_bar(s, .) from Q_mu(s, .) ``(B, O)``: one-hot greedy (ties: lowest index) or softmax."""
        if self.softmax_temperature is None:
            return nn.functional.one_hot(option_value.argmax(-1), option_value.shape[-1]).to(
                option_value.dtype
            )
        return torch.softmax(option_value / self.softmax_temperature, dim=-1)
