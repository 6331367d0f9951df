"""Algorithm 2's one implementation is the paper's recursion, and the kept second forms of
Algorithms 1 and 2 equal the one implementation, on random inputs.

One batched implementation per algorithm (``interruption_decide_of``, ``hierarchy_decide_of``);
two faster forms kept beside them (benchmarks/decision_forms.py, docs/benchmarks.md): the table
lookup of Algorithm 2 (``hierarchy_decide_table_of``) and the controllers' scalar rule for one
environment (``decide_scalar``). Inputs are integer-valued, so ties (tie-breaking) and values at
the threshold (strictness) are frequent.
"""

from __future__ import annotations

import dataclasses

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from taskvar_torch import keys
from taskvar_torch.controllers import HierarchyController, InterruptionController
from taskvar_torch.controllers.hierarchy import (
    TreeTables,
    hierarchy_decide_of,
    hierarchy_decide_table_of,
)
from taskvar_torch.heads.robustness import RobustnessCalibration
from taskvar_torch.oracle import table_heads
from taskvar_torch.subtasks import Hierarchy

torch.set_num_threads(1)

A = 4
TREES = [
    (Hierarchy(root="TG+FE", children={"TG+FE": ("TG", "FE")}), ("TG", "FE", "TG+FE")),
    (
        Hierarchy(root="root", children={"root": ("A", "B"), "A": ("A1", "A2")}),
        ("root", "A", "B", "A1", "A2"),
    ),
    (  # three components under the root, one composed: another radix
        Hierarchy(root="r", children={"r": ("x", "y", "z"), "y": ("y1", "y2", "y3")}),
        ("y3", "r", "x", "y", "z", "y1", "y2"),
    ),
]
CASE = dict(
    seed=st.integers(0, 2**31 - 1),
    tree=st.integers(0, len(TREES) - 1),
    batch=st.integers(1, 64),
    terminated=st.booleans(),
    startable=st.booleans(),
)


def ints(g: torch.Generator, *shape: int, low: int = -2, high: int = 2) -> torch.Tensor:
    return torch.randint(low, high, shape, generator=g).to(torch.float64)


def hierarchy_case(seed, tree, batch, terminated, startable):
    """Random option-first inputs of Algorithm 2 for ``batch`` states of tree ``tree``."""
    h, names = TREES[tree]
    O = len(names)  # noqa: E741
    g = torch.Generator().manual_seed(seed)
    x = {
        "q_opt": ints(g, O, A, batch),
        "robustness": ints(g, O, A, batch),
        "running": torch.randint(-1, O, (batch,), generator=g),
        "terminated": torch.rand(batch, generator=g) < 0.3 if terminated else None,
        "startable": torch.rand(O, batch, generator=g) < 0.7 if startable else None,
    }
    return h, names, g, x


@settings(max_examples=300, deadline=None)
@given(**CASE, thresholds=st.sampled_from(["scalar", "per_option", "per_row", "normalised"]))
def test_table_form_equals_the_search(seed, tree, batch, terminated, startable, thresholds):
    h, names, g, x = hierarchy_case(seed, tree, batch, terminated, startable)
    O = len(names)  # noqa: E741
    tt = TreeTables.build(h, names)
    assert tt.table_option is not None
    tau, loc, scale = 0.0, None, None
    if thresholds == "per_option":
        tau = ints(g, O, 1)
    elif thresholds == "per_row":
        tau = ints(g, O, batch)
    elif thresholds == "normalised":  # descent by (R - tau) / scale
        tau = ints(g, O, 1)
        loc, scale = tau, torch.randint(1, 4, (O, 1), generator=g).to(torch.float64)
    args = (x["q_opt"], x["robustness"], x["running"], tt, tau, x["terminated"], x["startable"])
    walk = hierarchy_decide_of(*args, loc, scale)
    table = hierarchy_decide_table_of(*args, loc, scale)
    assert walk.keys() == table.keys()
    for k in walk:
        assert torch.equal(walk[k], table[k]), k


def literal_search(h: Hierarchy, names, q, rob, tau, running, ended, can) -> int:
    """Algorithm 2 as the paper writes it, recursive, for one state (``q``, ``rob``: ``[O][A]``
    lists; ``can``: ``[O]`` bool or None): the option whose action is returned."""
    act = [max(range(A), key=lambda a: (q[o][a], -a)) for o in range(len(names))]

    def parent_of(o: int) -> int | None:
        p = h.parent(names[o])
        return None if p is None else names.index(p)

    def search(o_run: int, p: int | None) -> int:  # HierarchicalSearch(K, o_run, p, tau, s)
        if p is not None and rob[p][act[p]] > tau:  # lines 1-3
            return p
        a = act[o_run]  # line 5
        kids = [names.index(k) for k in h.components(names[o_run])]
        kids = [k for k in kids if can is None or can[k]]
        if not kids or rob[o_run][a] > tau:  # line 6
            return o_run
        q_star = max(kids, key=lambda k: (rob[k][a], -k))  # line 10 (first on ties)
        return search(q_star, o_run)  # line 11

    o = names.index(h.root) if running < 0 else running
    if ended and running >= 0 and parent_of(o) is not None:  # control returns up the tree
        o = parent_of(o)
    return search(o, parent_of(o))


