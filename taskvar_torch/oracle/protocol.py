"""The oracle protocol: what a family's exact oracle offers (docs/oracle.md, docs/families.md).

Two levels, each a ``typing.Protocol`` (structural: an oracle implements it by having the
members, no base class needed; ``isinstance`` checks the names):

- :class:`OracleTables`: the exact tables of the paper's heads on the training distribution
  (§3.1 the averaging policy on the mean MDP, §3.2 the options and switching values, §3.3
  Definition 1's max-values) and the instance set and quadrature they are computed over. The
  windy oracles (:class:`~taskvar_torch.families.windy.oracle.WindyOracle`,
  :class:`~taskvar_torch.families.windy.sparse_oracle.SparseWindyOracle`) and Taxi's
  (:class:`~taskvar_torch.families.taxi.oracle.TaxiOracle`) implement it.
- :class:`ExactOracle`: the tables plus the exact evaluation ``taskvar eval`` reads per episode
  (:mod:`~taskvar_torch.oracle.episodes`, regret by step): the controllers as Markov chains
  (Algorithms 1-2, :mod:`~taskvar_torch.oracle.chains`), the per-instance optimum and the heads
  bundle of the tables. ``Family.oracle`` returns one (``WindyOracle``, ``TaxiOracle``).

An instance is given by the family's fields, positionally, in the order of ``instance_keys``
(windy: ``p, direction``; Taxi: ``rainy_probability, fickle_probability``); scalars or ``(B,)``.
Optional members the evaluation reads where present: ``obs_encoding`` (the observation learnt
heads read, else the family's), ``exact_solves`` / ``max_exact_solves`` and ``step_solves`` /
``max_step_solves`` (a bound on the distinct instances solved per call).
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import torch

from taskvar_torch.heads.bundle import Heads

Tensor = torch.Tensor


@runtime_checkable
class OracleTables(Protocol):
    """Exact tables of the heads over a family's states ``S`` and options ``O`` (paper §3.1-3.3)."""

    option_names: tuple[str, ...]
    gamma: float  # discount of the values (the networks' gamma)
    horizon: int  # episode length of the returns
    S: int
    O: int  # noqa: E741
    start_cells: Tensor  # (K,) the episode's start states
    is_goal: Tensor  # (S,) bool

    def instance_set(self, instances: Any = None) -> tuple[Tensor, ...]:
        """The finite instance set of Definition 1's max (``None``: the training one), as the
        instance fields, each ``(M,)``."""
        ...

    def quadrature(self, instances: Any = None) -> tuple[Tensor, ...]:
        """Instance fields ``(K,)`` and weights ``(K,)`` integrating over a distribution."""
        ...

    def averaging_q(self) -> Tensor:
        """``Q_avg (S, A)``: the optimal values of the mean MDP (§3.1)."""
        ...

    def averaging_policy(self) -> Tensor:
        """``(S,)`` int64: greedy in :meth:`averaging_q` (lowest index on ties)."""
        ...

    def option_q(self) -> Tensor:
        """``Q_o (O, S, A)``: each option's optimal values on its subtask reward (§3.2)."""
        ...

    def option_policies(self) -> Tensor:
        """``pi^o (O, S)`` int64: greedy in :meth:`option_q`."""
        ...

    def switching_q(self) -> Tensor:
        """``Q_mu (S, O)``: option values of mu_bar on the mean MDP (§3.2)."""
        ...

    def v_mu_bar(self) -> Tensor:
        """``V^{mu_bar}(s) (S,)``: Definition 1's right-hand side."""
        ...

    def instance_option_q(self, *fields: Any) -> Tensor:
        """``Q^{m, mu_bar}(s, o)`` in the instances ``fields`` (Definition 1's left-hand side)."""
        ...

    def max_value(self, instances: Any = None) -> Tensor:
        """``Q_hat (S, O)``: the max over :meth:`instance_set` of :meth:`instance_option_q`."""
        ...

    def expected_return(
        self, policy: Tensor, instances: Any = None, starts: Any = "uniform"
    ) -> Tensor:
        """``E_m[return]`` of a stationary policy ``(S,)`` (instance drawn per episode)."""
        ...


@runtime_checkable
class ExactOracle(OracleTables, Protocol):
    """:class:`OracleTables` plus exact evaluation of controllers and of the per-instance optimum."""

    instance_keys: tuple[str, ...]  # the ("instance", key) fields an episode holds, in order

    def heads(self, *args: Any, **kwargs: Any) -> Heads:
        """The tables as a :class:`Heads` bundle (averaging, options, switching, max-value)."""
        ...

    def controller_chain(self, controller: Any, **kwargs: Any) -> dict[str, Tensor]:
        """A controller (a name or a ``Controller``) as a Markov chain on (state, carried state):
        ``decision (S, Z, N)``, ``action (S, N)``, ``next_state (N,)``, ``fires (S, Z)``."""
        ...

    def controller_return(self, controller: Any, *fields: Any, **kwargs: Any) -> Tensor:
        """Exact expected ``horizon``-step return ``(B, S)`` of a controller in instances
        ``fields`` (``start=None``: every start state)."""
        ...

    def controller_expected_return(
        self, controller: Any, instances: Any = None, starts: Any = "uniform", **kwargs: Any
    ) -> Tensor:
        """A controller's exact expected return over an instance distribution."""
        ...

    def optimal_return(self, *fields: Any, **kwargs: Any) -> Tensor:
        """Exact per-instance optimal ``horizon``-step return ``(B, S)``: the regret ceiling."""
        ...

    def step_regret(self, *fields_and_trace: Any, **kwargs: Any) -> Tensor:
        """``(B, T)`` instantaneous regret ``V*_{H-t}(s_t) - Q*_{H-t}(s_t, a_t)`` of played
        episodes: the instance fields, then ``cells``, ``actions`` ``(B, T)`` and ``alive``."""
        ...


__all__ = ["ExactOracle", "OracleTables"]
