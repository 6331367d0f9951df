"""Exact tabular oracle for the windy family (paper §3.1-3.4, Definition 1, Algorithms 1-2).

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
  oracle's tables or trained networks) by an implementation of Algorithms 1 and 2 independent of
  ``controllers/``. :meth:`WindyOracle.controller_fire_count` gives the exact expected number of
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

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import cached_property
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn

from taskvar_torch import keys
from taskvar_torch.envs import windy
from taskvar_torch.envs.instances import WindyInstances, windy_instances
from taskvar_torch.envs.windy_env import observation_table, resolve_layout
from taskvar_torch.heads.bundle import HEAD_OUT_KEYS, Heads
from taskvar_torch.subtasks.base import Hierarchy, Subtasks
from taskvar_torch.subtasks.windy import WindySubtasks

TIE_ATOL = 1e-9
"""Values closer than this are treated as equal (see "Ties" above)."""

CONTROLLER_NAMES = ("averaging", "options", "interruption", "hierarchy")

Tensor = torch.Tensor


# --------------------------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------------------------


def snap_ties(q: Tensor, atol: float = TIE_ATOL) -> Tensor:
    """Set entries within ``atol`` of their row maximum (last dim) to that maximum."""
    m = q.max(-1, keepdim=True).values  # (..., 1)
    return torch.where(q >= m - atol, m.expand_as(q), q)


def greedy(q: Tensor, atol: float = TIE_ATOL) -> Tensor:
    """``argmax`` over the last dim, lowest index among entries within ``atol`` of the maximum."""
    return snap_ties(q, atol).argmax(-1)


def gauss_legendre(n: int, low: float, high: float) -> tuple[Tensor, Tensor]:
    """Nodes and weights (summing to 1) of ``n``-point Gauss-Legendre for the uniform law on [low, high]."""
    if high <= low:
        return torch.tensor([float(low)], dtype=torch.float64), torch.ones(1, dtype=torch.float64)
    x, w = np.polynomial.legendre.leggauss(int(n))
    p = 0.5 * (high - low) * x + 0.5 * (high + low)
    return torch.as_tensor(p, dtype=torch.float64), torch.as_tensor(w / 2.0, dtype=torch.float64)


class TableLookup(nn.Module):
    """A head backed by a table: ``forward(cell) -> table[cell]`` (or argmax of a one-hot observation).

    Args:
        table: ``(S, ...)`` values per cell.
        one_hot: read a one-hot observation ``(..., S)`` instead of an integer cell.
    """

    def __init__(self, table: Tensor, one_hot: bool = False):
        super().__init__()
        self.register_buffer("table", table)
        self.one_hot = one_hot

    def forward(self, x: Tensor) -> Tensor:
        idx = x.argmax(-1) if self.one_hot else x  # (...,)
        return self.table[idx]  # (..., *table.shape[1:])


def table_heads(
    option_names: Sequence[str],
    *,
    averaging: Tensor | None = None,  # (S, A)
    options: Tensor | None = None,  # (S, O, A)
    switching: Tensor | None = None,  # (S, O)
    max_value: Tensor | None = None,  # (S, O)
    robustness: Tensor | None = None,  # (S, O, A)
    in_key: Any = keys.CELL,
    softmax_temperature: float | None = None,
) -> Heads:
    """A :class:`Heads` bundle whose heads gather rows of tables indexed by the cell.

    ``in_key`` is ``keys.CELL`` (integer cell) or ``keys.OBSERVATION`` (one-hot observation).
    """
    one_hot = in_key != keys.CELL

    def mod(table: Tensor | None, out_key: str) -> TensorDictModule | None:
        if table is None:
            return None
        return TensorDictModule(TableLookup(table, one_hot), in_keys=[in_key], out_keys=[out_key])

    return Heads(
        option_names,
        averaging=mod(averaging, keys.ACTION_VALUE),
        options=mod(options, keys.OPTION_ACTION_VALUE),
        switching=mod(switching, keys.OPTION_VALUE),
        max_value=mod(max_value, keys.MAX_VALUE),
        robustness=mod(robustness, keys.ROBUSTNESS),
        softmax_temperature=softmax_temperature,
    )


def _policy_kernel(P: Tensor, policy: Tensor) -> Tensor:
    """``P_pi[b, s, s']`` for a deterministic ``(S,)`` / ``(B, S)`` or stochastic ``(S, A)`` policy."""
    B, S, A, _ = P.shape
    if policy.is_floating_point():  # (S, A) probabilities
        return torch.einsum("bsat,sa->bst", P, policy.to(P.dtype))
    pol = policy.to(torch.int64).expand(B, S)  # (B, S)
    return P.gather(2, pol.view(B, S, 1, 1).expand(B, S, 1, S)).squeeze(2)  # (B, S, S)


def _policy_reward(R: Tensor, policy: Tensor) -> Tensor:
    """``r_pi[b, s]`` from ``R (B, S, A)``."""
    B, S, _ = R.shape
    if policy.is_floating_point():
        return (R * policy.to(R.dtype)).sum(-1)
    return R.gather(2, policy.to(torch.int64).expand(B, S).unsqueeze(-1)).squeeze(-1)


def solve_mdp(
    P: Tensor,  # (..., S, A, S')
    R: Tensor,  # (..., S, A)
    gamma: float,
    cont: Tensor | None = None,  # (..., S') in [0, 1]: 1 - termination of the next state
    tol: float = 1e-10,
    max_iter: int = 1_000_000,
) -> Tensor:
    """Optimal ``Q (..., S, A)`` of a discounted MDP: value iteration, then a policy-iteration polish.

    ``Q(s,a) = R(s,a) + gamma sum_s' P(s,a,s') cont(s') max_a' Q(s',a')``. Value iteration stops once
    ``gamma/(1-gamma) ||V_k - V_{k-1}|| < tol`` (a contraction: always terminates for gamma < 1);
    the greedy policy is then improved with exact linear-solve evaluations until it is stable.
    """
    if not 0.0 <= gamma < 1.0:
        raise ValueError(f"gamma must be in [0, 1), got {gamma}")
    batch = P.shape[:-3]
    S, A = P.shape[-3], P.shape[-2]
    Pf = P.reshape(-1, S, A, S)  # (B, S, A, S)
    Rf = R.reshape(-1, S, A)  # (B, S, A)
    c = torch.ones(Pf.shape[0], S, dtype=P.dtype, device=P.device)
    if cont is not None:
        c = c * cont.reshape(-1, S)
    Pc = Pf * c.unsqueeze(1).unsqueeze(1)  # (B, S, A, S): discount-free continuation kernel
    V = torch.zeros(Pf.shape[0], S, dtype=P.dtype, device=P.device)
    bound = tol * (1.0 - gamma) / max(gamma, 1e-300)
    for _ in range(max_iter):
        Q = Rf + gamma * torch.einsum("bsat,bt->bsa", Pc, V)
        V_new = Q.max(-1).values
        delta = (V_new - V).abs().max()
        V = V_new
        if gamma == 0.0 or bool(delta < bound):
            break
    else:  # pragma: no cover - a contraction always converges
        raise RuntimeError("value iteration did not converge")
    pi = greedy(Q)  # (B, S)
    eye = torch.eye(S, dtype=P.dtype, device=P.device)
    for _ in range(1000):  # policy iteration polish: exact values of the greedy policy
        Ppi = _policy_kernel(Pc, pi)  # (B, S, S)
        rpi = _policy_reward(Rf, pi)  # (B, S)
        Vpi = torch.linalg.solve(eye - gamma * Ppi, rpi.unsqueeze(-1)).squeeze(-1)  # (B, S)
        Q = Rf + gamma * torch.einsum("bsat,bt->bsa", Pc, Vpi)
        pi_new = greedy(Q)
        # keep the current action unless another is better by more than the tie tolerance
        cur = Q.gather(-1, pi.unsqueeze(-1)).squeeze(-1)
        better = Q.max(-1).values > cur + TIE_ATOL
        if not bool(better.any()):
            break
        pi = torch.where(better, pi_new, pi)
    return snap_ties(Q).reshape(*batch, S, A)


# --------------------------------------------------------------------------------------------
# the oracle
# --------------------------------------------------------------------------------------------


class WindyOracle:
    """Exact solver of a windy layout's family (docs/oracle.md).

    Args:
        model_or_layout: a :class:`~taskvar_torch.envs.windy.WindyModel`, a layout, a layout name
            (``default``, ``middle_exits``, ``whole_column_windy``) or a map string.
        gamma: discount of the values compared against the networks.
        horizon: episode length of the returns (default :func:`windy.default_horizon`, 100 on 5x5).
        train_instances: the training distribution (name, dict or :class:`WindyInstances`).
        wrong_exit_penalty: subtask penalty for reaching the goal through another exit
            (:class:`~taskvar_torch.subtasks.windy.WindySubtasks`).
        p_grid: ``p`` values of Q_hat's default instance set: an int (evenly spaced over
            ``[p_low, p_high]``) or a sequence of values.
        mu_temperature: ``None`` for a greedy mu_bar, else the temperature of a softmax mu_bar.
        quad_nodes: Gauss-Legendre nodes for expectations over ``p`` (default ``ceil(horizon/2)``:
            exact for returns).
        tol: value-iteration stopping tolerance.
        device: torch device of the tables.
    """

    def __init__(
        self,
        model_or_layout: windy.WindyModel | windy.WindyLayout | str = "default",
        gamma: float = 0.99,
        horizon: int | None = None,
        train_instances: str | dict | WindyInstances = "train",
        wrong_exit_penalty: float = 100.0,
        p_grid: int | Sequence[float] = 21,
        mu_temperature: float | None = None,
        quad_nodes: int | None = None,
        tol: float = 1e-10,
        device: torch.device | str = "cpu",
    ):
        if isinstance(model_or_layout, windy.WindyModel):
            layout = model_or_layout.layout
        else:
            layout = resolve_layout(model_or_layout)
        if not 0.0 <= gamma < 1.0:
            raise ValueError(f"gamma must be in [0, 1), got {gamma}")
        self.layout = layout
        self.device = torch.device(device)
        self.model = windy.WindyModel(layout, self.device)
        self.gamma = float(gamma)
        self.horizon = int(horizon) if horizon is not None else windy.default_horizon(layout)
        if self.horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        self.train_instances = windy_instances(train_instances)
        self.subtasks = WindySubtasks(self.model, wrong_exit_penalty)
        self.option_names = self.subtasks.names
        self.mu_temperature = mu_temperature
        self.quad_nodes = (
            int(quad_nodes) if quad_nodes is not None else max(1, math.ceil(self.horizon / 2))
        )
        self.tol = float(tol)
        ti = self.train_instances
        if isinstance(p_grid, int):
            if p_grid < 1:
                raise ValueError(f"p_grid must be >= 1 or a sequence of p values, got {p_grid}")
            grid = torch.linspace(ti.p_low, ti.p_high, p_grid, dtype=torch.float64)
        else:
            grid = torch.as_tensor(list(p_grid), dtype=torch.float64)
            if grid.numel() == 0 or bool(((grid < 0) | (grid > 1)).any()):
                raise ValueError(f"p_grid values must be in [0, 1], got {list(p_grid)}")
        self.p_grid = grid.to(self.device)
        self.S, self.A, self.O = (
            self.model.num_cells,
            self.model.num_actions,
            len(self.option_names),
        )
        self.start_cells = self.model.start_cells  # (K,)
        self.is_goal = self.model.is_goal  # (S,)

    # ---- models -----------------------------------------------------------------------------

    def _f(self, x: Any) -> Tensor:
        return torch.as_tensor(x, dtype=torch.float64, device=self.device)

    def _instances_arg(self, p: Any, direction: Any) -> tuple[Tensor, Tensor, bool]:
        """``(p (B,), direction (B,), scalar)`` from scalars, sequences or tensors (broadcast)."""
        scalar = not isinstance(p, (Sequence, Tensor, np.ndarray)) or (
            isinstance(p, (Tensor, np.ndarray)) and np.ndim(p) == 0
        )
        if isinstance(direction, str) or not isinstance(direction, (Sequence, Tensor, np.ndarray)):
            d = torch.tensor([windy.direction_index(direction)], device=self.device)
        elif isinstance(direction, Tensor):
            d = direction.to(self.device, torch.int64).reshape(-1)
        else:
            d = torch.tensor([windy.direction_index(x) for x in direction], device=self.device)
            scalar = False
        pt = self._f(p).reshape(-1)
        if bool(((pt < 0) | (pt > 1)).any()):
            raise ValueError(f"p must be in [0, 1], got {p}")
        if bool(((d < 0) | (d >= len(windy.DIRECTIONS))).any()):
            raise ValueError(f"direction must be one of {list(windy.DIRECTIONS)} or 0..3")
        pt, d = torch.broadcast_tensors(pt, d)
        return pt.contiguous(), d.contiguous(), scalar and pt.numel() == 1

    def transition(self, p: Any, direction: Any) -> tuple[Tensor, Tensor]:
        """Exact instance models ``P (B, S, A, S)``, ``R (B, S, A)`` (float64)."""
        pt, d, _ = self._instances_arg(p, direction)
        return windy.transition_tensors(self.model, pt, d, dtype=torch.float64)

    def instance_set(self, instances: Any = None) -> tuple[Tensor, Tensor]:
        """``(p (M,), direction (M,))`` of a finite instance set (Q_hat's max, Definition 1).

        ``None``: the training distribution's ``points``, else ``p_grid`` x training directions. A
        :class:`WindyInstances` (or name/dict): its points, else ``p_grid`` rescaled to its range x its
        directions. A ``(p, direction)`` pair of sequences/tensors: those instances.
        """
        if isinstance(instances, tuple) and len(instances) == 2:
            pt, d, _ = self._instances_arg(instances[0], instances[1])
            return pt, d
        dist = self.train_instances if instances is None else windy_instances(instances)
        if dist.points is not None:
            return self._instances_arg([p for p, _ in dist.points], [d for _, d in dist.points])[:2]
        t = self.p_grid
        if instances is not None:
            ti = self.train_instances
            span = ti.p_high - ti.p_low
            u = (t - ti.p_low) / span if span > 0 else torch.zeros_like(t)
            t = dist.p_low + (dist.p_high - dist.p_low) * u
        dirs = [windy.direction_index(x) for x in dist.directions]
        pp = t.repeat(len(dirs))
        dd = torch.tensor(dirs, device=self.device).repeat_interleave(t.numel())
        return pp, dd

    def quadrature(self, instances: Any = None) -> tuple[Tensor, Tensor, Tensor]:
        """``(p (K,), direction (K,), weight (K,))`` integrating over an instance distribution.

        Continuous ``p ~ U[p_low, p_high]``: Gauss-Legendre with ``quad_nodes`` nodes x uniform
        directions; ``points``: each point with weight ``1/len(points)``.
        """
        dist = self.train_instances if instances is None else windy_instances(instances)
        if dist.points is not None:
            pt, d = self.instance_set(dist)
            return pt, d, torch.full_like(pt, 1.0 / pt.numel())
        x, w = gauss_legendre(self.quad_nodes, dist.p_low, dist.p_high)
        dirs = [windy.direction_index(x) for x in dist.directions]
        nd = len(dirs)
        pp = x.to(self.device).repeat(nd)
        dd = torch.tensor(dirs, device=self.device).repeat_interleave(x.numel())
        ww = (w.to(self.device) / nd).repeat(nd)
        return pp, dd, ww

    @cached_property
    def _mean_mdp(self) -> tuple[Tensor, Tensor]:
        ti = self.train_instances
        if ti.points is not None:
            P, R = self.transition(*self.instance_set(ti))
        else:
            mean_p = 0.5 * (ti.p_low + ti.p_high)
            P, R = self.transition([mean_p] * len(ti.directions), list(ti.directions))
        return P.mean(0), R.mean(0)

    def mean_mdp(self) -> tuple[Tensor, Tensor]:
        """The training distribution's mean MDP ``(P̄ (S, A, S), R̄ (S, A))`` (paper §3.1)."""
        return self._mean_mdp

    # ---- subtask tables ----------------------------------------------------------------------

    def _cells_td(self, cells: Tensor) -> TensorDict:
        return TensorDict({keys.CELL: cells}, batch_size=cells.shape, device=self.device)

    @cached_property
    def termination_table(self) -> Tensor:
        """``beta (S, O)`` float64: 1 where option o terminates (windy: goal cells)."""
        cells = torch.arange(self.S, device=self.device)
        return self.subtasks.termination(self._cells_td(cells)).to(torch.float64)

    @cached_property
    def subtask_reward_table(self) -> Tensor:
        """``r_o(s, s') (O, S, S')`` float64 from :class:`WindySubtasks` (-1/step, wrong-exit penalty)."""
        S = self.S
        s = torch.arange(S, device=self.device).repeat_interleave(S)  # (S*S,)
        s2 = torch.arange(S, device=self.device).repeat(S)  # (S*S,)
        td = self._cells_td(s)
        td.set(keys.NEXT, self._cells_td(s2))
        r = self.subtasks.reward(td).to(torch.float64)  # (S*S, O)
        return r.T.reshape(self.O, S, S)

    # ---- averaging policy (paper §3.1) --------------------------------------------------------

    @cached_property
    def _averaging_q(self) -> Tensor:
        P, R = self.mean_mdp()
        return self._zero_goal(solve_mdp(P, R, self.gamma, tol=self.tol))

    def averaging_q(self) -> Tensor:
        """Optimal ``Q (S, A)`` of the mean MDP: the averaging policy's values (paper §3.1)."""
        return self._averaging_q

    def averaging_policy(self) -> Tensor:
        """The averaging policy pi_bar ``(S,)`` int64: greedy in :meth:`averaging_q`."""
        return greedy(self.averaging_q())

    def optimal_q(self, p: Any, direction: Any, option: str | int | None = None) -> Tensor:
        """Per-instance optimal ``Q (B, S, A)`` (env reward, or option ``option``'s subtask reward)."""
        pt, d, scalar = self._instances_arg(p, direction)
        P, R = windy.transition_tensors(self.model, pt, d, dtype=torch.float64)
        if option is None:
            Q = solve_mdp(P, R, self.gamma, tol=self.tol)
        else:
            o = self.subtasks.index(option) if isinstance(option, str) else int(option)
            Ro, cont = self._option_reward(P, o)
            Q = solve_mdp(P, Ro, self.gamma, cont=cont.expand(P.shape[0], -1), tol=self.tol)
        Q = self._zero_goal(Q)
        return Q[0] if scalar else Q

    # ---- options (paper §3.2) ------------------------------------------------------------------

    def _option_reward(self, P: Tensor, o: int) -> tuple[Tensor, Tensor]:
        """Expected subtask reward ``(..., S, A)`` of option ``o`` and its continuation ``(S',)``."""
        Ro = torch.einsum("...sat,st->...sa", P, self.subtask_reward_table[o])
        Ro = Ro.masked_fill(self.is_goal.view(-1, 1), 0.0)  # outside the initiation set: unused
        return Ro, 1.0 - self.termination_table[:, o]

    @cached_property
    def _option_q(self) -> Tensor:
        P, _ = self.mean_mdp()
        Rs, conts = zip(*(self._option_reward(P, o) for o in range(self.O)))
        Po = P.unsqueeze(0).expand(self.O, *P.shape)
        Q = solve_mdp(Po, torch.stack(Rs), self.gamma, cont=torch.stack(conts), tol=self.tol)
        return self._zero_goal(Q)

    def option_q(self) -> Tensor:
        """``Q_o (O, S, A)``: each exit option's averaging values on the mean MDP (subtask reward)."""
        return self._option_q

    def option_policies(self) -> Tensor:
        """``pi^o (O, S)`` int64: greedy in :meth:`option_q`."""
        return greedy(self.option_q())

    # ---- switching and max-values (paper §3.2, §3.3) --------------------------------------------

    def _mu(self, q_mu: Tensor) -> Tensor:
        if self.mu_temperature is None:
            return nn.functional.one_hot(greedy(q_mu), self.O).to(q_mu.dtype)
        return torch.softmax(q_mu / self.mu_temperature, dim=-1)

    def option_values(
        self, P: Tensor, R: Tensor, mu: Tensor, policies: Tensor | None = None
    ) -> Tensor:
        """``Q^{m,mu}(s, o) (B, S, O)``: run option o from s, then continue with ``mu (S, O)`` (SMDP).

        Solves ``Q(s,o) = r(s,a) + gamma sum_s' P(s,a,s') [(1-beta_o(s')) Q(s',o) + beta_o(s') V(s')]``
        with ``a = pi^o(s)`` and ``V(s') = sum_q mu(s',q) Q(s',q)`` exactly (one linear solve).
        """
        B, S, K = P.shape[0], self.S, self.O  # K options
        pol = self.option_policies() if policies is None else policies  # (K, S)
        Po = torch.stack([_policy_kernel(P, pol[o]) for o in range(K)], 2)  # (B, S, K, S')
        ro = torch.stack([_policy_reward(R, pol[o]) for o in range(K)], 2)  # (B, S, K)
        beta = self.termination_table  # (S', K)
        stay = Po * (1.0 - beta.T).view(1, 1, K, S)  # (B, S, K, S')
        eye_o = torch.eye(K, dtype=P.dtype, device=P.device)
        M = stay.unsqueeze(-1) * eye_o.view(1, 1, K, 1, K)  # (B, S, K, S', K'): keep running o
        M = M + torch.einsum("bsot,to,tp->bsotp", Po, beta, mu.to(P.dtype))  # terminate, mu picks
        M = M.reshape(B, S * K, S * K)
        eye = torch.eye(S * K, dtype=P.dtype, device=P.device)
        x = torch.linalg.solve(eye - self.gamma * M, ro.reshape(B, S * K, 1))
        return self._zero_goal(x.reshape(B, S, K))

    def _zero_goal(self, q: Tensor) -> Tensor:
        """Values ``(..., S, X)`` with goal rows set to exactly 0 (the episode has ended there)."""
        return q.masked_fill(self.is_goal.view(-1, 1), 0.0)

    @cached_property
    def _switching_q(self) -> Tensor:
        P, R = self.mean_mdp()
        P, R = P.unsqueeze(0), R.unsqueeze(0)
        mu = torch.full((self.S, self.O), 1.0 / self.O, dtype=torch.float64, device=self.device)
        q = self.option_values(P, R, mu)[0]
        for _ in range(1000):  # policy iteration over mu_bar (windy: beta only at the goal, 1 step)
            mu = self._mu(snap_ties(q))
            q_new = self.option_values(P, R, mu)[0]
            if bool((q_new - q).abs().max() < self.tol):
                q = q_new
                break
            q = q_new
        else:  # pragma: no cover
            raise RuntimeError("switching values did not converge")
        return snap_ties(q)

    def switching_q(self) -> Tensor:
        """``Q_mu (S, O)``: option values of mu_bar on the mean MDP, env reward (paper §3.2).

        mu_bar is greedy (or softmax) in these values. Windy options terminate only at the goal, so
        ``Q_mu(s, o)`` is the mean-MDP value of running ``pi^o`` from ``s``.
        """
        return self._switching_q

    def mu_bar(self) -> Tensor:
        """mu_bar ``(S, O)``: greedy one-hot (lowest index on ties) or softmax in :meth:`switching_q`."""
        return self._mu(self.switching_q())

    def v_mu_bar(self) -> Tensor:
        """``V^{mu_bar}(s) = sum_q mu_bar(s, q) Q_mu(s, q)`` ``(S,)`` (Definition 1's right-hand side)."""
        return (self.mu_bar() * self.switching_q()).sum(-1)

    def instance_option_q(self, p: Any, direction: Any) -> Tensor:
        """``Q^{m, mu_bar}(s, o)`` ``(B, S, O)`` (or ``(S, O)`` for a scalar instance) in instance m."""
        pt, d, scalar = self._instances_arg(p, direction)
        P, R = windy.transition_tensors(self.model, pt, d, dtype=torch.float64)
        q = self.option_values(P, R, self.mu_bar())
        return q[0] if scalar else q

    def max_value(self, instances: Any = None) -> Tensor:
        """``Q_hat (S, O) = max_m Q^{m, mu_bar}(s, o)`` over an instance set (Definition 1).

        ``instances``: see :meth:`instance_set` (default: ``p_grid`` x training directions).
        Values within ``TIE_ATOL`` of ``V^{mu_bar}(s)`` are snapped to it (see "Ties").
        """
        if instances is None:
            return self._max_value_default
        return self._max_value(*self.instance_set(instances))

    def _max_value(self, p: Tensor, d: Tensor) -> Tensor:
        chunks = [
            self.instance_option_q(p[i : i + 64], d[i : i + 64]) for i in range(0, p.numel(), 64)
        ]
        q_hat = torch.cat(chunks).max(0).values  # (S, O)
        v = self.v_mu_bar().unsqueeze(-1)  # (S, 1)
        return torch.where((q_hat - v).abs() <= TIE_ATOL, v.expand_as(q_hat), q_hat)

    @cached_property
    def _max_value_default(self) -> Tensor:
        return self._max_value(*self.instance_set(None))

    # ---- what the learnt heads converge to (docs/oracle.md) -------------------------------------

    def _objective_tables(self, option: str | int | None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``(P (K, S, A, S), R (K, S, A), cont (S,), weight (K,))`` over the training quadrature:
        env reward (``option=None``) or option ``option``'s subtask reward and termination."""
        pt, d, w = self.quadrature()
        P, R = self.transition(pt, d)
        cont = torch.ones(self.S, dtype=torch.float64, device=self.device)
        if option is not None:
            o = self.subtasks.index(option) if isinstance(option, str) else int(option)
            R, cont = self._option_reward(P, o)
        return P, R, cont, w

    def fixed_instance_value(self, policy: Tensor, option: str | int | None = None) -> Tensor:
        """``E_m[V^{m, pi}(s)] (S,)``: discounted value of a stationary policy when the instance is
        drawn once per episode and held fixed (training distribution), env or subtask reward."""
        P, R, cont, w = self._objective_tables(option)
        V = self._evaluate(P * cont.view(1, 1, 1, -1), R, policy.to(self.device))  # (K, S)
        return torch.einsum("k,ks->s", w, V)

    def fixed_instance_policy(self, option: str | int | None = None) -> Tensor:
        """The best Markov policy for the fixed-instance objective ``E_m[V^{m, pi}]`` ``(S,)``.

        Maximises the mean over start cells of :meth:`fixed_instance_value` (env reward, or option
        ``option``'s subtask reward) by policy search over deterministic Markov policies: from the
        mean-MDP optimum, change one cell's action at a time while that improves the objective by
        more than ``TIE_ATOL`` (a local optimum under single-cell changes). Unlike the mean MDP
        (paper §3.1), which redraws the instance at every step, this objective keeps it fixed for
        the episode, as the training episodes and the printed returns do; a memoryless policy cannot
        adapt to the instance, so the optimum differs from the mean-MDP one where a route is cheap
        on average but traps the agent in some instances (``whole_column_windy``: the windy column
        under a strong opposing wind).
        """
        P, R, cont, w = self._objective_tables(option)
        Pc = P * cont.view(1, 1, 1, -1)
        starts = self.start_cells

        def score(pol: Tensor) -> float:
            V = self._evaluate(Pc, R, pol)  # (K, S)
            return float(torch.einsum("k,ks->s", w, V)[starts].mean())

        pol = (
            self.averaging_policy()
            if option is None
            else self.option_policies()[
                self.subtasks.index(option) if isinstance(option, str) else int(option)
            ]
        )
        pol, best = pol.clone(), score(pol)
        cells = [s for s in range(self.S) if not bool(self.is_goal[s])]
        improved = True
        while improved:
            improved = False
            for s in cells:
                for a in range(self.A):
                    if a == int(pol[s]):
                        continue
                    trial = pol.clone()
                    trial[s] = a
                    v = score(trial)
                    if v > best + TIE_ATOL:
                        pol, best, improved = trial, v, True
        return pol

    def visit_probability(self, behaviour: Tensor, p: Any, direction: Any) -> Tensor:
        """``(B, S, A)``: probability that an episode (uniform start cell, ``horizon`` steps) of the
        stochastic policy ``behaviour (S, A)`` takes action a at cell s at least once, per instance.

        This is how often a first-visit replay (``heads/first_visit.py``) holds a sample of (s, a)
        from an episode of that instance. Backward induction over steps-to-go, all (s, a) at once.
        """
        P, _ = self.transition(p, direction)  # (B, S, A, S')
        B, S, A = P.shape[0], self.S, self.A
        b = behaviour.to(P.dtype).to(self.device)  # (S, A)
        Pb = torch.einsum("ksat,sa->kst", P, b)  # (B, S, S') kernel of the behaviour
        live = (~self.is_goal).to(P.dtype)  # (S,): the episode ends at the goal
        target = torch.arange(S * A, device=self.device)
        ts, ta = target // A, target % A  # (T,) the (s*, a*) each chain targets
        # h[T, k, x]: P(take a* at s* within the steps left | at x), instance k
        h = torch.zeros(S * A, B, S, dtype=P.dtype, device=self.device)
        P_target = P[:, ts, ta, :].transpose(0, 1)  # (T, B, S'): P(s*, a*, .)
        b_target = b[ts, ta]  # (T,)
        for _ in range(self.horizon):
            nxt = torch.einsum("kxt,Tkt->Tkx", Pb, h)  # (T, B, S) follow the behaviour
            at = b_target.view(-1, 1) * (1.0 - (P_target * h).sum(-1))  # (T, B): take a* at s*
            nxt[target, :, ts] += at
            h = nxt * live
        start = torch.zeros(S, dtype=P.dtype, device=self.device)
        start[self.start_cells] = 1.0 / self.start_cells.numel()
        return torch.einsum("Tks,s->kT", h, start).reshape(B, S, A)

    def replay_mdp(
        self, behaviour: Tensor, option: str | int | None = None
    ) -> tuple[Tensor, Tensor]:
        """The MDP a Q-learner sees in a first-visit replay of fixed-instance episodes ``(P, R)``.

        At (s, a) the next state is drawn from the instance mixture weighted by the prior times the
        chance that an episode of that instance visits (s, a) under ``behaviour (S, A)``
        (:meth:`visit_probability`), not by the prior alone as in the mean MDP. Pairs no instance
        visits keep the prior's weights. Env reward, or option ``option``'s subtask reward.
        """
        P, R, _, w = self._objective_tables(option)
        pt, d, _ = self.quadrature()
        v = self.visit_probability(behaviour, pt, d)  # (K, S, A)
        wk = w.view(-1, 1, 1) * v  # (K, S, A)
        total = wk.sum(0, keepdim=True)
        wk = torch.where(total > 0, wk / total.clamp_min(1e-300), w.view(-1, 1, 1).expand_as(wk))
        return torch.einsum("ksa,ksat->sat", wk, P), (wk * R).sum(0)

    def replay_policy(
        self, option: str | int | None = None, epsilon: float = 0.05, max_iter: int = 20
    ) -> Tensor:
        """The Q-learning fixed point on its own epsilon-greedy first-visit replay ``(S,)``.

        Iterates: behaviour = epsilon-greedy in the current policy; the greedy policy of the
        optimal Q of :meth:`replay_mdp` (env reward, or the option's subtask reward with its
        termination); until the policy repeats on the cells the behaviour visits (or ``max_iter``).
        """
        _, _, cont, _ = self._objective_tables(option)
        k = (
            None
            if option is None
            else (self.subtasks.index(option) if isinstance(option, str) else int(option))
        )
        pol = self.averaging_policy() if k is None else self.option_policies()[k]
        for _ in range(max_iter):
            b = torch.full((self.S, self.A), epsilon / self.A, dtype=torch.float64)
            b[torch.arange(self.S), pol] += 1.0 - epsilon
            P, R = self.replay_mdp(b, option)
            q = self._zero_goal(solve_mdp(P, R, self.gamma, cont=cont, tol=self.tol))
            new = greedy(q)
            if bool((new == pol).all()):
                break
            pol = new
        return pol

    # ---- evaluation ----------------------------------------------------------------------------

    def _start_index(self, start: Any) -> Tensor | None:
        if start is None or (isinstance(start, str) and start == "uniform"):
            return None
        if isinstance(start, tuple) and len(start) == 2:
            r, c = start
            return torch.tensor(int(r) * self.layout.width + int(c), device=self.device)
        return torch.as_tensor(start, dtype=torch.int64, device=self.device)

    def _select_start(self, V: Tensor, start: Any) -> Tensor:
        """``V (B, S)`` -> per-cell (start None), mean over start cells ('uniform'), or one cell."""
        if start is None:
            return V
        if isinstance(start, str):
            if start != "uniform":
                raise ValueError(
                    f"start must be None, 'uniform', a cell or (row, col), got {start!r}"
                )
            return V[:, self.start_cells].mean(-1)
        return V[:, self._start_index(start)]

    def evaluate(self, policy: Tensor, p: Any, direction: Any) -> Tensor:
        """Discounted values ``V (B, S)`` of a deterministic ``(S,)`` or stochastic ``(S, A)`` policy."""
        pt, d, scalar = self._instances_arg(p, direction)
        P, R = windy.transition_tensors(self.model, pt, d, dtype=torch.float64)
        V = self._evaluate(P, R, policy.to(self.device))
        return V[0] if scalar else V

    def _evaluate(self, P: Tensor, R: Tensor, policy: Tensor) -> Tensor:
        Ppi, rpi = _policy_kernel(P, policy), _policy_reward(R, policy)
        eye = torch.eye(self.S, dtype=P.dtype, device=P.device)
        return torch.linalg.solve(eye - self.gamma * Ppi, rpi.unsqueeze(-1)).squeeze(-1)

    def _finite_horizon(self, Ppi: Tensor, rpi: Tensor) -> Tensor:
        """Backward induction over steps-to-go: ``V_H`` with ``V_k = r_pi + P_pi V_{k-1}``, ``V_0 = 0``."""
        V = torch.zeros_like(rpi)
        for _ in range(self.horizon):
            V = rpi + torch.einsum("bst,bt->bs", Ppi, V)
        return V

    def episode_return(self, policy: Tensor, p: Any, direction: Any, start: Any = None) -> Tensor:
        """Exact expected ``horizon``-step undiscounted return of a stationary policy in an instance.

        ``start``: ``None`` (every cell, ``(B, S)``), ``"uniform"`` (mean over start cells), a cell
        index or ``(row, col)``. A scalar instance drops the batch dimension.
        """
        pt, d, scalar = self._instances_arg(p, direction)
        P, R = windy.transition_tensors(self.model, pt, d, dtype=torch.float64)
        policy = policy.to(self.device)
        V = self._finite_horizon(_policy_kernel(P, policy), _policy_reward(R, policy))
        out = self._select_start(V, start)
        return out[0] if scalar else out

    def mean_mdp_return(self, policy: Tensor, start: Any = None) -> Tensor:
        """Exact ``horizon``-step return of a policy in the mean MDP (instance redrawn every step)."""
        P, R = self.mean_mdp()
        policy = policy.to(self.device)
        V = self._finite_horizon(_policy_kernel(P[None], policy), _policy_reward(R[None], policy))
        return self._select_start(V, start)[0]

    def expected_return(
        self, policy: Tensor, instances: Any = None, starts: Any = "uniform"
    ) -> Tensor:
        """``E_m[return]`` of a policy when the instance is drawn per episode and held fixed.

        Quadrature over ``instances`` (default: the training distribution), see :meth:`quadrature`.
        ``starts``: ``"uniform"`` (scalar), ``None`` (per cell, ``(S,)``) or one cell.
        """
        pt, d, w = self.quadrature(instances)
        ret = self.episode_return(policy, pt, d, start=starts)  # (K, ...)
        return torch.einsum("k,k...->...", w, ret)

    # ---- heads ---------------------------------------------------------------------------------

    def heads(
        self,
        in_key: Any = keys.CELL,
        dtype: torch.dtype = torch.float64,
        robustness: Tensor | None = None,
    ) -> Heads:
        """A :class:`Heads` bundle of the oracle's tables (averaging, options, switching, max-value).

        Heads read ``in_key`` (``keys.CELL`` or a one-hot ``keys.OBSERVATION``) and gather rows:
        ``action_value (B, A)``, ``option_action_value (B, O, A)``, ``option_value (B, O)``,
        ``max_value (B, O)``; optionally ``robustness (B, O, A)`` from a given ``(S, O, A)`` table.
        """
        t = dict(dtype=dtype, device=self.device)
        return table_heads(
            self.option_names,
            averaging=self.averaging_q().to(**t),
            options=self.option_q().permute(1, 0, 2).contiguous().to(**t),
            switching=self.switching_q().to(**t),
            max_value=self.max_value().to(**t),
            robustness=None if robustness is None else robustness.to(**t),
            in_key=in_key,
            softmax_temperature=self.mu_temperature,
        )

    def observation_td(self, obs_encoding: str = "onehot") -> TensorDict:
        """A ``(S,)`` tensordict of every cell: ``cell`` and ``observation`` (for tabulating heads)."""
        cells = torch.arange(self.S, device=self.device)
        obs = torch.as_tensor(observation_table(self.layout, obs_encoding), device=self.device)
        return TensorDict(
            {keys.CELL: cells, keys.OBSERVATION: obs}, batch_size=[self.S], device=self.device
        )

    # ---- exact evaluation of controllers ---------------------------------------------------------

    @torch.no_grad()
    def tabulate(self, heads: Heads, obs_encoding: str = "onehot") -> dict[str, Tensor]:
        """Every head's output at every cell, ``{out_key: (S, ...)}`` (heads may read cell or observation)."""
        param = next(iter(heads.parameters()), None)  # heads may live on another device
        device = self.device if param is None else param.device
        td = heads(self.observation_td(obs_encoding).to(device))
        return {HEAD_OUT_KEYS[h]: td.get(HEAD_OUT_KEYS[h]).to(self.device) for h in heads.heads}

    def controller_chain(
        self,
        controller: Any,
        *,
        heads: Heads | None = None,
        hierarchy: Hierarchy | None = None,
        tau: float | None = None,
        subtasks: Subtasks | None = None,
        obs_encoding: str = "onehot",
    ) -> dict[str, Tensor]:
        """The controller as a Markov chain on (cell, carried state), from tabulated head outputs.

        ``controller``: a name in ``CONTROLLER_NAMES`` (with the oracle's heads unless ``heads`` is
        given) or a :class:`~taskvar_torch.controllers.base.Controller` (its heads, subtasks,
        hierarchy and tau). Carried state ``z``: 0 = none, ``k + 1`` = option/subtask ``k`` ran last.

        Returns ``decision (S, Z, N)``: distribution of the acting option ``n`` given ``(s, z)``;
        ``action (S, N)``: its greedy action; ``next_state (N,)``: ``z'`` after ``n`` acted;
        ``fires (S, Z)`` bool: an interruption fires (Algorithm 1 line 6) / control moves
        (Algorithm 2). This is an implementation of Algorithms 1-2 independent of ``controllers/``.
        """
        name = controller if isinstance(controller, str) else controller.name
        if name not in CONTROLLER_NAMES:
            raise ValueError(f"controller must be one of {list(CONTROLLER_NAMES)}, got {name!r}")
        if not isinstance(controller, str):
            heads = controller.heads
            subtasks = controller.subtasks
            hierarchy = getattr(controller, "hierarchy", hierarchy)
            tau = getattr(controller, "tau", tau)
        elif heads is None:
            heads, subtasks = self.heads(), self.subtasks if subtasks is None else subtasks
        t = self.tabulate(heads, obs_encoding)
        S = self.S
        if name == "averaging":
            act = t[keys.ACTION_VALUE].argmax(-1).unsqueeze(-1)  # (S, 1)
            one = torch.ones(S, 1, 1, dtype=torch.float64, device=self.device)
            return {
                "decision": one,
                "action": act,
                "next_state": torch.zeros(1, dtype=torch.int64, device=self.device),
                "fires": torch.zeros(S, 1, dtype=torch.bool, device=self.device),
            }
        q_opt = t[keys.OPTION_ACTION_VALUE]  # (S, O, A)
        O = q_opt.shape[1]  # noqa: E741
        act = q_opt.argmax(-1)  # (S, O)
        decision = torch.zeros(S, O + 1, O, dtype=torch.float64, device=self.device)
        fires = torch.zeros(S, O + 1, dtype=torch.bool, device=self.device)
        next_state = torch.arange(1, O + 1, device=self.device)
        if name in ("options", "interruption"):
            q_mu = t[keys.OPTION_VALUE]  # (S, O)
            mu = heads.mu_bar(q_mu).to(torch.float64)  # (S, O)
            v = (heads.mu_bar(q_mu) * q_mu).sum(-1)  # (S,)
            best = q_mu.argmax(-1)  # (S,) line 4
            beta = torch.zeros(S, O, dtype=torch.bool, device=self.device)
            if subtasks is not None:
                beta = subtasks.termination(self._cells_td(torch.arange(S, device=self.device)))
            for s in range(S):
                for z in range(O + 1):
                    if z == 0 or bool(beta[s, z - 1]):
                        decision[s, z, best[s]] = 1.0
                    elif name == "interruption" and bool(t[keys.MAX_VALUE][s, z - 1] < v[s]):
                        decision[s, z] = mu[s]  # lines 6-8
                        fires[s, z] = True
                    else:
                        decision[s, z, z - 1] = 1.0
            return {"decision": decision, "action": act, "next_state": next_state, "fires": fires}
        # hierarchy (Algorithm 2), literally, with greedy option policies
        if hierarchy is None or tau is None:
            raise ValueError("the hierarchy controller needs a hierarchy and tau")
        names = list(heads.option_names)
        rob = t[keys.ROBUSTNESS]  # (S, O, A)

        def search(s: int, o_run: int, p: int | None) -> int:
            """HierarchicalSearch(K, o_run, p, tau, s): the option whose action is returned."""
            if p is not None and float(rob[s, p, act[s, p]]) > tau:  # lines 1-3
                return p
            a = int(act[s, o_run])  # line 5
            kids = [names.index(k) for k in hierarchy.components(names[o_run])]
            if not kids or float(rob[s, o_run, a]) > tau:  # line 6
                return o_run
            q_star = max(kids, key=lambda q: (float(rob[s, q, a]), -q))  # line 10 (first on ties)
            return search(s, q_star, o_run)  # line 11

        root = names.index(hierarchy.root)
        for s in range(S):
            for z in range(O + 1):
                o_run = root if z == 0 else z - 1
                parent = hierarchy.parent(names[o_run])
                n = search(s, o_run, None if parent is None else names.index(parent))
                decision[s, z, n] = 1.0
                fires[s, z] = z > 0 and n != z - 1
        return {"decision": decision, "action": act, "next_state": next_state, "fires": fires}

    def controller_return(
        self, controller: Any, p: Any, direction: Any, start: Any = None, **kwargs: Any
    ) -> Tensor:
        """Exact expected ``horizon``-step undiscounted return of a controller in instance(s).

        Backward induction over steps-to-go on the chain of :meth:`controller_chain` (the carried
        state starts empty). ``start`` as in :meth:`episode_return`; ``kwargs`` go to
        :meth:`controller_chain`.
        """
        pt, d, scalar = self._instances_arg(p, direction)
        P, R = windy.transition_tensors(self.model, pt, d, dtype=torch.float64)
        chain = self.controller_chain(controller, **kwargs)
        V = self._chain_values(P, R, chain)[..., 0]  # (B, S): empty carried state
        out = self._select_start(V, start)
        return out[0] if scalar else out

    def controller_fire_count(
        self, controller: Any, p: Any, direction: Any, start: Any = None, **kwargs: Any
    ) -> Tensor:
        """Exact expected number of steps per episode at which the controller's ``fires`` flag is
        set (Algorithm 1: interruptions; Algorithm 2: control moves), within the horizon."""
        pt, d, scalar = self._instances_arg(p, direction)
        P, R = windy.transition_tensors(self.model, pt, d, dtype=torch.float64)
        chain = self.controller_chain(controller, **kwargs)
        V = self._chain_values(P, R, chain, count_fires=True)[..., 0]  # (B, S)
        out = self._select_start(V, start)
        return out[0] if scalar else out

    def controller_expected_return(
        self, controller: Any, instances: Any = None, starts: Any = "uniform", **kwargs: Any
    ) -> Tensor:
        """A controller's exact expected return over an instance distribution (quadrature)."""
        pt, d, w = self.quadrature(instances)
        ret = self.controller_return(controller, pt, d, start=starts, **kwargs)  # (K, ...)
        return torch.einsum("k,k...->...", w, ret)

    def _chain_values(
        self, P: Tensor, R: Tensor, chain: dict[str, Tensor], count_fires: bool = False
    ) -> Tensor:
        """``V_H (B, S, Z)``: ``V_k(s,z) = sum_n D[s,z,n] (r(s,a_n) + sum_s' P(s,a_n,s') V_{k-1}(s',z'_n))``.

        With ``count_fires`` the per-step reward is the ``fires (s, z)`` indicator (0 at the goal).
        """
        D, act, nz = chain["decision"], chain["action"], chain["next_state"]  # (S,Z,N) (S,N) (N,)
        B, S = P.shape[0], self.S
        N, Z = act.shape[1], D.shape[1]
        idx = act.view(1, S, N, 1).expand(B, S, N, S)
        Pn = P.gather(2, idx)  # (B, S, N, S'): P(s, a_n(s), s')
        rn = R.gather(2, act.unsqueeze(0).expand(B, S, N))  # (B, S, N)
        if count_fires:
            rn = torch.zeros_like(rn)
            fz = (chain["fires"] & ~self.is_goal.view(-1, 1)).to(P.dtype)  # (S, Z)
        V = torch.zeros(B, S, Z, dtype=P.dtype, device=P.device)
        for _ in range(self.horizon):
            W = rn + torch.einsum("bsnt,btn->bsn", Pn, V[:, :, nz])  # (B, S, N)
            V = torch.einsum("szn,bsn->bsz", D, W)
            if count_fires:
                V = V + fz
        return V
