"""The oracle protocol: what a family's exact oracle offers (docs/oracle.md, docs/families.md), as
structural ``typing.Protocol`` s.

:class:`OracleTables`: the exact tables of the paper's heads on the training distribution (§3.1-3.3)
and their instance set and quadrature. :class:`ExactOracle`: the tables plus what ``taskvar eval``
reads per episode: controllers as Markov chains (Algorithms 1-2), the per-instance optimum and the
tables' heads bundle. An instance is the family's fields, positionally in ``instance_keys`` order
(scalars or ``(B,)``). Optional members: ``obs_encoding``, ``exact_solves`` / ``max_exact_solves``,
``step_solves`` / ``max_step_solves``.
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
