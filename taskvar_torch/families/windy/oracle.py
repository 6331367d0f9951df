"""The windy family's exact oracle, :class:`WindyOracle` (paper §3.1-3.4, Definition 1;
docs/oracle.md#design-decisions).
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import cached_property
from typing import Any

import torch
from tensordict import TensorDict
from torch import nn

from taskvar_torch import keys
from taskvar_torch.families.windy import dynamics as windy
from taskvar_torch.families.windy.env import observation_table
from taskvar_torch.families.windy.instances import WindyInstances
from taskvar_torch.families.windy.oracle_base import WindyOracleBase
from taskvar_torch.families.windy.replay_reference import ReplayReference
from taskvar_torch.families.windy.subtasks import WindySubtasks
from taskvar_torch.oracle.chains import ControllerChains
from taskvar_torch.oracle.mdp import (
    TIE_ATOL,
    greedy,
    policy_kernel,
    policy_reward,
    snap_ties,
    solve_mdp,
)
from taskvar_torch.oracle.tables import DerivedTables

Tensor = torch.Tensor


class WindyOracle(ControllerChains, ReplayReference, DerivedTables, WindyOracleBase):
    """Exact solver of a windy layout's family (docs/oracle.md).

    Args:
        model_or_layout: a ``WindyModel``, a layout, a layout name or a map string.
        gamma: discount of the values. horizon: episode length of the returns.
        train_instances: the training distribution (name, dict or :class:`WindyInstances`).
        wrong_exit_penalty: subtask penalty for leaving through another exit.
        p_grid: ``p`` values of Q_hat's instance set (an int: evenly spaced).
        mu_temperature: ``None`` for a greedy mu_bar, else a softmax temperature.
        quad_nodes: Gauss-Legendre nodes over ``p`` (default ``ceil(horizon/2)``).
        tol: value-iteration tolerance. device: torch device of the tables.
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
        super().__init__(
            model_or_layout, gamma, horizon, train_instances, p_grid, quad_nodes, device
        )
        self.subtasks = WindySubtasks(self.model, wrong_exit_penalty)
        self.option_names = self.subtasks.names
        self.O = len(self.option_names)  # noqa: E741
        self.mu_temperature = mu_temperature
        self.tol = float(tol)

    # ---- models -----------------------------------------------------------------------------

    def transition(self, p: Any, direction: Any) -> tuple[Tensor, Tensor]:
        """Exact instance models ``P (B, S, A, S)``, ``R (B, S, A)`` (float64)."""
        pt, d, _ = self._instances_arg(p, direction)
        return windy.transition_tensors(self.model, pt, d, dtype=torch.float64)

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
        """``Q^{m,mu}(s, o) (B, S, O)``: run option o from s, then continue with ``mu (S, O)``
        (SMDP; one exact linear solve)."""
        B, S, K = P.shape[0], self.S, self.O  # K options
        pol = self.option_policies() if policies is None else policies  # (K, S)
        Po = torch.stack([policy_kernel(P, pol[o]) for o in range(K)], 2)  # (B, S, K, S')
        ro = torch.stack([policy_reward(R, pol[o]) for o in range(K)], 2)  # (B, S, K)
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
        """``Q_mu (S, O)``: option values of mu_bar on the mean MDP, env reward (paper §3.2)."""
        return self._switching_q

    def mu_bar(self) -> Tensor:
        """mu_bar ``(S, O)``: greedy one-hot (lowest index on ties) or softmax in :meth:`switching_q`."""
        return self._mu(self.switching_q())

    def instance_option_q(self, p: Any, direction: Any) -> Tensor:
        """``Q^{m, mu_bar}(s, o)`` ``(B, S, O)`` (or ``(S, O)`` for a scalar instance) in instance m."""
        pt, d, scalar = self._instances_arg(p, direction)
        P, R = windy.transition_tensors(self.model, pt, d, dtype=torch.float64)
        q = self.option_values(P, R, self.mu_bar())
        return q[0] if scalar else q

    def _max_value(self, p: Tensor, d: Tensor) -> Tensor:
        chunks = [
            self.instance_option_q(p[i : i + 64], d[i : i + 64]) for i in range(0, p.numel(), 64)
        ]
        q_hat = torch.cat(chunks).max(0).values  # (S, O)
        v = self.v_mu_bar().unsqueeze(-1)  # (S, 1)
        return torch.where((q_hat - v).abs() <= TIE_ATOL, v.expand_as(q_hat), q_hat)

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
        Ppi, rpi = policy_kernel(P, policy), policy_reward(R, policy)
        eye = torch.eye(self.S, dtype=P.dtype, device=P.device)
        return torch.linalg.solve(eye - self.gamma * Ppi, rpi.unsqueeze(-1)).squeeze(-1)

    def _finite_horizon(self, Ppi: Tensor, rpi: Tensor) -> Tensor:
        """Backward induction over steps-to-go: ``V_H`` with ``V_k = r_pi + P_pi V_{k-1}``, ``V_0 = 0``."""
        V = torch.zeros_like(rpi)
        for _ in range(self.horizon):
            V = rpi + torch.einsum("bst,bt->bs", Ppi, V)
        return V

    def episode_return(self, policy: Tensor, p: Any, direction: Any, start: Any = None) -> Tensor:
        """Exact expected ``horizon``-step return of a stationary policy in an instance; ``start``:
        ``None`` (``(B, S)``), ``"uniform"``, a cell or ``(row, col)``.
        """
        pt, d, scalar = self._instances_arg(p, direction)
        P, R = windy.transition_tensors(self.model, pt, d, dtype=torch.float64)
        policy = policy.to(self.device)
        V = self._finite_horizon(policy_kernel(P, policy), policy_reward(R, policy))
        out = self._select_start(V, start)
        return out[0] if scalar else out

    def optimal_return(self, p: Any, direction: Any, start: Any = None) -> Tensor:
        """Exact per-instance optimal ``horizon``-step return ``(B, S)`` over all policies (backward
        induction), the ceiling of regret (docs/evaluation.md); ``start`` as in
        :meth:`episode_return`."""
        pt, d, scalar = self._instances_arg(p, direction)
        m = self.model
        moved = m.move  # (S, A)
        gust = m.push[moved.unsqueeze(0), d.view(-1, 1, 1)]  # (B, S, A)
        pp = pt.view(-1, 1, 1)
        goal = self.is_goal.view(1, -1)
        B = pt.numel()
        V = torch.zeros(B, self.S, dtype=torch.float64, device=self.device)
        for _ in range(self.horizon):
            nxt = (1.0 - pp) * V[:, moved] + pp * V.gather(1, gust.reshape(B, -1)).view_as(gust)
            V = torch.where(goal, 0.0, (nxt - 1.0).max(-1).values)
        out = self._select_start(V, start)
        return out[0] if scalar else out

    def step_regret(
        self, p: Any, direction: Any, cells: Any, actions: Any, alive: Any = None
    ) -> Tensor:
        """Instantaneous regret ``(B, T)``: ``V*_{H-t}(s_t) - Q*_{H-t}(s_t, a_t)``, 0 where not
        ``alive``; its sum over an episode is in expectation ``optimal_return - return``
        (docs/evaluation.md)."""
        pt, d, _ = self._instances_arg(p, direction)
        s, a, live = self._step_trace(pt.numel(), cells, actions, alive)
        B, T = s.shape
        m = self.model
        moved = m.move  # (S, A)
        gust = m.push[moved.unsqueeze(0), d.view(-1, 1, 1)]  # (B, S, A)
        pp = pt.view(-1, 1, 1)
        goal = self.is_goal.view(1, -1, 1)
        rows = torch.arange(B, device=self.device)
        out = torch.zeros(B, T, dtype=torch.float64, device=self.device)
        V = torch.zeros(B, self.S, dtype=torch.float64, device=self.device)
        for togo in range(1, self.horizon + 1):
            nxt = (1.0 - pp) * V[:, moved] + pp * V.gather(1, gust.reshape(B, -1)).view_as(gust)
            Q = torch.where(goal, 0.0, nxt - 1.0)  # (B, S, A), togo steps to go
            V = Q.max(-1).values
            t = self.horizon - togo
            if t < T:
                st, at = s[:, t], a[:, t]
                gap = V[rows, st] - Q[rows, st, at]
                out[:, t] = torch.where(live[:, t], gap, 0.0)
        return out

    def mean_mdp_return(self, policy: Tensor, start: Any = None) -> Tensor:
        """Exact ``horizon``-step return of a policy in the mean MDP (instance redrawn every step)."""
        P, R = self.mean_mdp()
        policy = policy.to(self.device)
        V = self._finite_horizon(policy_kernel(P[None], policy), policy_reward(R[None], policy))
        return self._select_start(V, start)[0]

    def expected_return(
        self, policy: Tensor, instances: Any = None, starts: Any = "uniform"
    ) -> Tensor:
        """``E_m[return]`` of a policy, instance drawn per episode (quadrature over ``instances``);
        ``starts``: ``"uniform"``, ``None`` (``(S,)``) or one cell.
        """
        pt, d, w = self.quadrature(instances)
        ret = self.episode_return(policy, pt, d, start=starts)  # (K, ...)
        return torch.einsum("k,k...->...", w, ret)

    # ---- heads ---------------------------------------------------------------------------------

    def observation_td(self, obs_encoding: str = "onehot") -> TensorDict:
        """A ``(S,)`` tensordict of every cell: ``cell`` and ``observation`` (for tabulating heads)."""
        cells = torch.arange(self.S, device=self.device)
        obs = torch.as_tensor(observation_table(self.layout, obs_encoding), device=self.device)
        return TensorDict(
            {keys.CELL: cells, keys.OBSERVATION: obs}, batch_size=[self.S], device=self.device
        )
