"""Hierarchical search in a composition hierarchy (paper §3.4, Algorithm 2) as a batched controller.

Carried state: ``running_option`` = the subtask that acted last step (-1 at the episode start:
control starts at the root). Its parent is a function of it (the hierarchy is a tree), so nothing
else is carried. Every step (Algorithm 2, with greedy option policies ``pi^o = argmax Q_o``):

1. lines 1-3: if the running subtask has a parent ``p`` and ``R(p, s_t, pi^p(s_t)) > tau``, the
   parent regains control and acts;
2. lines 5-7: else the running subtask acts if it is a leaf (primitive option) or
   ``R(o_run, s_t, pi^{o_run}(s_t)) > tau``;
3. lines 9-11: else control descends to ``q* = argmax_{q in components(o_run)} R(q, s_t, a)``, where
   ``a`` is the action *of o_run* (line 10), and the search repeats from ``q*`` with parent
   ``o_run``. In that recursive call line 2 re-checks ``R(o_run, s_t, pi^{o_run}(s_t)) > tau``, which
   has just failed (deterministic policies), so it is not re-evaluated.

The recursion depth is bounded by the tree depth, so the batched version loops over levels.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch

from taskvar_torch import keys
from taskvar_torch.controllers.base import Controller, argmax_last, take_row
from taskvar_torch.heads.bundle import Heads
from taskvar_torch.subtasks.base import Hierarchy

Tensor = torch.Tensor


@dataclass(frozen=True)
class TreeTables:
    """A :class:`Hierarchy` as index tables over the bundle's option dimension ``O``."""

    root: int
    parent: Tensor  # (O,) int64: parent index, -1 for the root (and options outside the tree)
    is_leaf: Tensor  # (O,) bool: no components (primitive option)
    child_mask: Tensor  # (O, O) bool: child_mask[o, q] = q is a component of o
    depth: Tensor  # (O,) int64: 0 at the root
    max_depth: int

    @classmethod
    def build(
        cls, hierarchy: Hierarchy, option_names: Sequence[str], device: torch.device | str = "cpu"
    ) -> TreeTables:
        names = list(option_names)
        unknown = [o for o in hierarchy.options if o not in names]
        if unknown:
            raise ValueError(
                f"hierarchy option(s) {unknown} are not in the head bundle's options {names}"
            )
        O = len(names)  # noqa: E741
        parent = torch.full((O,), -1, dtype=torch.int64)
        is_leaf = torch.ones(O, dtype=torch.bool)
        child = torch.zeros(O, O, dtype=torch.bool)
        depth = torch.zeros(O, dtype=torch.int64)
        for o in hierarchy.options:
            i = names.index(o)
            depth[i] = hierarchy.depth(o)
            kids = hierarchy.components(o)
            is_leaf[i] = len(kids) == 0
            for k in kids:
                parent[names.index(k)] = i
                child[i, names.index(k)] = True
        dev = torch.device(device)
        return cls(
            root=names.index(hierarchy.root),
            parent=parent.to(dev),
            is_leaf=is_leaf.to(dev),
            child_mask=child.to(dev),
            depth=depth.to(dev),
            max_depth=max(hierarchy.depth(o) for o in hierarchy.options),
        )

    def to(self, device: torch.device | str) -> TreeTables:
        return TreeTables(
            self.root,
            self.parent.to(device),
            self.is_leaf.to(device),
            self.child_mask.to(device),
            self.depth.to(device),
            self.max_depth,
        )


def hierarchy_decide(
    q_opt: Tensor,  # (B, O, A) Q_o(s_t, a): option policies pi^o (greedy)
    robustness: Tensor,  # (B, O, A) R(o, s_t, a)
    running: Tensor,  # (B,) int64 running subtask, -1 = none (start at the root)
    tree: TreeTables,
    tau: float,
) -> dict[str, Tensor]:
    """One step of Algorithm 2 for a batch.

    Returns ``action``, ``option`` (the subtask that acts: the next running subtask),
    ``hierarchy_level`` (its depth, 0 = root) and ``interrupted`` (control left the running subtask:
    the parent regained it or it descended; False at the episode start).
    """
    acts = argmax_last(q_opt)  # (B, O): pi^o(s_t) of every option
    rob_t = robustness.transpose(1, 2)  # (B, A, O)
    o = torch.where(running < 0, torch.full_like(running, tree.root), running)  # (B,)
    p = tree.parent[o]  # (B,)
    pc = p.clamp(min=0)
    a_p = take_row(acts, pc)  # (B,) line 1
    regain = (p >= 0) & (take_row(take_row(robustness, pc), a_p) > tau)  # (B,) line 2
    result = torch.where(regain, pc, o)
    done = regain
    node = o
    for _ in range(tree.max_depth + 1):
        a = take_row(acts, node)  # (B,) line 5
        ok = tree.is_leaf[node] | (take_row(take_row(robustness, node), a) > tau)  # line 6
        result = torch.where(ok & ~done, node, result)
        done = done | ok
        r_a = take_row(rob_t, a)  # (B, O): R(q, s_t, a) with a the action of o_run (line 10)
        r_a = r_a.masked_fill(~tree.child_mask[node], float("-inf"))
        node = torch.where(done, node, argmax_last(r_a))  # line 11: recurse into q*
    action = take_row(acts, result)
    interrupted = (running >= 0) & (result != running)
    return {
        "action": action,
        "option": result,
        keys.HIERARCHY_LEVEL: tree.depth[result],
        keys.INTERRUPTED: interrupted,
    }


class HierarchyController(Controller):
    """HierarchicalSearch (Algorithm 2) over a composition hierarchy; reads Q_o and R heads only.

    Every node of ``hierarchy`` must be an option of the bundle (the root's option head is the
    full-task policy: paper §3.4.2, "the policy of this subtask is the full task averaging policy").

    Args:
        heads: a bundle with ``options`` and ``robustness`` heads.
        hierarchy: the tree (config data).
        tau: robustness threshold (paper §3.4.3).

    Writes ``action``, ``option``, ``hierarchy_level``, ``interrupted`` and
    ``("next", "running_option")``.
    """

    name = "hierarchy"
    required_heads = ("options", "robustness")
    trace_keys = (keys.OPTION, keys.INTERRUPTED, keys.HIERARCHY_LEVEL)

    def __init__(self, heads: Heads, hierarchy: Hierarchy, tau: float, seed: int = 0):
        super().__init__(heads, None, seed)
        self.hierarchy = hierarchy
        self.tau = float(tau)
        self._tree = TreeTables.build(hierarchy, heads.option_names)
        self._trees: dict[torch.device, TreeTables] = {}

    def tree(self, device: torch.device) -> TreeTables:
        """The tree's index tables on ``device`` (cached)."""
        t = self._trees.get(device)
        if t is None:
            t = self._trees[device] = self._tree.to(device)
        return t

    def decide(
        self, values: Mapping[str, Tensor], running: Tensor, terminated: Tensor | None
    ) -> dict[str, Tensor]:
        q_opt = values[keys.OPTION_ACTION_VALUE]
        return hierarchy_decide(
            q_opt, values[keys.ROBUSTNESS], running, self.tree(q_opt.device), self.tau
        )
