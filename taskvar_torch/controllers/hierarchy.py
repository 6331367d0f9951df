"""Hierarchical search in a composition hierarchy (paper §3.4, Algorithm 2) as a batched controller.

The root acts by its option head or, with ``root_policy="averaging"``, by the averaging head
(§3.4.2: "the policy of this subtask is the full task averaging policy"); ``pi^root`` below is
that policy.

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

Batched kernels. With greedy option policies the search reads only, per state and per *composed*
node ``o``, the bit ``ok_o = R(o, s_t, pi^o(s_t)) > tau`` and the index of its most robust component
under its own action (leaves always act, and only composed nodes are parents). So for small trees
(``(O + 1) x prod over composed nodes of 2 x #components <= 65536``, e.g. 16 for Wargus's 3-node
tree) :class:`TreeTables` precomputes the decision for every (running subtask, bits, choices) code
and the kernel is one table lookup
(:func:`hierarchy_decide_table_of`); larger trees walk the levels (:func:`hierarchy_search_of`,
bounded by the tree depth). Both are tested against the scalar search and the oracle's.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from taskvar_torch import keys
from taskvar_torch.controllers.base import (
    Controller,
    argmax0,
    first_argmax,
    lookup,
    option_first,
    select0,
)
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
    # compiled decision table (None for trees too large to tabulate)
    internal: tuple[tuple[int, Tensor, int, int], ...] = ()  # (node, components, bit, radix)
    num_codes: int = 0  # codes per running value
    table_option: Tensor | None = None  # ((O + 1) * num_codes,) int64: the option that acts
    table_level: Tensor | None = None  # ((O + 1) * num_codes,) int64: its depth

    MAX_TABLE = 1 << 16

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
        root = names.index(hierarchy.root)
        tables = _compile_table(hierarchy, names, root, parent.tolist(), depth.tolist())
        return cls(
            root=root,
            parent=parent.to(dev),
            is_leaf=is_leaf.to(dev),
            child_mask=child.to(dev),
            depth=depth.to(dev),
            max_depth=max(hierarchy.depth(o) for o in hierarchy.options),
            **tables,
        ).to(dev)

    def to(self, device: torch.device | str) -> TreeTables:
        mv = lambda t: None if t is None else t.to(device)  # noqa: E731
        return TreeTables(
            self.root,
            self.parent.to(device),
            self.is_leaf.to(device),
            self.child_mask.to(device),
            self.depth.to(device),
            self.max_depth,
            tuple((i, k.to(device), b, r) for i, k, b, r in self.internal),
            self.num_codes,
            mv(self.table_option),
            mv(self.table_level),
        )


def _compile_table(
    hierarchy: Hierarchy, names: list[str], root: int, parent: list[int], depth: list[int]
) -> dict[str, Any]:
    """Algorithm 2's decision for every (running subtask, robustness bits, component choices).

    Code of a state: bit ``j`` = composed node ``j`` is robust under its own action; digit ``j`` (mixed
    radix) = the index of its most robust component under that action.
    """
    O = len(names)  # noqa: E741
    nodes = [names.index(o) for o in hierarchy.options]
    kids = {i: sorted(names.index(k) for k in hierarchy.components(names[i])) for i in nodes}
    internal = [i for i in nodes if kids[i]]
    bits = {i: 1 << j for j, i in enumerate(internal)}
    radices, r = {}, 2 ** len(internal)
    for i in internal:
        radices[i] = r
        r *= len(kids[i])
    num_codes = r
    if (O + 1) * num_codes > TreeTables.MAX_TABLE:
        return {}
    opt = torch.empty((O + 1) * num_codes, dtype=torch.int64)
    for code in range(num_codes):
        ok = {i: bool(code & bits[i]) for i in internal}
        choice = {i: kids[i][(code // radices[i]) % len(kids[i])] for i in internal}
        for running in range(-1, O):
            o = root if running < 0 else running
            p = parent[o]
            if p >= 0 and ok.get(p, False):  # lines 1-3
                node = p
            else:
                node = o
                while kids.get(node) and not ok[node]:  # lines 5-11 (leaves always act)
                    node = choice[node]
            opt[(running + 1) * num_codes + code] = node
    return {
        "internal": tuple(
            (i, torch.tensor(kids[i], dtype=torch.int64), bits[i], radices[i]) for i in internal
        ),
        "num_codes": num_codes,
        "table_option": opt,
        "table_level": torch.tensor(depth, dtype=torch.int64)[opt],
    }


def hierarchy_decide_of(
    q_opt: Tensor,  # (O, A, B) Q_o(s_t, a), option-first: option policies pi^o (greedy)
    robustness: Tensor,  # (O, A, B) R(o, s_t, a)
    running: Tensor,  # (B,) int64 running subtask, -1 = none (start at the root)
    tree: TreeTables,
    tau: float,
) -> dict[str, Tensor]:
    """One step of Algorithm 2 for a batch (option-first inputs).

    Returns ``action``, ``option`` (the subtask that acts: the next running subtask),
    ``hierarchy_level`` (its depth, 0 = root) and ``interrupted`` (control left the running subtask:
    the parent regained it or it descended; False at the episode start), each ``(B,)``.
    Uses the compiled table when the tree has one, else walks the levels.
    """
    if tree.table_option is not None:
        return hierarchy_decide_table_of(q_opt, robustness, running, tree, tau)
    return hierarchy_search_of(q_opt, robustness, running, tree, tau)


def hierarchy_decide_table_of(
    q_opt: Tensor,  # (O, A, B)
    robustness: Tensor,  # (O, A, B)
    running: Tensor,  # (B,)
    tree: TreeTables,
    tau: float,
) -> dict[str, Tensor]:
    """Algorithm 2 by table lookup: encode each state's robustness bits and component choices."""
    code = torch.zeros(running.shape, dtype=torch.int64, device=running.device)
    for node, kids, bit, radix in tree.internal:
        a = argmax0(q_opt[node])  # (B,): pi^node(s_t) (lines 1, 5)
        rob_a = robustness.gather(1, a.view(1, 1, -1).expand(robustness.shape[0], 1, -1))
        rob_a = rob_a.squeeze(1)  # (O, B): R(q, s_t, pi^node(s_t)) for every q
        code = code + (rob_a[node] > tau) * bit  # robust under its own action (lines 2, 6)
        code = code + argmax0(rob_a.index_select(0, kids)) * radix  # q* of line 10
    code = code + (running + 1) * tree.num_codes
    option = tree.table_option.index_select(0, code)  # (B,)
    return {
        "action": argmax0(select0(q_opt, option)),  # the acting option's greedy action
        "option": option,
        keys.HIERARCHY_LEVEL: tree.table_level.index_select(0, code),
        keys.INTERRUPTED: (running >= 0) & (option != running),
    }


