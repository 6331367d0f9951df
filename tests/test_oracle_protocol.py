"""The oracle protocol (taskvar_torch/oracle/protocol.py): the windy and Taxi oracles implement it,
with the members' arguments in the protocol's order, and a family's ``oracle`` returns one."""

from __future__ import annotations

import inspect

import pytest

from taskvar_torch.config import load_config
from taskvar_torch.families import family
from taskvar_torch.families.taxi.oracle import TaxiOracle
from taskvar_torch.families.windy.oracle import WindyOracle
from taskvar_torch.families.windy.sparse_oracle import SparseWindyOracle
from taskvar_torch.oracle.protocol import ExactOracle, OracleTables

ORACLES = {
    "windy": (WindyOracle, ExactOracle),
    "windy_sparse": (SparseWindyOracle, OracleTables),
    "taxi": (TaxiOracle, ExactOracle),
}


def members(protocol: type) -> list[str]:
    """The protocol's attributes and methods (its own and its bases')."""
    annotated = [n for c in protocol.__mro__ for n in getattr(c, "__annotations__", {})]
    return sorted({n for n in (*dir(protocol), *annotated) if not n.startswith("_")})


@pytest.mark.parametrize("name", list(ORACLES))
def test_each_oracle_implements_its_protocol(name):
    cls, protocol = ORACLES[name]
    oracle = cls()
    assert isinstance(oracle, protocol)
    assert isinstance(oracle, OracleTables)
    for m in members(protocol):
        assert hasattr(oracle, m), (name, m)
        want = getattr(protocol, m, None)
        if not callable(want):
            continue
        # keyword parameters the protocol names come in the same order (positional fields are
        # the family's own: windy's p, direction; Taxi's q, f)
        got = [p for p in inspect.signature(getattr(oracle, m)).parameters]
        named = [
            p.name
            for p in inspect.signature(want).parameters.values()
            if p.kind is p.POSITIONAL_OR_KEYWORD and p.name != "self"
        ]
        assert [p for p in got if p in named] == named, (name, m, got, named)
    assert len(oracle.instance_keys) == len(oracle.instance_set()), name
    assert len(oracle.quadrature()) == len(oracle.instance_keys) + 1, name


@pytest.mark.parametrize("config", ["configs/windy.yaml", "configs/taxi.yaml"])
def test_a_familys_oracle_is_an_exact_oracle(config):
    cfg = load_config(config)
    oracle = family(cfg).oracle(cfg)
    assert isinstance(oracle, ExactOracle)