@settings(max_examples=200, deadline=None)
@given(**CASE)
def test_the_search_is_the_papers_recursion(seed, tree, batch, terminated, startable):
    h, names, g, x = hierarchy_case(seed, tree, batch, terminated, startable)
    args = (x["q_opt"], x["robustness"], x["running"], TreeTables.build(h, names), 0.0)
    out = hierarchy_decide_of(*args, x["terminated"], x["startable"])
    for i in range(batch):
        want = literal_search(
            h,
            names,
            x["q_opt"][..., i].tolist(),
            x["robustness"][..., i].tolist(),
            0.0,
            int(x["running"][i]),
            x["terminated"] is not None and bool(x["terminated"][i]),
            None if x["startable"] is None else x["startable"][:, i].tolist(),
        )
        assert out["option"][i].item() == want, i


@settings(max_examples=150, deadline=None)
@given(**CASE, descent=st.sampled_from(["raw", "normalised"]), calibrated=st.booleans())
def test_scalar_hierarchy_equals_the_search(
    seed, tree, batch, terminated, startable, descent, calibrated
):
    h, names, g, x = hierarchy_case(seed, tree, batch, terminated, startable)
    O = len(names)  # noqa: E741
    one_state = x["q_opt"][..., :1].permute(2, 0, 1)
    heads = table_heads(names, options=one_state, robustness=one_state)
    ctrl = HierarchyController(heads, h, tau=-1.0, descent=descent)
    if calibrated:
        ctrl.calibration = RobustnessCalibration(
            ints(g, O), torch.randint(1, 4, (O,), generator=g).to(torch.float64)
        )
    values = {keys.OPTION_ACTION_VALUE: x["q_opt"], keys.ROBUSTNESS: x["robustness"]}
    if x["startable"] is not None:
        values[keys.STARTABLE] = x["startable"]
    cpu = torch.device("cpu")  # no table: decide_of runs the search itself
    ctrl._trees[cpu] = dataclasses.replace(ctrl.tree(cpu), table_option=None, table_level=None)
    batched = ctrl.decide_of(values, x["running"], x["terminated"])
    for i in range(batch):
        one = ctrl.decide_scalar(
            {k: v[..., i].tolist() for k, v in values.items()},
            int(x["running"][i]),
            x["terminated"] is not None and bool(x["terminated"][i]),
        )
        for k in ("action", "option", keys.HIERARCHY_LEVEL, keys.INTERRUPTED):
            assert one[k] == batched[k][i].item(), (k, i)


@settings(max_examples=200, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    options=st.integers(1, 5),
    batch=st.integers(1, 64),
    interrupt=st.booleans(),
    terminated=st.booleans(),
    initiation=st.booleans(),
)
def test_scalar_interruption_equals_the_batched_rule(
    seed, options, batch, interrupt, terminated, initiation
):
    """Algorithm 1 with a greedy mu_bar (the softmax draw is a random stream: its per-state
    distribution is checked against the oracle's chain in test_controllers.py)."""
    O = options  # noqa: E741
    g = torch.Generator().manual_seed(seed)
    names = tuple(f"o{k}" for k in range(O))
    heads = table_heads(
        names,
        averaging=ints(g, 1, A),
        options=ints(g, 1, O, A),
        switching=ints(g, 1, O),
        max_value=ints(g, 1, O),
    )
    ctrl = InterruptionController(heads)
    ctrl.interrupt = interrupt  # False: the options controller (no lines 6-9)
    values = {
        keys.OPTION_ACTION_VALUE: ints(g, O, A, batch),
        keys.OPTION_VALUE: ints(g, O, batch),
        keys.MAX_VALUE: ints(g, O, batch),
        keys.ACTION_VALUE: ints(g, A, batch),
    }
    if initiation:
        values[keys.INITIABLE] = torch.rand(O, batch, generator=g) < 0.6
    running = torch.randint(-1, O, (batch,), generator=g)
    ended = torch.rand(batch, generator=g) < 0.3 if terminated else None
    if not initiation:  # as the controller reads them: no averaging head without I_o
        values.pop(keys.ACTION_VALUE)
    batched = ctrl.decide_of(values, running, ended)
    for i in range(batch):
        one = ctrl.decide_scalar(
            {k: v[..., i].tolist() for k, v in values.items()},
            int(running[i]),
            ended is not None and bool(ended[i]),
        )
        for k in ("action", "option", keys.INTERRUPTED):
            assert one[k] == batched[k][i].item(), (k, i)