def hierarchy_search_of(
    q_opt: Tensor,  # (O, A, B)
    robustness: Tensor,  # (O, A, B)
    running: Tensor,  # (B,)
    tree: TreeTables,
    tau: float,
) -> dict[str, Tensor]:
    """Algorithm 2 by walking the levels (any tree size): the literal recursion, batched."""
    acts = argmax0(q_opt.transpose(0, 1))  # (O, B): pi^o(s_t) of every option
    rob_a = robustness.transpose(0, 1)  # (A, O, B)
    o = torch.where(running < 0, torch.full_like(running, tree.root), running)  # (B,)
    p = lookup(tree.parent, o)  # (B,)
    pc = p.clamp(min=0)
    a_p = select0(acts, pc)  # (B,) line 1
    regain = (p >= 0) & (select0(select0(robustness, pc), a_p) > tau)  # (B,) line 2
    result = torch.where(regain, pc, o)
    done = regain
    node = o
    for _ in range(tree.max_depth + 1):
        a = select0(acts, node)  # (B,) line 5
        ok = lookup(tree.is_leaf, node) | (select0(select0(robustness, node), a) > tau)  # line 6
        result = torch.where(ok & ~done, node, result)
        done = done | ok
        r_a = select0(rob_a, a)  # (O, B): R(q, s_t, a), a the action of o_run (line 10)
        kids = tree.child_mask.t().index_select(1, node)  # (O, B): q is a component of o_run
        r_a = r_a.masked_fill(~kids, float("-inf"))
        node = torch.where(done, node, argmax0(r_a))  # line 11: recurse into q*
    action = select0(acts, result)
    interrupted = (running >= 0) & (result != running)
    return {
        "action": action,
        "option": result,
        keys.HIERARCHY_LEVEL: lookup(tree.depth, result),
        keys.INTERRUPTED: interrupted,
    }


def hierarchy_decide(
    q_opt: Tensor,  # (B, O, A)
    robustness: Tensor,  # (B, O, A)
    running: Tensor,  # (B,)
    tree: TreeTables,
    tau: float,
) -> dict[str, Tensor]:
    """:func:`hierarchy_decide_of` for head outputs in the bundle layout (batch first)."""
    return hierarchy_decide_of(option_first(q_opt), option_first(robustness), running, tree, tau)


