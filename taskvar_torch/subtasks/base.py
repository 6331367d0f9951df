"""The subtask interface shared by every family (paper §3.2, §3.4)."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from tensordict import TensorDictBase


@dataclass(frozen=True)
class Hierarchy:
    """A composition hierarchy as data (paper §3.4.2, Figure 3): a tree of option names.

    A tree, not a graph: Algorithm 2 returns control to the running option's parent, so a
    component shared by several composed options (MAXQ's Navigate under Get and Put) is refused;
    give each parent its own copy of the option.

    ``children[o]`` are the components of the composed subtask ``o``; options without children are
    the leaves ("primitive options" of Algorithm 2). Control starts at ``root``.

    Examples:
        >>> h = Hierarchy(root="TG+FE", children={"TG+FE": ("TG", "FE")})
        >>> h.parent("TG"), h.is_leaf("FE")
        ('TG+FE', True)
    """

    root: str
    children: dict[str, tuple[str, ...]] = field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "children", {k: tuple(v) for k, v in self.children.items()})
        seen, stack = set(), [self.root]
        while stack:
            o = stack.pop()
            if o in seen:
                raise ValueError(
                    f"hierarchy must be a tree: option {o!r} is reached twice from the root "
                    "(a component shared by two composed options, or a cycle); Algorithm 2 hands "
                    "control back to the running option's parent, which a shared component does "
                    f"not determine: give each parent its own copy (e.g. {o + '_1'!r}, {o + '_2'!r})"
                )
            seen.add(o)
            stack.extend(self.children.get(o, ()))
        unknown = sorted(set(self.children) - seen)
        if unknown:
            raise ValueError(
                f"hierarchy children given for options not under root {self.root!r}: {unknown}"
            )

    @property
    def options(self) -> tuple[str, ...]:
        """All options of the tree, root first (breadth-first)."""
        out, queue = [], [self.root]
        while queue:
            o = queue.pop(0)
            out.append(o)
            queue.extend(self.children.get(o, ()))
        return tuple(out)

    def components(self, option: str) -> tuple[str, ...]:
        return self.children.get(option, ())

    def is_leaf(self, option: str) -> bool:
        return not self.children.get(option)

    def parent(self, option: str) -> str | None:
        for p, kids in self.children.items():
            if option in kids:
                return p
        return None

    def depth(self, option: str) -> int:
        d, o = 0, option
        while (o := self.parent(o)) is not None:
            d += 1
        return d

    @classmethod
    def from_dict(cls, data: dict) -> Hierarchy:
        """From config data ``{"root": ..., "children": {name: [names]}}``."""
        unknown = sorted(set(data) - {"root", "children"})
        if unknown:
            raise ValueError(f"unknown hierarchy field(s) {unknown}; allowed: ['children', 'root']")
        return cls(root=data["root"], children=dict(data.get("children", {})))


class Subtasks:
    """Options of a family, vectorised. Subclasses set ``names`` and implement the methods.

    Shapes: ``B`` transitions, ``O = len(names)`` options. Methods read the state at the root of
    ``td`` and, for transition quantities, the next state under ``("next", ...)``.
    """

    names: tuple[str, ...] = ()
    hierarchy: Hierarchy | None = None
    initiable_everywhere: bool = False
    """Every option's initiation set is the whole state space: the option controllers then skip
    the initiation mask and its averaging fallback (the same decisions, less work a step)."""

    @property
    def num_options(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        if name not in self.names:
            raise ValueError(f"option must be one of {list(self.names)}, got {name!r}")
        return self.names.index(name)

    def initiation(self, td: TensorDictBase) -> torch.Tensor:
        """``(B, O)`` bool: the state at the root of ``td`` is in option o's initiation set I_o."""
        raise NotImplementedError

    def termination(self, td: TensorDictBase) -> torch.Tensor:
        """``(B, O)`` bool: beta_o = 1 at the state at the root of ``td`` (pass ``td["next"]``)."""
        raise NotImplementedError

    def reward(self, td: TensorDictBase) -> torch.Tensor:
        """``(B, O)`` float: subtask reward of each option for the transition ``td -> td["next"]``."""
        raise NotImplementedError

    def robustness_reward(self, td: TensorDictBase) -> torch.Tensor:
        """``(B, O)`` float: robustness reward (paper §3.4.3, §3.5.2) for the transition."""
        raise NotImplementedError(f"{type(self).__name__} defines no robustness reward")

    def startable(self, td: TensorDictBase) -> torch.Tensor:
        """``(B, O)`` bool: option o can take control at the state at the root of ``td``: s is in
        I_o and o's termination condition does not already hold there (the hierarchy's descent,
        Algorithm 2 line 10, only hands control to such a component). Default: I_o."""
        return self.initiation(td)

    def no_conflict(self, td: TensorDictBase) -> torch.Tensor | None:
        """``(B,)`` bool: the subgoals of the composed subtasks do not conflict at s (paper
        §3.5.3); the states on which a calibrated threshold keeps the composed node in control
        (``train.robustness_keep_share`` of them). Default ``None``: the family names no such
        states, and a calibrated composed node keeps the fixed ``train.robustness_tau`` (on every
        state it would be kept in control on the keep share of them whatever its policy is
        worth: the root held 100% of MiniGrid DoorKey's steps; docs/controllers.md)."""
        return None

    given: tuple[bool, ...] | None = None
    """Which options act by a policy the family gives (a hand-written controller) rather than one
    learnt from Q_o: ``None`` (the default) when none does. Their actions are
    :meth:`given_actions`; their values are learnt like any option's (docs/gymnasium.md)."""

    def given_actions(self, td: TensorDictBase) -> torch.Tensor | None:
        """``(B, O)`` int64: the action each given-policy option takes at the state at the root
        of ``td`` (-1 for a learnt option); ``None`` where no option has a given policy."""
        return None

    def option_input_mask(self, obs_dim: int) -> torch.Tensor | None:
        """``(O, obs_dim)`` 0/1: the observation features option o's own subtask needs (what its
        policy sees with ``heads.option_inputs=subtask``); ``None``: the family defines none."""
        return None
