"""The models of the Taxi family's exact oracle (paper §3.1): augmented states, their sparse kernels
per instance ``(q, f)``, quadrature, the sparse solvers and the per-instance optimum; the base of
:class:`~taskvar_torch.families.taxi.oracle.TaxiOracle`, whose module docstring gives the design.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np
import torch

from taskvar_torch.families.taxi import dynamics as taxi
from taskvar_torch.families.taxi.dynamics import TaxiInstances, taxi_instances
from taskvar_torch.families.taxi.subtasks import TaxiSubtasks, state_parts
from taskvar_torch.oracle.chains import ControllerChains
from taskvar_torch.oracle.mdp import TIE_ATOL, gauss_legendre, greedy, snap_ties

Tensor = torch.Tensor

FICKLE_WEIGHTS = ("visits", "pickup")
_K = 4 * taxi.NUM_OUTCOMES  # successors per (x, a): 3 rain outcomes x (3 redraws, no redraw)


class TaxiModels(ControllerChains):
    """The instance models and the per-instance optimum of :class:`~taskvar_torch.families.taxi.oracle.TaxiOracle`
    (its arguments: that class)."""

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
        """``prob (B, X, A, 12)`` over :attr:`succ` for instances ``(q, f)``; pending rows redraw
        with probability f (``informed``: armed rows with probability 1).
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
        """Exact augmented models ``P (B, X, A, X)``, ``R (B, X, A)``, ``done (B, X, A)`` (float64,
        X = 1000).
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
        """``(q (K,), f (K,), weight (K,))``, exact for returns: the points, or Gauss-Legendre in q
        over the rainy range plus the dry ``q = 1``, each with ``f = E f``.
        """
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
        """Exact per-instance optimal ``horizon``-step return ``(B, S)`` by backward induction, from
        each start (``start`` as in :meth:`controller_return`).
        """
        qt, ft, scalar = self._instances_arg(q, f)
        steps = self._optimal_steps(qt, torch.ones_like(ft) if informed else ft)
        _, _, V = deque(steps, maxlen=1)[0]  # the last: horizon steps to go (earlier W dropped)
        out = self._select_start(self._start_mix(V, ft, informed), start)
        return out[0] if scalar else out

    def _optimal_steps(self, q: Tensor, fr: Tensor) -> Iterator[tuple[int, Tensor, Tensor]]:
        """Yields ``(togo, W (B, X, A), V)`` of the per-instance optimum for ``togo = 1 ..
        horizon``.
        """
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
        """Instantaneous regret ``(B, T)`` of the actions played: ``V*_{H-t}(x_t) - Q*_{H-t}(x_t,
        a_t)``, 0 where not ``alive``; ``cells``, ``actions`` are ``(B, T)``, ``T <= horizon``.

        ``x_t`` is pending until the trace's first fickle move, so the reference knows (q, f) but
        not the coin; an episode's sum is its regret in expectation (docs/memory.md).
        """
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