ROOT_POLICIES = ("averaging", "option")  # the root's pi: greedy in Q_avg, or in its option head


def with_root_policy(q_opt: Tensor, q_avg: Tensor, root: int) -> Tensor:
    """``q_opt`` ``(O, A, B)`` with the root's row replaced by ``Q_avg`` ``(A, B)``: pi^root = pi^avg."""
    return torch.cat([q_opt[:root], q_avg.unsqueeze(0), q_opt[root + 1 :]])


class HierarchyController(Controller):
    """HierarchicalSearch (Algorithm 2) over a composition hierarchy; reads Q_o and R heads only.

    Every node of ``hierarchy`` must be an option of the bundle. The root's policy pi^root is its
    option head (``root_policy="option"``) or the averaging head (``"averaging"``: paper §3.4.2,
    "the policy of this subtask is the full task averaging policy"); the robustness critic of the
    root must have been learnt for that same policy (``train.root_policy``).

    Args:
        heads: a bundle with ``options`` and ``robustness`` heads (and ``averaging`` for
            ``root_policy="averaging"``).
        hierarchy: the tree (config data).
        tau: robustness threshold (paper §3.4.3).
        root_policy: ``"option"`` or ``"averaging"``.

    Writes ``action``, ``option``, ``hierarchy_level``, ``interrupted`` and
    ``("next", "running_option")``.
    """

    name = "hierarchy"
    required_heads = ("options", "robustness")
    trace_keys = (keys.OPTION, keys.INTERRUPTED, keys.HIERARCHY_LEVEL)

    def __init__(
        self,
        heads: Heads,
        hierarchy: Hierarchy,
        tau: float,
        seed: int = 0,
        root_policy: str = "option",
    ):
        if root_policy not in ROOT_POLICIES:
            raise ValueError(
                f"root_policy must be one of {list(ROOT_POLICIES)}, got {root_policy!r}"
            )
        if root_policy == "averaging":  # the instance's own heads (read by the base class)
            self.required_heads = ("averaging", *type(self).required_heads)
        super().__init__(heads, None, seed)
        self.hierarchy = hierarchy
        self.tau = float(tau)
        self.root_policy = root_policy
        self._tree = TreeTables.build(hierarchy, heads.option_names)
        self._trees: dict[torch.device, TreeTables] = {}
        tt = self._tree
        self._tree_lists = {
            "root": tt.root,
            "parent": tt.parent.tolist(),
            "is_leaf": tt.is_leaf.tolist(),
            "depth": tt.depth.tolist(),
            "children": [row.nonzero().flatten().tolist() for row in tt.child_mask],
        }

    def tree(self, device: torch.device) -> TreeTables:
        """The tree's index tables on ``device`` (cached)."""
        t = self._trees.get(device)
        if t is None:
            t = self._trees[device] = self._tree.to(device)
        return t

    def decide_of(
        self, values: Mapping[str, Tensor], running: Tensor, terminated: Tensor | None
    ) -> dict[str, Tensor]:
        q_opt = values[keys.OPTION_ACTION_VALUE]  # (O, A, B)
        if self.root_policy == "averaging":
            q_opt = with_root_policy(q_opt, values[keys.ACTION_VALUE], self._tree.root)
        return hierarchy_decide_of(
            q_opt, values[keys.ROBUSTNESS], running, self.tree(q_opt.device), self.tau
        )

    def decide_scalar(
        self, values: Mapping[str, list], running: int, terminated: bool
    ) -> dict[str, Any]:
        q, rob, tau = values[keys.OPTION_ACTION_VALUE], values[keys.ROBUSTNESS], self.tau
        t = self._tree_lists
        if self.root_policy == "averaging":
            q = [values[keys.ACTION_VALUE] if i == t["root"] else row for i, row in enumerate(q)]
        o = t["root"] if running < 0 else running
        p = t["parent"][o]
        if p >= 0 and rob[p][first_argmax(q[p])] > tau:  # lines 1-3
            node = p
        else:
            node = o
            while True:
                a = first_argmax(q[node])  # line 5
                if t["is_leaf"][node] or rob[node][a] > tau:  # line 6
                    break
                kids = t["children"][node]  # lines 9-11
                node = kids[first_argmax([rob[k][a] for k in kids])]
        return {
            "action": first_argmax(q[node]),
            "option": node,
            keys.HIERARCHY_LEVEL: t["depth"][node],
            keys.INTERRUPTED: running >= 0 and node != running,
        }
