"""Hierarchical search in a composition hierarchy (paper §3.4, Algorithm 2) as a batched controller.

Carried state: ``running_option``, the subtask that acted last step (-1: control starts at the
root). Every step, with greedy option policies ``pi^o = argmax Q_o`` (``pi^root`` the root's option
head or, with ``root_policy="averaging"``, the averaging head, §3.4.2):

1. lines 1-3: if the running subtask has a parent ``p`` and ``R(p, s_t, pi^p(s_t)) > tau``, the
   parent regains control and acts;
2. lines 5-7: else the running subtask acts if it is a leaf or ``R(o_run, s_t, pi^{o_run}(s_t)) >
   tau``;
3. lines 9-11: else control descends to ``argmax_{q in components(o_run)} R(q, s_t, a)`` with ``a``
   the action of ``o_run``, and the search repeats from there.

:func:`hierarchy_decide_of` is the recursion, batched by walking the levels; for small trees
:class:`TreeTables` tabulates the decision per (running subtask, robustness bits, component choices)
and :func:`hierarchy_decide_table_of` is one lookup; :meth:`HierarchyController.decide_scalar` is
the search on Python floats. All three are tested equal (tests/test_controllers.py).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase

from taskvar_torch import keys
from taskvar_torch.controllers.base import (
    Controller,
    argmax0,
    first_argmax,
    lookup,
    select0,
)
from taskvar_torch.heads.bundle import Heads
from taskvar_torch.heads.robustness import RobustnessCalibration
from taskvar_torch.subtasks.base import Hierarchy, Subtasks

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
    """Algorithm 2's decision for every code: per composed node ``j``, bit ``2j`` robust under its
    own action, bit ``2j + 1`` no component can take control, mixed-radix digit ``j`` its best
    component.
    """
    O = len(names)  # noqa: E741
    nodes = [names.index(o) for o in hierarchy.options]
    kids = {i: sorted(names.index(k) for k in hierarchy.components(names[i])) for i in nodes}
    internal = [i for i in nodes if kids[i]]
    bits = {i: 1 << (2 * j) for j, i in enumerate(internal)}
    radices, r = {}, 4 ** len(internal)
    for i in internal:
        radices[i] = r
        r *= len(kids[i])
    num_codes = r
    if (O + 1) * num_codes > TreeTables.MAX_TABLE:
        return {}
    opt = torch.empty((O + 1) * num_codes, dtype=torch.int64)
    for code in range(num_codes):
        ok = {i: bool(code & bits[i]) for i in internal}
        keep = {i: bool(code & (bits[i] << 1)) for i in internal}
        choice = {i: kids[i][(code // radices[i]) % len(kids[i])] for i in internal}
        for running in range(-1, O):
            o = root if running < 0 else running
            p = parent[o]
            if p >= 0 and ok.get(p, False):  # lines 1-3
                node = p
            else:
                node = o  # lines 5-11 (leaves always act)
                while kids.get(node) and not (ok[node] or keep[node]):
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


def _at(x: float | Tensor, node: int) -> float | Tensor:
    """Per-option value ``x[node]`` (``(1,)`` or ``(B,)``) of ``x`` ``(O, 1|B)``, or the scalar ``x``."""
    return x[node] if isinstance(x, Tensor) else x


def _scores(
    rob: Tensor,  # (K, B) R(q, s_t, a) of the candidate components
    kids: Tensor,  # (K,) their option indices
    loc: Tensor | None,  # (O, 1|B) or None: raw R
    scale: Tensor | None,  # (O, 1|B)
    startable: Tensor | None,  # (O, B) bool or None
) -> tuple[Tensor, Tensor | None]:
    """Descent scores of line 10 (raw or ``(R - loc) / scale``), -inf where a component cannot take
    control; and ``(B,)`` bool "no component can" (None without ``startable``)."""
    if loc is not None:
        rob = (rob - loc.index_select(0, kids)) / scale.index_select(0, kids)
    if startable is None:
        return rob, None
    st = startable.index_select(0, kids)  # (K, B)
    return rob.masked_fill(~st, float("-inf")), ~st.any(0)


def _control_start(running: Tensor, terminated: Tensor | None, tree: TreeTables) -> Tensor:
    """Where the search starts: ``running``, or its parent where ``beta_{o_run}(s_t)`` holds
    (control returns up the tree); -1 (the root) at the episode start."""
    if terminated is None:
        return running
    up = terminated & (running >= 0)
    parent = lookup(tree.parent, running.clamp(min=0))  # (B,)
    return torch.where(up & (parent >= 0), parent, running)


def _interrupted(option: Tensor, running: Tensor, terminated: Tensor | None) -> Tensor:
    """Control left a running subtask that had not terminated (False at the episode start)."""
    changed = (running >= 0) & (option != running)
    return changed if terminated is None else changed & ~terminated


def hierarchy_decide_of(
    q_opt: Tensor,  # (O, A, B) Q_o(s_t, a), option-first: option policies pi^o (greedy)
    robustness: Tensor,  # (O, A, B) R(o, s_t, a)
    running: Tensor,  # (B,) int64 running subtask, -1 = none (start at the root)
    tree: TreeTables,
    tau: float | Tensor,  # threshold, or per option (O, 1|B)
    terminated: Tensor | None = None,  # (B,) bool beta_{o_run}(s_t): control returns up
    startable: Tensor | None = None,  # (O, B) bool: where a component can take control
    loc: Tensor | None = None,  # (O, 1|B) descent by (R - loc) / scale; None: raw R
    scale: Tensor | None = None,  # (O, 1|B)
) -> dict[str, Tensor]:
    """One step of Algorithm 2 for a batch (option-first inputs), at most ``tree.max_depth + 1``
    passes.

    A running subtask whose termination holds (``terminated``) hands control to its parent first.
    The descent (line 10) only considers components that can take control (``startable``) and
    compares raw R (the paper) or the margin ``(R - loc) / scale``. Returns ``action``, ``option``
    (the next running subtask), ``hierarchy_level`` (0 = root) and ``interrupted`` (control left a
    running, unterminated subtask), each ``(B,)``.
    """
    start = _control_start(running, terminated, tree)
    O = q_opt.shape[0]  # noqa: E741
    acts = argmax0(q_opt.transpose(0, 1))  # (O, B): pi^o(s_t) of every option
    rob_a = robustness.transpose(0, 1)  # (A, O, B)
    if isinstance(tau, Tensor):
        tau = tau.expand(O, start.shape[0])  # (O, B)
    o = torch.where(start < 0, torch.full_like(start, tree.root), start)  # (B,)
    p = lookup(tree.parent, o)  # (B,)
    pc = p.clamp(min=0)
    a_p = select0(acts, pc)  # (B,) line 1
    tau_p = select0(tau, pc) if isinstance(tau, Tensor) else tau
    regain = (p >= 0) & (select0(select0(robustness, pc), a_p) > tau_p)  # (B,) line 2
    result = torch.where(regain, pc, o)
    done = regain
    node = o
    all_opts = torch.arange(O, device=start.device)
    for _ in range(tree.max_depth + 1):
        a = select0(acts, node)  # (B,) line 5
        tau_n = select0(tau, node) if isinstance(tau, Tensor) else tau
        r_a = select0(rob_a, a)  # (O, B): R(q, s_t, a), a the action of o_run (line 10)
        kids = tree.child_mask.t().index_select(1, node)  # (O, B): q is a component of o_run
        score, _ = _scores(r_a, all_opts, loc, scale, None)
        if startable is not None:
            kids = kids & startable
        score = score.masked_fill(~kids, float("-inf"))
        none_can = ~kids.any(0)  # a leaf, or no component can take control
        ok = none_can | (select0(r_a, node) > tau_n)  # line 6
        result = torch.where(ok & ~done, node, result)
        done = done | ok
        node = torch.where(done, node, argmax0(score))  # line 11: recurse into q*
    return {
        "action": select0(acts, result),
        "option": result,
        keys.HIERARCHY_LEVEL: lookup(tree.depth, result),
        keys.INTERRUPTED: _interrupted(result, running, terminated),
    }


def hierarchy_decide_table_of(
    q_opt: Tensor,  # (O, A, B)
    robustness: Tensor,  # (O, A, B)
    running: Tensor,  # (B,)
    tree: TreeTables,
    tau: float | Tensor,
    terminated: Tensor | None = None,  # (B,)
    startable: Tensor | None = None,  # (O, B)
    loc: Tensor | None = None,  # (O, 1|B)
    scale: Tensor | None = None,  # (O, 1|B)
) -> dict[str, Tensor]:
    """:func:`hierarchy_decide_of` by table lookup, for trees with ``tree.table_option`` set."""
    start = _control_start(running, terminated, tree)
    code = torch.zeros(start.shape, dtype=torch.int64, device=start.device)
    for node, kids, bit, radix in tree.internal:
        a = argmax0(q_opt[node])  # (B,): pi^node(s_t) (lines 1, 5)
        rob_a = robustness.gather(1, a.view(1, 1, -1).expand(robustness.shape[0], 1, -1))
        rob_a = rob_a.squeeze(1)  # (O, B): R(q, s_t, pi^node(s_t)) for every q
        ok = rob_a[node] > _at(tau, node)  # robust under its own action (lines 2, 6)
        score, none_can = _scores(rob_a.index_select(0, kids), kids, loc, scale, startable)
        code = code + ok * bit
        if none_can is not None:  # no component can take control: a descent stops here
            code = code + none_can * (bit << 1)
        code = code + argmax0(score) * radix  # q* of line 10
    code = code + (start + 1) * tree.num_codes
    option = tree.table_option.index_select(0, code)  # (B,)
    return {
        "action": argmax0(select0(q_opt, option)),  # the acting option's greedy action
        "option": option,
        keys.HIERARCHY_LEVEL: tree.table_level.index_select(0, code),
        keys.INTERRUPTED: _interrupted(option, running, terminated),
    }


DESCENTS = ("raw", "normalised")  # line 10's metric: raw R, or (R - tau) / scale per component


class HierarchyController(Controller):
    """HierarchicalSearch (Algorithm 2) over a composition hierarchy; reads Q_o and R heads only.

    Every node of ``hierarchy`` must be an option of the bundle; the root's robustness critic must
    be learnt for the same ``root_policy`` (``train.hierarchy_root_policy``).

    Args:
        heads: a bundle with ``options`` and ``robustness`` heads (and ``averaging`` for
            ``root_policy="averaging"``).
        hierarchy: the tree (config data).
        tau: robustness threshold of every capability (paper §3.4.3), unless ``calibration``.
        root_policy: ``"option"`` or ``"averaging"``.
        subtasks: with them a terminated component hands control back up and the descent picks only
            a component that can start (``Subtasks.startable``); ``None``: the paper's literal
            search.
        descent: line 10's metric, ``"raw"`` (argmax R) or ``"normalised"`` (argmax ``(R - tau_q) /
            scale_q``).
        calibration: per-capability thresholds and scales
            (:class:`~taskvar_torch.heads.robustness.RobustnessCalibration`); replaces ``tau``; may
            be set later.

    See docs/controllers.md for the settings.
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
        subtasks: Subtasks | None = None,
        descent: str = "raw",
        calibration: RobustnessCalibration | None = None,
    ):
        if descent not in DESCENTS:
            raise ValueError(f"descent must be one of {list(DESCENTS)}, got {descent!r}")
        super().__init__(heads, subtasks, seed, root_policy=root_policy, hierarchy=hierarchy)
        self.hierarchy = hierarchy
        self.tau = float(tau)
        self.descent = descent
        self.calibration = calibration
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

    def extra_inputs(self, td: TensorDictBase) -> dict[str, Tensor]:
        """``startable`` ``(B, O)`` when the controller honours termination, beside the base's
        inputs (given policies' actions)."""
        if self.subtasks is None:
            return {}
        return {**super().extra_inputs(td), keys.STARTABLE: self.subtasks.startable(td)}

    def thresholds(self, device: torch.device) -> tuple[float | Tensor, Tensor | None]:
        """``(tau, scale)``: per-option ``(O, 1)`` tensors from the calibration, else ``(tau, None)``."""
        if self.calibration is None:
            return self.tau, None
        return (
            self.calibration.tau.to(device).unsqueeze(-1),
            self.calibration.scale.to(device).unsqueeze(-1),
        )

    def decide_of(
        self, values: Mapping[str, Tensor], running: Tensor, terminated: Tensor | None
    ) -> dict[str, Tensor]:
        q_opt = values[keys.OPTION_ACTION_VALUE]  # (O, A, B)
        tau, scale = self.thresholds(q_opt.device)
        if keys.ROBUSTNESS_TAU in values:  # per-row calibration (O, B)
            tau, scale = values[keys.ROBUSTNESS_TAU], values[keys.ROBUSTNESS_SCALE]
        loc = None
        if self.descent == "normalised":
            loc = tau if isinstance(tau, Tensor) else torch.full_like(q_opt[:, 0, :1], tau)
            scale = scale if scale is not None else torch.ones_like(loc)
        tree = self.tree(q_opt.device)
        decide = hierarchy_decide_of if tree.table_option is None else hierarchy_decide_table_of
        return decide(
            q_opt,
            values[keys.ROBUSTNESS],
            running,
            tree,
            tau,
            terminated,
            values.get(keys.STARTABLE),
            loc,
            scale,
        )

    def decide_scalar(
        self, values: Mapping[str, list], running: int, terminated: bool
    ) -> dict[str, Any]:
        q, rob = values[keys.OPTION_ACTION_VALUE], values[keys.ROBUSTNESS]
        t = self._tree_lists
        O = len(q)  # noqa: E741
        if self.calibration is None:
            tau, scale = [self.tau] * O, [1.0] * O
        else:
            tau, scale = self.calibration.tau.tolist(), self.calibration.scale.tolist()
        can = values.get(keys.STARTABLE, [True] * O)
        normalised = self.descent == "normalised"

        def score(k: int, a: int) -> float:
            if not can[k]:
                return float("-inf")
            return (rob[k][a] - tau[k]) / scale[k] if normalised else rob[k][a]

        o = t["root"] if running < 0 else running
        if terminated and running >= 0 and t["parent"][o] >= 0:  # control returns up
            o = t["parent"][o]
        p = t["parent"][o]
        if p >= 0 and rob[p][first_argmax(q[p])] > tau[p]:  # lines 1-3
            node = p
        else:
            node = o
            while True:
                a = first_argmax(q[node])  # line 5
                kids = [k for k in t["children"][node] if can[k]]
                if not kids or rob[node][a] > tau[node]:  # line 6 (leaves always act)
                    break
                node = kids[first_argmax([score(k, a) for k in kids])]  # lines 9-11
        return {
            "action": first_argmax(q[node]),
            "option": node,
            keys.HIERARCHY_LEVEL: t["depth"][node],
            keys.INTERRUPTED: running >= 0 and node != running and not terminated,
        }
