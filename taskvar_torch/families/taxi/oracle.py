"""The Taxi family's exact oracle, :class:`TaxiOracle` (paper §3.1-3.3, Definition 1, Algorithm 1).

Taxi-v4 (``families/taxi/dynamics.py``) with a hidden instance ``(q, f)``: rain ``rainy_probability`` q and a
fickle passenger ``fickle_probability`` f. The oracle has the windy oracle's interface where it
applies (:mod:`taskvar_torch.oracle`); the design decisions special to Taxi:

- **Augmented states.** The fickle rule is not Markov in the 500 Taxi states, so every exact
  model runs on 1000 augmented states ``x = s + 500 k``: ``k = 1`` while the fickle draw is
  *pending* (no step has yet started with the passenger aboard and moved the taxi), ``k = 0``
  after. At the first such step the destination is redrawn (uniform over the three others) with
  probability f and ``k`` drops to 0 either way; an episode starts pending. This is the belief
  MDP of an agent that knows the instance but not the passenger's coin: Taxi-v4 flips the coin
  ("armed") at reset, but nothing reveals it before that first move, so both give every policy
  over the 500 Taxi states the same law of observed trajectories (tested against Gymnasium's
  ``step``). Transitions are affine in f (the coin is flipped once) and in q (each step's kernel),
  so the same holds for their mean. ``informed=True`` gives the *armed* augmentation instead
  (``k = 1`` iff armed and not fired, armed at reset with probability f): the model of an agent
  that also knows the coin, for :meth:`TaxiOracle.optimal_q` / :meth:`TaxiOracle.optimal_return`.
  Heads, observations and controllers see only the 500 Taxi states.
- **Delivered states are absorbing.** A delivery leads to ``passenger == destination``, which
  nothing else reaches: those 100 states (``is_goal``) absorb with reward 0, as windy's goal
  cells (Gymnasium's ``P`` keeps them live; the episode has ended there).
- **Mean MDP over the 500 observed states** (paper §3.1). The instance prior averages the
  augmented kernel exactly (``E[T_aug] = T_aug(E q, E f)`` for independent q and f; the mean of
  the points' kernels for a finite set). Projecting onto the observed states needs
  ``w(s) = P(pending | s)``, and only where pending changes the next step: the 16 states with the
  passenger aboard on a landmark (pending with the passenger aboard implies the taxi has not moved
  since the pickup). ``fickle_weights="visits"`` (default) takes ``w`` from the averaging policy's
  own undiscounted ``horizon``-step occupancy over the training distribution (uniform Taxi-v4
  starts, quadrature in q, ``E f``), iterated to a fixed point (policy -> occupancy -> ``w`` ->
  mean MDP -> greedy policy): the fixed point of Q-learning on the greedy policy's own
  every-visit data (Singh, Jaakkola & Jordan 1994 for aliased states), the closest exact
  statement of what the averaging head estimates; the head's epsilon-greedy, mixed-age replay and
  its visit weighting of q (prior weights in q here, as windy's oracle; :mod:`oracle.replay`
  covers the latter there) keep it from being exactly that. ``fickle_weights="pickup"`` sets
  ``w = 1`` on those 16 states (an aboard taxi on a landmark has just picked up): policy-free,
  wrong only where a taxi re-enters a landmark aboard. Options and switching values use the same
  projected mean MDP.
- **Initiation sets** (:class:`~taskvar_torch.families.taxi.subtasks.TaxiSubtasks`). mu_bar's argmax and
  draws (Algorithm 1 lines 4 and 7) and ``V^{mu_bar}`` (line 6, Definition 1) range over the
  options initiable at s only: ``mu_bar(s, .)`` is the greedy one-hot (or softmax) of ``Q_mu(s, .)``
  masked to I(s). Where no option is initiable the controller falls back to the averaging
  action and holds no option; on Taxi that happens only at delivered states (every live state
  has an initiable ``to_*``), so the fallback never acts in an episode.
- **Q_hat** (Definition 1): ``max`` over the instance set *and* the hidden fickle status of
  ``Q^{m, mu_bar}((s, k), o)`` (optimism over everything hidden). Default set: ``q_grid`` values
  over ``[q_low, q_high]`` (plus the dry ``q = 1`` when some episodes are dry) x the extreme f of
  the training support (``0`` when some episodes are not fickle, ``f_low``, ``f_high``): values are
  affine in f, so the max over f's support is at these.
- **Values and returns** as windy's oracle: values compared with the heads are discounted with
  ``gamma``; returns are exact ``horizon``-step (200) undiscounted sums by backward induction on
  (augmented state, running option). ``expected_return`` over a distribution is exact: returns are
  affine in f (use ``E f``) and polynomials of degree ``< horizon`` in q (Gauss-Legendre with
  ``ceil(horizon / 2)`` nodes over ``[q_low, q_high]``, plus the dry point).
- **Per-instance optimum**: discounted optimal values over augmented states
  (:meth:`TaxiOracle.optimal_q`) and the exact finite-horizon optimal return
  (:meth:`TaxiOracle.optimal_return`, backward induction: the best history-dependent policy of an
  agent that knows (q, f), and with ``informed`` the coin).

Examples:
    >>> oracle = TaxiOracle()
    >>> oracle.averaging_policy().shape, oracle.option_q().shape
    (torch.Size([500]), torch.Size([6, 500, 6]))
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterator, Sequence
from functools import cached_property
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict
from torch import nn

from taskvar_torch import keys
from taskvar_torch.families.taxi import dynamics as taxi
from taskvar_torch.families.taxi.dynamics import TaxiInstances, taxi_instances
from taskvar_torch.families.taxi.env import observation_table
from taskvar_torch.families.taxi.subtasks import TaxiSubtasks, state_parts
from taskvar_torch.heads.bundle import Heads
from taskvar_torch.oracle.chains import CONTROLLER_NAMES, ControllerChains
from taskvar_torch.oracle.mdp import TIE_ATOL, gauss_legendre, greedy, snap_ties, solve_mdp
from taskvar_torch.oracle.tables import table_heads

Tensor = torch.Tensor

FICKLE_WEIGHTS = ("visits", "pickup")
_K = 4 * taxi.NUM_OUTCOMES  # successors per (x, a): 3 rain outcomes x (3 redraws, no redraw)


class TaxiOracle(ControllerChains):
    """Exact solver of the Taxi family (module docstring).

    Args:
        gamma: discount of the values compared against the networks.
        horizon: episode length of the returns (Taxi-v4: 200).
        train_instances: the training distribution (name, dict or :class:`TaxiInstances`).
        end_penalty: navigation options' cost of delivering away from their landmark
            (:class:`TaxiSubtasks`).
        q_grid: q values of Q_hat's default instance set: an int (evenly spaced over
            ``[q_low, q_high]``) or a sequence of values.
        fickle_weights: ``"visits"`` or ``"pickup"``: how the mean MDP weighs the hidden fickle
            status (module docstring).
        mu_temperature: ``None`` for a greedy mu_bar, else the temperature of a softmax mu_bar.
        quad_nodes: Gauss-Legendre nodes in q (default ``ceil(horizon / 2)``: exact for returns).
        tol: certified error of the iterative solves.
        device: torch device of the tables.
        obs_encoding: the observation learnt heads read (``families/taxi/env.py``), used where a
            controller's heads are tabulated at every state.
    """

    instance_keys = ("rainy_probability", "fickle_probability")
    """The ``("instance", key)`` fields :meth:`controller_return` takes, in order (docs/families.md)."""
    max_exact_solves = 32
    """``taskvar eval`` computes per-episode exact returns by default only for episodes with at
    most this many distinct rain values (each costs a chain solve of ~0.2-0.5 s per method;
    ``taskvar eval --exact`` computes them anyway)."""

    max_step_solves = 32
    """``taskvar eval`` computes per-step regret (:meth:`step_regret`) by default only for episodes
    with at most this many distinct instances (each a backward induction of ~0.1-0.3 s; ``--exact``
    computes it anyway)."""

    @staticmethod
    def step_solves(q: Any, f: Any) -> int:
        """The backward inductions :meth:`step_regret` runs for episodes with these instances."""
        return int(np.unique(np.stack([np.asarray(q), np.asarray(f)], -1), axis=0).shape[0])

    @staticmethod
    def exact_solves(q: Any, f: Any) -> int:
        """The chain solves per controller for episodes with these instances (distinct q: the
        values are affine in f, :meth:`_chain_values_by_rain`)."""
        return int(np.unique(np.asarray(q)).size)

    def __init__(
        self,
        gamma: float = 0.99,
        horizon: int = 200,
        train_instances: str | dict | TaxiInstances = "train",
        end_penalty: float = 100.0,
        q_grid: int | Sequence[float] = 11,
        fickle_weights: str = "visits",
        mu_temperature: float | None = None,
        quad_nodes: int | None = None,
        tol: float = 1e-10,
        device: torch.device | str = "cpu",
        obs_encoding: str = "onehot",
    ):
        if not 0.0 <= gamma < 1.0:
            raise ValueError(f"gamma must be in [0, 1), got {gamma}")
        if int(horizon) < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        if fickle_weights not in FICKLE_WEIGHTS:
            raise ValueError(
                f"fickle_weights must be one of {list(FICKLE_WEIGHTS)}, got {fickle_weights!r}"
            )
        self.device = torch.device(device)
        self.obs_encoding = obs_encoding
        self.model = taxi.TaxiModel(self.device)
        self.gamma, self.horizon, self.tol = float(gamma), int(horizon), float(tol)
        self.train_instances = taxi_instances(train_instances)
        self.subtasks = TaxiSubtasks(end_penalty)
        self.option_names = self.subtasks.names
        self.fickle_weights = fickle_weights
        self.mu_temperature = mu_temperature
        self.quad_nodes = int(quad_nodes) if quad_nodes is not None else math.ceil(horizon / 2)
        self.q_grid = q_grid
        self.S, self.A, self.O = taxi.NUM_STATES, taxi.NUM_ACTIONS, len(self.option_names)
        self.X = 2 * self.S
        self.start_cells = self.model.start_states  # (300,)
        _, pas, dest = state_parts(torch.arange(self.S, device=self.device))
        self.is_goal = pas == dest  # (S,) delivered: absorbing
        self.is_goal_x = self.is_goal.repeat(2)  # (X,)
        self._build_successors()

    # ---- models -----------------------------------------------------------------------------

    def _f(self, x: Any) -> Tensor:
        return torch.as_tensor(x, dtype=torch.float64, device=self.device)

    def _build_successors(self) -> None:
        """The instance-free successor table ``succ (X, A, 12)`` and its slot masks."""
        S, A, dev = self.S, self.A, self.device
        s = torch.arange(S, device=dev)
        nxt = self.model.next.clone()  # (S, A, 3)
        nxt[self.is_goal] = s[self.is_goal].view(-1, 1, 1)  # absorbing
        fires, targets = self.model.fickle_moves, self.model.fickle_targets  # (S, S) (S, 3)
        fire = fires[s.view(-1, 1, 1), nxt] & ~self.is_goal.view(-1, 1, 1)  # (S, A, 3)
        red = targets[nxt]  # (S, A, 3 outcomes, 3 redraws): unarmed after the redraw
        # slots per outcome j: 3 redraws (unpending), then the no-redraw successor
        pend_keep = torch.where(fire, nxt, nxt + S)  # (S, A, 3): still pending unless it fired
        pend = torch.cat([red, pend_keep.unsqueeze(-1)], -1)  # (S, A, 3, 4)
        unp = torch.cat([nxt.unsqueeze(-1).expand(S, A, 3, 3), nxt.unsqueeze(-1)], -1)
        self.succ = torch.cat([unp, pend]).reshape(self.X, A, _K)  # (X, A, 12)
        self._fire = torch.cat([torch.zeros_like(fire), fire])  # (X, A, 3)
        R = self.model.reward.to(torch.float64).masked_fill(self.is_goal.view(-1, 1), 0.0)
        self.R = R  # (S, A) env reward, 0 at delivered states
        self.R_x = R.repeat(2, 1)  # (X, A)

    def _outcome_probs(self, q: Tensor) -> Tensor:
        """``(B, A, 3)`` rain-outcome probabilities (moves: q, (1-q)/2, (1-q)/2; else 1, 0, 0)."""
        B = q.numel()
        lat = 0.5 * (1.0 - q).view(B, 1)
        move = torch.stack([q.view(B, 1), lat, lat], -1)  # (B, 1, 3)
        other = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64, device=self.device)
        is_move = (torch.arange(self.A, device=self.device) < 4).view(1, -1, 1)
        return torch.where(is_move, move, other.view(1, 1, 3))  # (B, A, 3)

    def _instances_arg(self, q: Any, f: Any) -> tuple[Tensor, Tensor, bool]:
        """``(q (B,), f (B,), scalar)`` from scalars, sequences or tensors (broadcast)."""
        scalar = all(np.ndim(v) == 0 for v in (q, f))
        qt, ft = self._f(q).reshape(-1), self._f(f).reshape(-1)
        for name, v in (("rainy_probability", qt), ("fickle_probability", ft)):
            if bool(((v < 0) | (v > 1) | v.isnan()).any()):
                raise ValueError(f"{name} must be in [0, 1], got {v.tolist()}")
        qt, ft = torch.broadcast_tensors(qt, ft)
        return qt.contiguous(), ft.contiguous(), scalar

    def kernel_probs(self, q: Any, f: Any, informed: bool = False) -> Tensor:
        """``prob (B, X, A, 12)`` over :attr:`succ` for instances ``(q, f)``.

        Pending rows (``x >= 500``) on a firing transition redraw with probability f (each other
        destination f/3), else go on unpended; ``informed``: the armed augmentation, whose armed
        rows redraw with probability 1 (f then enters only the start, :meth:`start_weights`).
        """
        qt, ft, _ = self._instances_arg(q, f)
        B, S, A = qt.numel(), self.S, self.A
        po = self._outcome_probs(qt).unsqueeze(1)  # (B, 1, A, 3)
        fr = torch.ones_like(ft) if informed else ft  # (B,) redraw probability when pending
        fr = fr.view(B, 1, 1, 1)
        fire = self._fire[S:].unsqueeze(0)  # (1, S, A, 3)
        red = torch.where(fire, po * fr / 3.0, torch.zeros_like(po))  # (B, S, A, 3)
        keep = torch.where(fire, po * (1.0 - fr), po)  # (B, S, A, 3)
        pend = torch.cat([red.unsqueeze(-1).expand(B, S, A, 3, 3), keep.unsqueeze(-1)], -1)
        zero = torch.zeros(B, S, A, 3, 3, dtype=torch.float64, device=self.device)
        unp = torch.cat([zero, po.expand(B, S, A, 3).unsqueeze(-1)], -1)
        return torch.cat([unp, pend], 1).reshape(B, self.X, A, _K)

    def start_weights(self, f: Any, informed: bool = False) -> Tensor:
        """``(B, 2)``: probability of starting unpended / pending (armed when ``informed``)."""
        ft = self._f(f).reshape(-1)
        if informed:
            return torch.stack([1.0 - ft, ft], -1)
        return torch.stack([torch.zeros_like(ft), torch.ones_like(ft)], -1)

    def transition(self, q: Any, f: Any, informed: bool = False) -> tuple[Tensor, Tensor, Tensor]:
        """Exact augmented models ``P (B, X, A, X)``, ``R (B, X, A)``, ``done (B, X, A)`` (float64).

        ``X = 1000`` (module docstring); delivered states absorb with reward 0; ``done`` marks the
        delivering transitions (the episode ends).
        """
        prob = self.kernel_probs(q, f, informed)  # (B, X, A, K)
        B = prob.shape[0]
        P = torch.zeros(B, self.X, self.A, self.X, dtype=torch.float64, device=self.device)
        P.scatter_add_(3, self.succ.unsqueeze(0).expand_as(prob), prob)
        done = self.model.done.repeat(2, 1).unsqueeze(0).expand(B, -1, -1).clone()
        return P, self.R_x.unsqueeze(0).expand(B, -1, -1).clone(), done

    # ---- instance distributions ----------------------------------------------------------------

    def quadrature(
        self, instances: Any = None, nodes: int | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """``(q (K,), f (K,), weight (K,))``, exact for returns (module docstring): the points
        (equal weights), or Gauss-Legendre in q (``nodes``, default ``quad_nodes``) over the rainy
        range (weight ``rain_share``) plus the dry ``q = 1`` (``1 - rain_share``), each with
        ``f = E f``."""
        dist = self.train_instances if instances is None else taxi_instances(instances)
        if dist.points is not None:
            pts = self._f(dist.points)  # (K, 2)
            return pts[:, 0], pts[:, 1], torch.full_like(pts[:, 0], 1.0 / pts.shape[0])
        qs, ws = [], []
        if dist.rain_share > 0:
            x, w = gauss_legendre(nodes or self.quad_nodes, dist.q_low, dist.q_high)
            qs.append(x.to(self.device))
            ws.append(w.to(self.device) * dist.rain_share)
        if dist.rain_share < 1:
            qs.append(self._f([1.0]))
            ws.append(self._f([1.0 - dist.rain_share]))
        q = torch.cat(qs)
        mean_f = dist.fickle_share * 0.5 * (dist.f_low + dist.f_high)
        return q, torch.full_like(q, mean_f), torch.cat(ws)

    def instance_set(self, instances: Any = None) -> tuple[Tensor, Tensor]:
        """``(q (M,), f (M,))``: Q_hat's instance set (module docstring); a ``(q, f)`` pair of
        sequences gives those instances."""
        if isinstance(instances, tuple) and len(instances) == 2:
            q, f, _ = self._instances_arg(*instances)
            return q, f
        dist = self.train_instances if instances is None else taxi_instances(instances)
        if dist.points is not None:
            pts = self._f(dist.points)
            return pts[:, 0].contiguous(), pts[:, 1].contiguous()
        qs: list[float] = []
        if dist.rain_share > 0:
            if isinstance(self.q_grid, int):
                qs += np.linspace(dist.q_low, dist.q_high, max(self.q_grid, 1)).tolist()
            else:
                qs += [float(v) for v in self.q_grid]
        if dist.rain_share < 1:
            qs.append(1.0)
        fs: list[float] = []
        if dist.fickle_share < 1:
            fs.append(0.0)
        if dist.fickle_share > 0:
            fs += [dist.f_low, dist.f_high]
        qq = sorted(set(qs))
        ff = sorted(set(fs))
        q = self._f(qq).repeat_interleave(len(ff))
        return q, self._f(ff).repeat(len(qq))

    # ---- sparse solvers --------------------------------------------------------------------------

    def _expect(self, V: Tensor, prob: Tensor, succ: Tensor) -> Tensor:
        """``E[V(x')] (B, *I)`` for ``V (B, X)``, ``prob (B, *I, K)``, ``succ (*I, K)``."""
        B = V.shape[0]
        nxt = V.gather(1, succ.reshape(1, -1).expand(B, -1)).view(prob.shape)
        return (nxt * prob).sum(-1)

    def _bound(self) -> float:
        return self.tol * (1.0 - self.gamma) / max(self.gamma, 1e-300)

    def _solve_x(self, prob: Tensor, R: Tensor) -> Tensor:
        """Optimal ``Q (B, X, A)`` on augmented states: value iteration, then a policy-iteration
        polish with exact linear solves (as :func:`solve_mdp`), ties snapped."""
        B, X = prob.shape[0], self.X
        V = torch.zeros(B, X, dtype=torch.float64, device=self.device)
        for _ in range(1_000_000):
            Q = R + self.gamma * self._expect(V, prob, self.succ)
            V_new = Q.max(-1).values
            delta = float((V_new - V).abs().max())
            V = V_new
            if delta < self._bound():
                break
        pi = greedy(Q)  # (B, X)
        eye = torch.eye(X, dtype=torch.float64, device=self.device)
        for _ in range(100):
            Ppi = self._policy_matrix(prob, pi)  # (B, X, X)
            rpi = R.expand(B, -1, -1).gather(2, pi.unsqueeze(-1)).squeeze(-1)
            Vpi = torch.linalg.solve(eye - self.gamma * Ppi, rpi.unsqueeze(-1)).squeeze(-1)
            Q = R + self.gamma * self._expect(Vpi, prob, self.succ)
            cur = Q.gather(-1, pi.unsqueeze(-1)).squeeze(-1)
            better = Q.max(-1).values > cur + TIE_ATOL
            if not bool(better.any()):
                break
            pi = torch.where(better, greedy(Q), pi)
        return snap_ties(Q.masked_fill(self.is_goal_x.view(1, -1, 1), 0.0))

    def _policy_matrix(self, prob: Tensor, pi: Tensor) -> Tensor:
        """Dense ``P_pi (B, X, X)`` of a deterministic augmented policy ``pi (B, X)``."""
        B, X = prob.shape[0], self.X
        idx = pi.view(B, X, 1, 1).expand(B, X, 1, _K)
        p = prob.gather(2, idx).squeeze(2)  # (B, X, K)
        s = self.succ.unsqueeze(0).expand(B, -1, -1, -1).gather(2, idx).squeeze(2)
        M = torch.zeros(B, X, X, dtype=torch.float64, device=self.device)
        return M.scatter_add_(2, s, p)

    # ---- per-instance optimum ------------------------------------------------------------------

    def optimal_q(self, q: Any, f: Any, informed: bool = False) -> Tensor:
        """Per-instance optimal discounted ``Q (B, X, A)`` over augmented states (``(X, A)`` for a
        scalar instance): the agent knows (q, f) and, with ``informed``, the passenger's coin."""
        qt, ft, scalar = self._instances_arg(q, f)
        Q = self._solve_x(self.kernel_probs(qt, ft, informed), self.R_x.unsqueeze(0))
        return Q[0] if scalar else Q

    def optimal_return(self, q: Any, f: Any, start: Any = None, informed: bool = False) -> Tensor:
        """Exact per-instance optimal ``horizon``-step undiscounted return ``(B, S)`` (backward
        induction over steps-to-go: the best policy that knows (q, f), and with ``informed`` the
        coin), from each Taxi state at the episode start (``start`` as in
        :meth:`controller_return`)."""
        qt, ft, scalar = self._instances_arg(q, f)
        steps = self._optimal_steps(qt, torch.ones_like(ft) if informed else ft)
        _, _, V = deque(steps, maxlen=1)[0]  # the last: horizon steps to go (earlier W dropped)
        out = self._select_start(self._start_mix(V, ft, informed), start)
        return out[0] if scalar else out

    def _optimal_steps(self, q: Tensor, fr: Tensor) -> Iterator[tuple[int, Tensor, Tensor]]:
        """Backward induction of the per-instance optimum over steps-to-go: yields ``(togo, W, V)``
        for ``togo = 1 .. horizon``, ``W (B, X, A)`` the optimal values of each action with
        ``togo`` steps to go and ``V = W.max(-1)``; ``fr (B,)``: the redraw probability of a
        pending state (f, or 1 for the informed model)."""
        B = q.numel()
        po = self._outcome_probs(q).permute(0, 2, 1).unsqueeze(2)  # (B, 3, 1, A)
        flat = self._succ3.permute(2, 0, 1).reshape(1, -1).expand(B, -1)  # (B, 3*X*A)
        V = torch.zeros(B, self.X, dtype=torch.float64, device=self.device)
        for togo in range(1, self.horizon + 1):
            nxt = self._extend(V, fr).gather(1, flat).view(B, 3, self.X, self.A)
            W = self.R_x + po[:, 0] * nxt[:, 0] + po[:, 1] * nxt[:, 1] + po[:, 2] * nxt[:, 2]
            V = W.max(-1).values
            yield togo, W, V

    def step_regret(self, q: Any, f: Any, cells: Any, actions: Any, alive: Any = None) -> Tensor:
        """Instantaneous regret ``(B, T)`` of the actions played in ``B`` episodes, one instance
        each: ``V*_{H-t}(x_t) - Q*_{H-t}(x_t, a_t)`` at step ``t`` (``H = horizon``; the values of
        :meth:`optimal_return` with ``H - t`` steps to go), 0 where ``alive`` (default all) is
        false. ``cells``, ``actions``: ``(B, T)`` Taxi states and actions, ``T <= H``.

        ``x_t`` is the augmented state (module docstring): pending from the start until the first
        step that starts with the passenger aboard and moves the taxi, read off the trace itself
        (``fickle_moves[s_t, s_{t+1}]``), so the values are those of the agent that knows (q, f)
        but not the passenger's coin: the per-instance optimum every regret is measured against.
        By the performance-difference identity an episode's sum over steps is, in expectation
        over rain and the coin, its regret ``optimal_return - return`` (exactly so where the
        instance is deterministic: ``q = 1``, ``f = 0``; docs/memory.md)."""
        qt, ft, _ = self._instances_arg(q, f)
        s, a, live = self._step_trace(qt.numel(), cells, actions, alive)
        B, T = s.shape
        # pending (k = 1) until the first step from a passenger-aboard state that moves the taxi
        fired = self.model.fickle_moves[s[:, :-1], s[:, 1:]]  # (B, T - 1)
        done_before = torch.cumsum(fired.to(torch.int64), 1) > 0
        pending = torch.cat(
            [torch.ones(B, 1, dtype=torch.bool, device=self.device), ~done_before], 1
        )
        x = s + self.S * pending.to(torch.int64)  # (B, T)
        # the optimum's values depend on the instance only: one backward induction per distinct
        # (q, f) (a few for a test point like `gymnasium`; one per episode for a continuous range)
        uniq, inv = torch.unique(torch.stack([qt, ft], 1), dim=0, return_inverse=True)
        out = torch.zeros(B, T, dtype=torch.float64, device=self.device)
        for lo in range(0, uniq.shape[0], 128):  # (128, 1000, 6, 3) float64 per step at most
            part = uniq[lo : lo + 128]
            mine = ((inv >= lo) & (inv < lo + part.shape[0])).nonzero().squeeze(1)  # episodes
            out[mine] = self._step_gaps(part, inv[mine] - lo, x[mine], a[mine], live[mine])
        return out

    def _step_gaps(self, inst: Tensor, which: Tensor, x: Tensor, a: Tensor, live: Tensor) -> Tensor:
        """:meth:`step_regret` for episodes ``(N,)`` of the instances ``inst (U, 2)`` (``which``
        indexes them), augmented states ``x (N, T)``."""
        N, T = x.shape
        out = torch.zeros(N, T, dtype=torch.float64, device=self.device)
        for togo, W, V in self._optimal_steps(inst[:, 0].contiguous(), inst[:, 1].contiguous()):
            t = self.horizon - togo
            if t < T:
                xt = x[:, t]
                gap = V[which, xt] - W[which, xt, a[:, t]]
                out[:, t] = torch.where(live[:, t], gap, 0.0)
        return out

    def _start_mix(self, V: Tensor, f: Tensor, informed: bool = False) -> Tensor:
        """``(B, S)`` episode-start values from augmented ``V (B, X, ...)``'s first trailing slot."""
        w = self.start_weights(f, informed)  # (B, 2)
        v = V.reshape(V.shape[0], 2, self.S, -1)[..., 0]  # (B, 2, S)
        return (w.unsqueeze(-1) * v).sum(1)

    def _select_start(self, V: Tensor, start: Any) -> Tensor:
        """``V (B, S)`` -> per state (None), mean over Taxi-v4's 300 starts ('uniform'), or one."""
        if start is None:
            return V
        if isinstance(start, str):
            if start != "uniform":
                raise ValueError(f"start must be None, 'uniform' or a state, got {start!r}")
            return V[:, self.start_cells].mean(-1)
        return V[:, torch.as_tensor(start, dtype=torch.int64, device=self.device)]

    # ---- mean MDP (paper §3.1) -------------------------------------------------------------------

    @cached_property
    def _mean_probs(self) -> Tensor:
        """``(1, X, A, K)``: the prior mean of the augmented kernel (exact: affine in q and f)."""
        ti = self.train_instances
        if ti.points is not None:
            q, f = self.instance_set(ti)
            return self.kernel_probs(q, f).mean(0, keepdim=True)
        q, f, w = self.quadrature(ti)
        return torch.einsum("k,kxaj->xaj", w, self.kernel_probs(q, f)).unsqueeze(0)

    @cached_property
    def _aboard_at_landmark(self) -> Tensor:
        """``(S,)`` bool: passenger aboard and the taxi on a landmark (where pending matters)."""
        pos, pas, _ = state_parts(torch.arange(self.S, device=self.device))
        lm = torch.tensor([r * 5 + c for r, c in taxi.LOCS], device=self.device)
        return (pas == taxi.IN_TAXI) & (pos.unsqueeze(-1) == lm).any(-1)

    def project(self, w: Tensor) -> tuple[Tensor, Tensor]:
        """Mean MDP over the 500 observed states ``(P̄ (S, A, S), R̄ (S, A))`` for pending weights
        ``w (S,)`` (``P(pending | s)``; used only where it matters)."""
        S = self.S
        prob = self._mean_probs[0]  # (X, A, K)
        w = torch.where(self._aboard_at_landmark, w.to(torch.float64), 0.0).view(S, 1, 1)
        p = torch.cat([(1.0 - w) * prob[:S], w * prob[S:]], -1)  # (S, A, 2K)
        s2 = torch.cat([self.succ[:S], self.succ[S:]], -1) % S  # (S, A, 2K)
        P = torch.zeros(S, self.A, S, dtype=torch.float64, device=self.device)
        return P.scatter_add_(2, s2, p), self.R

    def occupancy(self, policy: Tensor, instances: Any = None) -> Tensor:
        """``(X,)`` expected number of visits per episode (``horizon`` steps, uniform starts,
        pending at the start) of a deterministic policy ``(S,)`` over an instance distribution."""
        q, f, w = self.quadrature(instances)
        prob = self.kernel_probs(q, f)  # (B, X, A, K)
        B, X = q.numel(), self.X
        pol = policy.to(self.device).repeat(2)  # (X,)
        idx = pol.view(1, X, 1, 1).expand(B, X, 1, _K)
        p = prob.gather(2, idx).squeeze(2)  # (B, X, K)
        s = self.succ.gather(1, pol.view(X, 1, 1).expand(X, 1, _K)).squeeze(1)  # (X, K)
        d = torch.zeros(B, X, dtype=torch.float64, device=self.device)
        d[:, self.S + self.start_cells] = 1.0 / self.start_cells.numel()
        live = (~self.is_goal_x).to(torch.float64)
        occ = torch.zeros_like(d)
        for _ in range(self.horizon):
            d = d * live
            occ += d
            d = torch.zeros_like(d).scatter_add_(
                1, s.reshape(1, -1).expand(B, -1), (d.unsqueeze(-1) * p).reshape(B, -1)
            )
        return torch.einsum("b,bx->x", w, occ)

    def pending_weights(self, policy: Tensor) -> Tensor:
        """``w (S,)`` = P(pending | s) under ``policy``'s occupancy; 1 where it never visits s."""
        occ = self.occupancy(policy).view(2, self.S)
        tot = occ.sum(0)
        return torch.where(tot > 0, occ[1] / tot.clamp_min(1e-300), 1.0)

    @cached_property
    def _mean_mdp(self) -> tuple[Tensor, Tensor, Tensor]:
        w = torch.ones(self.S, dtype=torch.float64, device=self.device)  # the pickup reading
        P, R = self.project(w)
        Q = self._solve_obs(P, R)
        if self.fickle_weights == "visits":
            seen = []
            for _ in range(50):
                pol = greedy(Q)
                w = self.pending_weights(pol)
                P, R = self.project(w)
                Q = self._solve_obs(P, R)
                new = greedy(Q)
                if bool((new == pol).all()):
                    break
                key = tuple(new.tolist())
                if key in seen:
                    raise RuntimeError("the visit-weighted mean MDP has no fixed point (cycle)")
                seen.append(key)
            else:  # pragma: no cover
                raise RuntimeError("the visit-weighted mean MDP did not converge")
        return P, R, w

    def _solve_obs(self, P: Tensor, R: Tensor, cont: Tensor | None = None) -> Tensor:
        Q = solve_mdp(P, R, self.gamma, cont=cont, tol=self.tol)
        return self._zero_goal(Q)

    def _zero_goal(self, q: Tensor) -> Tensor:
        """Values ``(..., S, X)`` with delivered rows set to exactly 0."""
        return q.masked_fill(self.is_goal.view(-1, 1), 0.0)

    def mean_mdp(self) -> tuple[Tensor, Tensor]:
        """The training distribution's mean MDP over the 500 Taxi states ``(P̄ (S, A, S), R̄ (S,
        A))`` (paper §3.1; the hidden fickle status weighed as ``fickle_weights`` says)."""
        P, R, _ = self._mean_mdp
        return P, R

    def mean_pending_weights(self) -> Tensor:
        """``w (S,)``: the pending weights the mean MDP uses (module docstring)."""
        return self._mean_mdp[2]

    @cached_property
    def _averaging_q(self) -> Tensor:
        return self._solve_obs(*self.mean_mdp())

    def averaging_q(self) -> Tensor:
        """Optimal ``Q (S, A)`` of the mean MDP: the averaging policy's values (paper §3.1)."""
        return self._averaging_q

    def averaging_policy(self) -> Tensor:
        """The averaging policy pi_bar ``(S,)`` int64: greedy in :meth:`averaging_q`."""
        return greedy(self.averaging_q())

    # ---- subtask tables and options (paper §3.2) -------------------------------------------------

    def _cells_td(self, cells: Tensor) -> TensorDict:
        return TensorDict({keys.CELL: cells}, batch_size=cells.shape, device=self.device)

    @cached_property
    def initiation_table(self) -> Tensor:
        """``I (S, O)`` bool from :class:`TaxiSubtasks`."""
        return self.subtasks.initiation(self._cells_td(torch.arange(self.S, device=self.device)))

    @cached_property
    def termination_table(self) -> Tensor:
        """``beta (S, O)`` float64 from :class:`TaxiSubtasks`."""
        cells = torch.arange(self.S, device=self.device)
        return self.subtasks.termination(self._cells_td(cells)).to(torch.float64)

    @cached_property
    def subtask_reward_table(self) -> Tensor:
        """``r_o(s, a, j) (O, S, A, 3)`` float64 per rain outcome j, from :class:`TaxiSubtasks`
        (the fickle redraw changes no subtask reward: it moves no taxi and delivers nothing)."""
        S, A = self.S, self.A
        s = torch.arange(S, device=self.device).view(S, 1, 1).expand(S, A, 3).reshape(-1)
        nxt = self.model.next.reshape(-1)
        r_env = self.model.reward.view(S, A, 1).expand(S, A, 3).reshape(-1)
        td = self._cells_td(s)
        td.set(keys.NEXT, TensorDict({keys.CELL: nxt, keys.REWARD: r_env}, batch_size=s.shape))
        r = self.subtasks.reward(td).to(torch.float64)  # (S*A*3, O)
        return r.T.reshape(self.O, S, A, 3)

    def _option_reward(self, o: int) -> Tensor:
        """Option ``o``'s expected subtask reward ``(S, A)`` on the mean MDP (0 when delivered)."""
        p = self._mean_probs[0, : self.S].reshape(self.S, self.A, 3, 4).sum(-1)  # (S, A, 3)
        r = (p * self.subtask_reward_table[o]).sum(-1)
        return r.masked_fill(self.is_goal.view(-1, 1), 0.0)

    @cached_property
    def _option_q(self) -> Tensor:
        P, _ = self.mean_mdp()
        Rs = torch.stack([self._option_reward(o) for o in range(self.O)])  # (O, S, A)
        cont = 1.0 - self.termination_table.T  # (O, S')
        Q = solve_mdp(P.expand(self.O, -1, -1, -1), Rs, self.gamma, cont=cont, tol=self.tol)
        return self._zero_goal(Q)

    def option_q(self) -> Tensor:
        """``Q_o (O, S, A)``: each option's averaging values on the mean MDP (subtask reward and
        termination; defined on every state, used on its initiation set and after)."""
        return self._option_q

    def option_policies(self) -> Tensor:
        """``pi^o (O, S)`` int64: greedy in :meth:`option_q`."""
        return greedy(self.option_q())

    # ---- switching and max-values (paper §3.2, §3.3) -------------------------------------------

    def masked_mu(self, q_mu: Tensor, init: Tensor | None = None) -> Tensor:
        """mu_bar ``(S, O)`` restricted to the initiable options: greedy one-hot (lowest index on
        ties) or softmax of ``Q_mu`` masked to ``init (S, O)``; all-zero rows where none is."""
        init = self.initiation_table if init is None else init
        masked = q_mu.masked_fill(~init, -math.inf)
        if self.mu_temperature is None:
            mu = nn.functional.one_hot(masked.argmax(-1), self.O).to(q_mu.dtype)
        else:
            mu = torch.softmax(masked / self.mu_temperature, dim=-1)
        return torch.where(init.any(-1, keepdim=True), mu.nan_to_num(0.0), 0.0)

    def _smdp_values(
        self, prob: Tensor, succ_x: bool, mu: Tensor, tol: float | None = None
    ) -> Tensor:
        """``Q^{m, mu}(x, o) (B, *, O)``: run pi^o from x, then continue with ``mu (S, O)`` where
        o terminates (iterative evaluation to the certified ``tol``). ``prob`` is over
        :attr:`succ` (augmented, ``succ_x``) or a projected observed kernel's successors."""
        pol = self.option_policies()  # (O, S)
        if succ_x:
            succ, n = self.succ, self.X
            pol_x = pol.repeat(1, 2)  # (O, X)
        else:
            succ, n = self._obs_succ, self.S
            pol_x = pol
        B, O, K = prob.shape[0], self.O, succ.shape[-1]  # noqa: E741
        idx = pol_x.T.reshape(1, n, O, 1).expand(B, n, O, K)
        p = prob.gather(2, idx)  # (B, n, O, K)
        s2 = succ.gather(1, pol_x.T.reshape(n, O, 1).expand(n, O, K))  # (n, O, K)
        r = self.R.repeat(2, 1) if succ_x else self.R
        r = r.gather(1, pol_x.T)  # (n, O)
        beta = self.termination_table.repeat(2, 1) if succ_x else self.termination_table  # (n, O)
        mu_n = mu.repeat(2, 1) if succ_x else mu  # (n, O)
        goal = self.is_goal_x if succ_x else self.is_goal
        flat = (s2 * O + torch.arange(O, device=self.device).view(1, O, 1)).reshape(1, -1)
        flat = flat.expand(B, -1)  # (B, n*O*K): (x', o) for the running option o
        Q = torch.zeros(B, n, O, dtype=torch.float64, device=self.device)
        bound = (self.tol if tol is None else tol) * (1.0 - self.gamma) / self.gamma
        for _ in range(1_000_000):
            V = (mu_n * Q).sum(-1, keepdim=True)  # (B, n, 1)
            cont = beta * V + (1.0 - beta) * Q  # (B, n, O): value on arriving at x'
            nxt = cont.reshape(B, -1).gather(1, flat).view(B, n, O, K)
            Q_new = r + self.gamma * (p * nxt).sum(-1)
            Q_new = Q_new.masked_fill(goal.view(1, -1, 1), 0.0)
            delta = float((Q_new - Q).abs().max())
            Q = Q_new
            if delta < bound:
                return Q
        raise RuntimeError("option values did not converge")  # pragma: no cover

    @cached_property
    def _obs_succ(self) -> Tensor:
        """``(S, A, 2K)`` observed successors of the projected mean MDP (:meth:`project`)."""
        return torch.cat([self.succ[: self.S], self.succ[self.S :]], -1) % self.S

    def _projected_probs(self) -> Tensor:
        S = self.S
        prob = self._mean_probs[0]
        w = torch.where(self._aboard_at_landmark, self.mean_pending_weights(), 0.0).view(S, 1, 1)
        return torch.cat([(1.0 - w) * prob[:S], w * prob[S:]], -1).unsqueeze(0)  # (1, S, A, 2K)

    @cached_property
    def _switching_q(self) -> Tensor:
        prob = self._projected_probs()
        init = self.initiation_table
        mu = init.to(torch.float64) / init.sum(-1, keepdim=True).clamp_min(1)
        q = self._smdp_values(prob, False, mu)[0]
        for _ in range(100):  # policy iteration over mu_bar
            mu = self.masked_mu(snap_ties(q.masked_fill(~init, -1e300)))
            q_new = self._smdp_values(prob, False, mu)[0]
            done = bool((q_new - q).abs().max() < 1e-8)
            q = q_new
            if done:
                break
        else:  # pragma: no cover
            raise RuntimeError("switching values did not converge")
        snapped = snap_ties(q.masked_fill(~init, -math.inf))  # ties among the initiable options
        return torch.where(init, snapped, q)

    def switching_q(self) -> Tensor:
        """``Q_mu (S, O)``: option values of mu_bar on the mean MDP, env reward (paper §3.2);
        mu_bar is greedy (or softmax) in these values over the options initiable at s."""
        return self._switching_q

    def mu_bar(self) -> Tensor:
        """mu_bar ``(S, O)`` over the initiable options (:meth:`masked_mu`)."""
        return self.masked_mu(self.switching_q())

    def v_mu_bar(self) -> Tensor:
        """``V^{mu_bar}(s) = sum_q mu_bar(s, q) Q_mu(s, q)`` over the initiable q ``(S,)``."""
        return (self.mu_bar() * self.switching_q()).sum(-1)

    def instance_option_q(self, q: Any, f: Any) -> Tensor:
        """``Q^{m, mu_bar}((s, k), o)`` ``(B, 2, S, O)`` (``k`` = pending) in instances ``(q, f)``."""
        qt, ft, scalar = self._instances_arg(q, f)
        out = self._smdp_values(self.kernel_probs(qt, ft), True, self.mu_bar(), tol=1e-8)
        out = out.reshape(-1, 2, self.S, self.O)
        return out[0] if scalar else out

    def max_value(self, instances: Any = None) -> Tensor:
        """``Q_hat (S, O)``: max over the instance set and the hidden fickle status of
        ``Q^{m, mu_bar}`` (Definition 1); values within ``TIE_ATOL`` of ``V^{mu_bar}`` snap to it."""
        if instances is None:
            return self._max_value_default
        return self._max_value(*self.instance_set(instances))

    def _max_value(self, q: Tensor, f: Tensor) -> Tensor:
        chunks = [
            self.instance_option_q(q[i : i + 16], f[i : i + 16]).amax((0, 1))
            for i in range(0, q.numel(), 16)
        ]
        q_hat = torch.stack(chunks).amax(0)  # (S, O)
        v = self.v_mu_bar().unsqueeze(-1)
        return torch.where((q_hat - v).abs() <= 1e-7, v.expand_as(q_hat), q_hat)

    @cached_property
    def _max_value_default(self) -> Tensor:
        return self._max_value(*self.instance_set(None))

    # ---- heads -----------------------------------------------------------------------------------

    def heads(self, in_key: Any = keys.CELL, dtype: torch.dtype = torch.float64) -> Heads:
        """A :class:`Heads` bundle of the oracle's tables (averaging, options, switching, max-value),
        reading ``in_key`` (``keys.CELL`` or the one-hot ``keys.OBSERVATION``)."""
        t = dict(dtype=dtype, device=self.device)
        return table_heads(
            self.option_names,
            averaging=self.averaging_q().to(**t),
            options=self.option_q().permute(1, 0, 2).contiguous().to(**t),
            switching=self.switching_q().to(**t),
            max_value=self.max_value().to(**t),
            in_key=in_key,
            softmax_temperature=self.mu_temperature,
        )

    def observation_td(self, obs_encoding: str = "onehot") -> TensorDict:
        """A ``(S,)`` tensordict of every Taxi state: ``cell`` and its ``observation`` in
        ``obs_encoding`` (``families/taxi/env.py``: onehot or factored), so learnt heads are read at
        every state."""
        cells = torch.arange(self.S, device=self.device)
        obs = torch.as_tensor(observation_table(obs_encoding), device=self.device)
        return TensorDict(
            {keys.CELL: cells, keys.OBSERVATION: obs}, batch_size=[self.S], device=self.device
        )

    # ---- controllers as chains (Algorithm 1 with initiation sets) -------------------------------

    def controller_chain(self, controller: Any, **kwargs: Any) -> dict[str, Tensor]:
        """The controller as a chain on (Taxi state, carried state) with initiation sets honoured.

        As :meth:`ControllerChains.controller_chain` (``decision (S, Z, N)``, ``action (S, N)``,
        ``next_state (N,)``, ``fires (S, Z)``; ``Z = O + 1``) with one more acting entry
        ``n = O``: the averaging action, holding no option (``z' = 0``), used where no option is
        initiable. No hierarchy (Taxi's options are flat).
        """
        name = controller if isinstance(controller, str) else controller.name
        if name not in CONTROLLER_NAMES or name == "hierarchy":
            raise ValueError(
                f"controller must be one of ['averaging', 'options', 'interruption'], got {name!r}"
            )
        heads = kwargs.get("heads")
        subtasks = kwargs.get("subtasks")
        if not isinstance(controller, str):
            heads, subtasks = controller.heads, controller.subtasks
        if heads is None:
            heads = self.heads()
        subtasks = self.subtasks if subtasks is None else subtasks
        t = self.tabulate(heads, kwargs.get("obs_encoding") or self.obs_encoding)
        if name == "averaging":
            return self._averaging_chain(t)
        return self._initiation_chain(t, heads, subtasks, interrupt=name == "interruption")

    def _initiation_chain(
        self, t: dict[str, Tensor], heads: Heads, subtasks: Any, interrupt: bool
    ) -> dict[str, Tensor]:
        """Algorithm 1 over initiable options: line 4's argmax and line 7's draw over I(s), line
        6's ``V^{mu_bar}(s)`` over I(s); no initiable option: the averaging action."""
        S, O, dev = self.S, self.O, self.device  # noqa: E741
        cells = self._cells_td(torch.arange(S, device=dev))
        init = subtasks.initiation(cells)  # (S, O)
        beta = subtasks.termination(cells)  # (S, O)
        q_mu = t[keys.OPTION_VALUE].to(torch.float64)  # (S, O)
        any_init = init.any(-1)  # (S,)
        if heads.softmax_temperature is None:
            mu = nn.functional.one_hot(q_mu.masked_fill(~init, -math.inf).argmax(-1), O).to(
                torch.float64
            )
        else:
            mu = torch.softmax(q_mu.masked_fill(~init, -math.inf) / heads.softmax_temperature, -1)
        mu = torch.where(any_init.unsqueeze(-1), mu.nan_to_num(0.0), 0.0)  # (S, O)
        fallback = nn.functional.one_hot(torch.full((S,), O, device=dev), O + 1).to(torch.float64)
        pick = torch.where(
            any_init.unsqueeze(-1),
            torch.cat(
                [
                    nn.functional.one_hot(q_mu.masked_fill(~init, -math.inf).argmax(-1), O).to(
                        torch.float64
                    ),
                    torch.zeros(S, 1, dtype=torch.float64, device=dev),
                ],
                -1,
            ),
            fallback,
        )  # (S, N) line 4 (argmax even for a softmax mu_bar)
        draw = torch.where(
            any_init.unsqueeze(-1),
            torch.cat([mu, torch.zeros(S, 1, dtype=torch.float64, device=dev)], -1),
            fallback,
        )  # (S, N) line 7
        v = (mu * q_mu.masked_fill(~init, 0.0)).sum(-1)  # (S,) V^{mu_bar}(s) over I(s)
        N, Z = O + 1, O + 1
        decision = torch.zeros(S, Z, N, dtype=torch.float64, device=dev)
        fires = torch.zeros(S, Z, dtype=torch.bool, device=dev)
        decision[:, 0] = pick
        stay = nn.functional.one_hot(torch.arange(O, device=dev), N).to(torch.float64)  # (O, N)
        ended = beta  # (S, O): o_run terminated at s
        below = (
            (t[keys.MAX_VALUE].to(torch.float64) < v.unsqueeze(-1)) & any_init.unsqueeze(-1)
            if interrupt
            else torch.zeros_like(beta)
        )  # (S, O) line 6
        run = torch.where(below.unsqueeze(-1), draw.unsqueeze(1), stay.unsqueeze(0))  # (S, O, N)
        decision[:, 1:] = torch.where(ended.unsqueeze(-1), pick.unsqueeze(1), run)
        fires[:, 1:] = below & ~ended
        act_opt = t[keys.OPTION_ACTION_VALUE].argmax(-1)  # (S, O)
        act_avg = t[keys.ACTION_VALUE].argmax(-1) if keys.ACTION_VALUE in t else act_opt[:, 0]
        action = torch.cat([act_opt, act_avg.unsqueeze(-1)], -1)  # (S, N)
        next_state = torch.cat(
            [torch.arange(1, O + 1, device=dev), torch.zeros(1, dtype=torch.int64, device=dev)]
        )
        return {"decision": decision, "action": action, "next_state": next_state, "fires": fires}

    @cached_property
    def _succ3(self) -> Tensor:
        """``(X, A, 3)`` successor per rain outcome into the extended table of :meth:`_extend`:
        unpended ``s'``; pending ``500 + s'``, or ``1000 + s'`` where the fickle rule fires."""
        S, A = self.S, self.A
        nxt = self.succ[:S].reshape(S, A, 3, 4)[..., 3]  # (S, A, 3)
        pend = torch.where(self._fire[S:], 2 * S + nxt, S + nxt)
        return torch.cat([nxt, pend])

    def _extend(self, V: Tensor, fr: Tensor) -> Tensor:
        """``U (B, 3S, ...)`` from augmented ``V (B, X, ...)``: unpended and pending values, then
        the value of arriving at ``s'`` on a firing step (redraw with probability ``fr (B,)``)."""
        S = self.S
        vu = V[:, :S]
        t = self._targets_t  # (3, S): the three redraws of each s'
        vr = (vu[:, t[0]] + vu[:, t[1]] + vu[:, t[2]]) / 3.0  # (B, S, ...)
        fr = fr.view(-1, *([1] * (V.dim() - 1)))
        return torch.cat([vu, V[:, S:], fr * vr + (1.0 - fr) * vu], 1)

    @cached_property
    def _targets_t(self) -> Tensor:
        return self.model.fickle_targets.T.contiguous()  # (3, S)

    def _chain_values(
        self, q: Tensor, f: Tensor, chain: dict[str, Tensor], count_fires: bool = False
    ) -> Tensor:
        """``V_H (B, X, Z)`` by backward induction on (augmented state, carried state); with
        ``count_fires`` the per-step reward is the ``fires (s, z)`` indicator (0 when delivered)."""
        D, act, nz = chain["decision"], chain["action"], chain["next_state"]  # (S,Z,N) (S,N) (N,)
        B, X = q.numel(), self.X
        N, Z = act.shape[1], D.shape[1]
        act_x = act.repeat(2, 1)  # (X, N)
        D_x = D.repeat(2, 1, 1)  # (X, Z, N)
        one_hot = bool((D_x.max(-1).values == 1.0).all())  # greedy: a gather, not a sum
        pick = D_x.argmax(-1).unsqueeze(0).expand(B, X, Z)  # (B, X, Z)
        po = self._outcome_probs(q)  # (B, A, 3)
        p = po[:, act_x].permute(0, 3, 1, 2).contiguous()  # (B, 3, X, N)
        s2 = self._succ3.gather(1, act_x.view(X, N, 1).expand(X, N, 3))  # (X, N, 3)
        flat = (s2 * Z + nz.view(1, N, 1)).permute(2, 0, 1).reshape(1, -1).expand(B, -1)
        rn = self.R_x.gather(1, act_x).unsqueeze(0)  # (1, X, N)
        if count_fires:
            rn = torch.zeros_like(rn)
            fz = (chain["fires"] & ~self.is_goal.view(-1, 1)).to(torch.float64).repeat(2, 1)
        V = torch.zeros(B, X, Z, dtype=torch.float64, device=self.device)
        for _ in range(self.horizon):
            U = self._extend(V, f).reshape(B, -1)  # (B, 3S*Z)
            nxt = U.gather(1, flat).view(B, 3, X, N)
            W = rn + p[:, 0] * nxt[:, 0] + p[:, 1] * nxt[:, 1] + p[:, 2] * nxt[:, 2]  # (B, X, N)
            V = W.gather(2, pick) if one_hot else torch.einsum("xzn,bxn->bxz", D_x, W)
            if count_fires:
                V = V + fz
        return V

    def _chain_values_by_rain(
        self, q: Tensor, f: Tensor, chain: dict[str, Tensor], count_fires: bool = False
    ) -> Tensor:
        """:meth:`_chain_values` for many instances at the cost of their distinct rain values:
        a chain's value is affine in f (the redraw happens at most once an episode, with
        probability f), so it is solved at f = 0 and f = 1 per distinct q and interpolated."""
        uq, inv = torch.unique(q, return_inverse=True)  # (U,), (B,)
        if 2 * uq.numel() >= q.numel():
            return self._chain_values(q, f, chain, count_fires)
        ends = torch.cat([torch.zeros_like(uq), torch.ones_like(uq)])
        V = self._chain_values(uq.repeat(2), ends, chain, count_fires)  # (2U, X, Z)
        V0, V1 = V[: uq.numel()][inv], V[uq.numel() :][inv]  # (B, X, Z)
        return V0 + f.view(-1, 1, 1) * (V1 - V0)

    def controller_return(
        self, controller: Any, q: Any, f: Any, start: Any = None, **kwargs: Any
    ) -> Tensor:
        """Exact expected ``horizon``-step undiscounted return ``(B, S)`` of a controller (a name
        in ``averaging``, ``options``, ``interruption`` with the oracle's heads, or a
        :class:`~taskvar_torch.controllers.base.Controller`) in instances ``(q, f)``, from each
        Taxi start state (``start``: ``None`` all, ``"uniform"`` Taxi-v4's starts, or a state);
        ``kwargs``: ``heads``, ``subtasks``, ``obs_encoding`` for a named controller."""
        qt, ft, scalar = self._instances_arg(q, f)
        chain = self.controller_chain(controller, **kwargs)
        V = self._chain_values_by_rain(qt, ft, chain)[..., 0]  # (B, X)
        out = self._select_start(V[:, self.S :], start)  # episodes start pending
        return out[0] if scalar else out

    def controller_fire_count(
        self, controller: Any, q: Any, f: Any, start: Any = None, **kwargs: Any
    ) -> Tensor:
        """Exact expected number of interruptions (Algorithm 1 line 6 firing) per episode."""
        qt, ft, scalar = self._instances_arg(q, f)
        chain = self.controller_chain(controller, **kwargs)
        V = self._chain_values(qt, ft, chain, count_fires=True)[..., 0]
        out = self._select_start(V[:, self.S :], start)
        return out[0] if scalar else out

    def controller_expected_return(
        self,
        controller: Any,
        instances: Any = None,
        starts: Any = "uniform",
        count_fires: bool = False,
        **kwargs: Any,
    ) -> Tensor:
        """A controller's exact expected return (or firing count) over an instance distribution
        (:meth:`quadrature`: exact, module docstring)."""
        q, f, w = self.quadrature(instances)
        fn = self.controller_fire_count if count_fires else self.controller_return
        out = torch.cat(
            [
                fn(controller, q[i : i + 32], f[i : i + 32], start=starts, **kwargs)
                for i in range(0, q.numel(), 32)
            ]
        )
        return torch.einsum("k,k...->...", w, out)

    def expected_return(
        self, policy: Tensor, instances: Any = None, starts: Any = "uniform"
    ) -> Tensor:
        """``E_m[return]`` of a stationary policy ``(S,)`` over the Taxi states (exact quadrature)."""
        q, f, w = self.quadrature(instances)
        pol = policy.to(self.device)
        chain = {
            "decision": torch.ones(self.S, 1, 1, dtype=torch.float64, device=self.device),
            "action": pol.view(-1, 1),
            "next_state": torch.zeros(1, dtype=torch.int64, device=self.device),
            "fires": torch.zeros(self.S, 1, dtype=torch.bool, device=self.device),
        }
        V = self._chain_values(q, f, chain)[..., 0]
        return torch.einsum("k,k...->...", w, self._select_start(V[:, self.S :], starts))

    def expected_optimal_return(
        self,
        instances: Any = None,
        starts: Any = "uniform",
        informed: bool = False,
        q_nodes: int = 16,
        f_nodes: int = 8,
    ) -> Tensor:
        """The per-instance optimum's expected return over a distribution, by quadrature of
        :meth:`optimal_return` over q (:meth:`quadrature`'s nodes) *and* f: unlike a fixed
        controller's, the optimum is not affine in f (it adapts to it: convex), so f is
        integrated too (``f_nodes`` Gauss-Legendre nodes over the fickle range, plus f = 0; in q,
        ``q_nodes``). In q and f the optimum is only piecewise polynomial: an approximation (the
        training distribution's 6.1364 at 16 x 8 nodes is 6.1364 at 100 x 8)."""
        dist = self.train_instances if instances is None else taxi_instances(instances)
        q, f, w = self.quadrature(dist, nodes=q_nodes)
        if dist.points is None:  # replace f = E f by nodes over f's own distribution
            fx = [self._f([0.0])] if dist.fickle_share < 1 else []
            fw = [self._f([1.0 - dist.fickle_share])] if dist.fickle_share < 1 else []
            if dist.fickle_share > 0:
                n = 1 if dist.f_low == dist.f_high else int(f_nodes)
                x, xw = gauss_legendre(n, dist.f_low, dist.f_high)
                fx.append(x.to(self.device))
                fw.append(xw.to(self.device) * dist.fickle_share)
            fx, fw = torch.cat(fx), torch.cat(fw)
            q, f = q.repeat_interleave(fx.numel()), fx.repeat(w.numel())
            w = (w.unsqueeze(-1) * fw.unsqueeze(0)).reshape(-1)
        ret = self.optimal_return(q, f, start=starts, informed=informed)
        return torch.einsum("k,k...->...", w, ret)
