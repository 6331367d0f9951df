"""The windy family (paper §3.3.1): its dynamics, env, Gymnasium wrapper, instances, options,
exact oracles, rendering and the Figure 2 experiment, in one package (docs/families.md).

Modules: :mod:`.dynamics` (pure batched transitions, layouts), :mod:`.env` (the TorchRL env),
:mod:`.gym_env` (the Gymnasium env), :mod:`.instances`, :mod:`.subtasks` (exit options),
:mod:`.oracle` (:class:`WindyOracle`, exact tables), :mod:`.sparse_oracle` (any grid size),
:mod:`.replay_reference`, :mod:`.learnt` and :mod:`.head_report` (learnt heads measured exactly),
:mod:`.render`, :mod:`.oracle_table`, :mod:`.fig2` with :mod:`.fig2_metrics` and
:mod:`.fig2_report` (the paper's Figure 2), and :mod:`.family` (the declaration).

The exact oracle. Exact tabular oracle for the windy family (paper §3.1-3.4, Definition 1, Algorithms 1-2).

Small windy instances are solved exactly in torch (float64, batched over instances). The oracle
computes the mean-MDP averaging optimum (paper §3.1), each exit option's averaging policy (§3.2),
the averaging switching values ``Q_mu`` and ``mu_bar`` (§3.2), per-instance option values
``Q^{m,mu_bar}`` and the max-values ``Q_hat`` (§3.3, Definition 1), policy evaluation, and the exact
expected return of every controller (Algorithms 1 and 2) in a given instance. It exposes its tables
as a :class:`~taskvar_torch.heads.bundle.Heads` bundle, so controllers run on the oracle exactly as
on trained networks.

Design decisions (documented here once):

- **Values are discounted.** Everything compared against the networks (``averaging_q``,
  ``option_q``, ``switching_q``, ``max_value``, :meth:`WindyOracle.evaluate`) is an
  infinite-horizon *discounted* value with ``gamma`` (default 0.99): the networks see no time, and
  truncation at the horizon is bootstrapped, so this is what they estimate. The Bellman operator
  is then a ``gamma``-contraction and value iteration terminates even when ``p = 1`` makes an exit
  unreachable: a policy that never arrives is worth ``-1 / (1 - gamma)`` (-100 at 0.99).
  Value iteration stops when the sup-norm change certifies an error below ``tol``; a policy
  iteration polish (exact linear solves) then makes the greedy policy and its values exact.
- **Returns are finite-horizon and undiscounted.** Episode returns (what experiments print, paper
  §3.3.1: "ranging from -100 to 0") are exact ``horizon``-step undiscounted returns computed by
  backward induction over steps-to-go. This is exact for stationary policies and for controllers
  whose decision depends on (cell, carried controller state) only, which is the case for all four
  controllers here (Markov chain on (cell, running option)).
- **Mean MDP** (paper §3.1). ``T`` is affine in ``p`` for a fixed direction, so for the training
  distribution ``p ~ U[p_low, p_high]``, ``dir`` uniform, the mean MDP is exactly
  ``mean_dir T(p = E[p], dir)``; for a finite ``points`` set it is the mean of the points' models.
  The reward (-1 per non-goal step) does not vary across the family.
- **Expectations over instances** (e.g. the expected return of a fixed policy when the instance is
  drawn once per episode and held fixed) use Gauss-Legendre quadrature in ``p`` with
  ``ceil(horizon / 2)`` nodes (50 at horizon 100), times the uniform mean over directions (or the
  mean over ``points``). The ``horizon``-step return of a fixed controller is a polynomial of degree
  ``<= horizon - 1`` in ``p`` (each step's kernel is affine in ``p``), and ``n``-node Gauss-Legendre
  is exact to degree ``2n - 1``, so these expectations are exact up to rounding. Note this is *not*
  the mean-MDP value: the mean MDP redraws the instance at every step, the episode holds it fixed.
- **Q_hat's instance set.** Definition 1 takes a max over training instances; by default the set
  is the ``p_grid`` (21 evenly spaced values over ``[p_low, p_high]``, endpoints included) times the
  training directions, or the ``points`` of a finite training distribution. Pass any set to
  :meth:`WindyOracle.max_value`.
- **Ties.** The default layout is symmetric, so exact ties are common (north vs south from the
  middle row). Tables are *tie-snapped*: values within ``TIE_ATOL`` (1e-9) of a row maximum are set
  to that maximum, and ``Q_hat`` values within ``TIE_ATOL`` of ``V^{mu_bar}`` are set equal to it. So
  ``argmax`` (lowest index on ties) and the strict ``<`` of Algorithm 1 line 6 give the same decisions
  in the controllers as in the oracle, regardless of floating-point noise. Heads default to
  float64 so that no two distinct values collapse in a cast.
- **Controllers** (:meth:`WindyOracle.controller_return`) are evaluated exactly as Markov chains on
  (cell, carried state): the state is the option/subtask that acted last step (or none), the
  decision kernel is tabulated from the heads' outputs at every cell (any :class:`Heads`: the
  oracle's tables or trained networks) by the controller's own rule (Algorithms 1 and 2 of
  ``controllers/``). :meth:`WindyOracle.controller_fire_count` gives the exact expected number of
  interruptions (Algorithm 1) or control moves (Algorithm 2) per episode.
- **Where interruption matters.** With the paper's training distribution the oracle's own tables
  satisfy Definition 1's condition at 12 (cell, option) pairs on every shipped layout, but none is
  reached while that option runs (from any start cell, in any instance): options and interruption
  have identical exact returns. (Wall cells are states of the tables too; ignore them.) Trained
  on south winds only, ``whole_column_windy`` makes interruption fire (up to 0.4 times per episode)
  and changes returns by up to 38 steps in north-wind instances.

Examples:
    >>> oracle = WindyOracle("default")
    >>> oracle.averaging_policy().shape, oracle.option_q().shape
    (torch.Size([25]), torch.Size([2, 25, 4]))
    >>> v = oracle.expected_return(oracle.averaging_policy(), "train", starts=None)  # (S,)
"""

from importlib import import_module
from typing import Any

_LAZY = {
    "ReplayReference": "replay_reference",
    "WindyGridEnv": "env",
    "WindyInstances": "instances",
    "WindyLayout": "dynamics",
    "WindyModel": "dynamics",
    "WindyOracle": "oracle",
    "WindySubtasks": "subtasks",
    "exact_returns": "learnt",
    "firing_values": "learnt",
    "learnt_vs_oracle_by_start": "learnt",
    "make_layout": "dynamics",
}
"""The package's names, imported from their module on first use (``import taskvar_torch`` reads
the family's declaration only, not its oracles)."""


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_LAZY])


__all__ = [
    "ReplayReference",
    "WindyGridEnv",
    "WindyInstances",
    "WindyLayout",
    "WindyModel",
    "WindyOracle",
    "WindySubtasks",
    "exact_returns",
    "firing_values",
    "learnt_vs_oracle_by_start",
    "make_layout",
]
