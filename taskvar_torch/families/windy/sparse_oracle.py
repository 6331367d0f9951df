"""Exact values of large windy layouts: :class:`SparseWindyOracle`
(docs/oracle.md#large-grids-the-sparse-oracle).

A kernel is a successor table ``succ, prob (B, S, A, K)``; every solve is a gather per sweep,
stopped at a certified error ``tol``, batched over instances, on any device. Ties are snapped at
``tie_atol``; on small layouts it agrees with ``WindyOracle`` to ``1e-8``.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import cached_property
from typing import Any

import torch

from taskvar_torch import keys
from taskvar_torch.controllers.interruption import interruption_decide_of
from taskvar_torch.families.windy import dynamics as windy
from taskvar_torch.families.windy.instances import WindyInstances
from taskvar_torch.families.windy.oracle_base import WindyOracleBase
from taskvar_torch.oracle.mdp import greedy, snap_ties

Tensor = torch.Tensor


class SparseKernel:
    """Windy kernels as successor tables: ``succ (B, S, A, K)`` int64, ``prob`` float64 (sums to
    1)."""

    def __init__(self, succ: Tensor, prob: Tensor):
        self.succ, self.prob = succ, prob
        self.B, self.S, self.A, self.K = succ.shape
        self._flat = succ.reshape(self.B, -1)
        self._planes: tuple[list[Tensor], list[Tensor]] | None = None

    def expect(self, V: Tensor) -> Tensor:
        """``E[V(s')] (B, S, A)`` for values ``V (B, S)``."""
        if self.K <= 2:  # one gather per outcome (expect_planes: the same bits, faster)
            if self._planes is None:
                self._planes = outcome_planes(self.succ, self.prob)
            return expect_planes(V, *self._planes).view(self.B, self.S, self.A)
        nxt = V.gather(1, self._flat).view(self.B, self.S, self.A, self.K)
        return (nxt * self.prob).sum(-1)

    def policy(self, policy: Tensor) -> SparseKernel:
        """The kernel of a deterministic policy ``(S,)`` or ``(B, S)`` as a one-action kernel."""
        pol = policy.to(torch.int64).expand(self.B, self.S).view(self.B, self.S, 1, 1)
        idx = pol.expand(self.B, self.S, 1, self.K)
        return SparseKernel(self.succ.gather(2, idx), self.prob.gather(2, idx))

    def expect_reward(self, r: Tensor) -> Tensor:
        """``E[r(s, s')] (B, S, A)`` for a transition reward ``r (S, S')`` given as a function
        ``(s (B, S, A, K), s' (B, S, A, K)) -> reward``."""
        s = torch.arange(self.S, device=self.succ.device).view(1, self.S, 1, 1)
        return (r(s.expand_as(self.succ), self.succ) * self.prob).sum(-1)


class SparseWindyOracle(WindyOracleBase):
    """Exact values of a windy layout of any size by per-instance iterations on successor tables.

    Args: as :class:`.oracle.WindyOracle` (``model_or_layout``, ``gamma``, ``horizon``,
    ``train_instances``, ``wrong_exit_penalty``, ``p_grid``, ``quad_nodes``, ``device``), plus
    ``tol`` (certified sup-norm error of every solve) and ``tie_atol`` (ties: lowest index wins).
    """

    def __init__(
        self,
        model_or_layout: windy.WindyModel | windy.WindyLayout | str = "default",
        gamma: float = 0.99,
        horizon: int | None = None,
        train_instances: str | dict | WindyInstances = "train",
        wrong_exit_penalty: float = 100.0,
        p_grid: int | Sequence[float] = 21,
        quad_nodes: int = 32,
        tol: float = 1e-8,
        tie_atol: float = 1e-6,
        device: torch.device | str = "cpu",
    ):
        if not 0 < tol < tie_atol:
            raise ValueError(f"tol must be in (0, tie_atol={tie_atol}), got {tol}")
        super().__init__(
            model_or_layout, gamma, horizon, train_instances, p_grid, quad_nodes, device
        )
        self.wrong_exit_penalty = float(wrong_exit_penalty)
        self.tol, self.tie_atol = float(tol), float(tie_atol)
        self.option_names = self.layout.exit_names
        self.O = self.layout.num_exits  # noqa: E741

    # ---- kernels --------------------------------------------------------------------------------

    def kernel(self, p: Any, direction: Any) -> SparseKernel:
        """Instances ``(p (B,), direction (B,))``: successors move / move-then-gust (``K = 2``);
        goals absorb."""
        p, d, _ = self._instances_arg(p, direction)
        B, S, A = p.numel(), self.S, self.A
        moved = self.model.move.unsqueeze(0).expand(B, S, A)
        gust = self.model.push[moved, d.view(B, 1, 1)]
        succ = torch.stack([moved, gust], -1)
        pp = p.view(B, 1, 1, 1).expand(B, S, A, 1)
        return SparseKernel(succ.contiguous(), torch.cat([1.0 - pp, pp], -1).contiguous())

    @cached_property
    def mean_kernel(self) -> SparseKernel:
        """The training distribution's mean MDP (paper §3.1), ``B = 1``: the move with probability
        ``1 - E[p]``, a gust towards d with ``E[p 1{dir = d}]`` (the kernel is affine in ``p``)."""
        ti = self.train_instances
        D = len(windy.DIRECTIONS)
        w = torch.zeros(D, dtype=torch.float64, device=self.device)
        if ti.points is not None:
            for p, d in ti.points:
                w[windy.direction_index(d)] += p / len(ti.points)
        else:
            mean_p = 0.5 * (ti.p_low + ti.p_high)
            for d in ti.directions:
                w[windy.direction_index(d)] += mean_p / len(ti.directions)
        moved = self.model.move  # (S, A)
        gusts = self.model.push[moved]  # (S, A, D)
        succ = torch.cat([moved.unsqueeze(-1), gusts], -1).unsqueeze(0)  # (1, S, A, 1 + D)
        prob = torch.cat([(1.0 - w.sum()).view(1), w]).expand(1, self.S, self.A, 1 + D)
        return SparseKernel(succ.contiguous(), prob.contiguous())

    # ---- rewards ---------------------------------------------------------------------------------

    def _env_reward(self, kernel: SparseKernel) -> Tensor:
        """``R (B, S, A)``: -1 per step outside the goal, 0 at the goal."""
        R = torch.full((kernel.B, self.S, self.A), -1.0, dtype=torch.float64, device=self.device)
        return R.masked_fill(self.is_goal.view(1, -1, 1), 0.0)

    def _option_reward(self, kernel: SparseKernel, o: int) -> Tensor:
        """Option ``o``'s expected subtask reward ``(B, S, A)``: -1 per step, and the wrong-exit
        penalty on arriving at the goal from another exit's cell (families/windy/subtasks.py)."""
        goal, exit_id, pen = self.is_goal, self.model.exit_id, self.wrong_exit_penalty

        def r(s: Tensor, s2: Tensor) -> Tensor:
            wrong = goal[s2] & (exit_id[s] != o)
            return -1.0 - pen * wrong.to(torch.float64)

        return kernel.expect_reward(r).masked_fill(self.is_goal.view(1, -1, 1), 0.0)

    # ---- solvers ---------------------------------------------------------------------------------

    def _bound(self) -> float:
        return self.tol * (1.0 - self.gamma) / max(self.gamma, 1e-300)

    def _start_values(self, B: int) -> Tensor:
        """``-1 / (1 - gamma)`` outside the goal (never arriving), 0 at the goal: the exact value of
        every cell a policy never leads to the goal from, so only the cells that do arrive need
        iterations (the certificate holds from any start)."""
        V = torch.full(
            (B, self.S), -1.0 / (1.0 - self.gamma), dtype=torch.float64, device=self.device
        )
        return V.masked_fill(self.is_goal, 0.0)

    def solve(self, kernel: SparseKernel, R: Tensor, max_iter: int = 1_000_000) -> Tensor:
        """Optimal ``Q (B, S, A)``: value iteration until the certified error is below ``tol``."""
        V = self._start_values(kernel.B)
        for _ in range(max_iter):
            Q = R + self.gamma * kernel.expect(V)
            V_new = Q.max(-1).values.masked_fill(self.is_goal, 0.0)
            delta = float((V_new - V).abs().max())
            V = V_new
            if delta < self._bound():
                break
        else:  # pragma: no cover - a contraction always converges
            raise RuntimeError("value iteration did not converge")
        Q = R + self.gamma * kernel.expect(V)
        return snap_ties(Q.masked_fill(self.is_goal.view(1, -1, 1), 0.0), self.tie_atol)

    def evaluate_kernel(self, kernel: SparseKernel, R: Tensor, policy: Tensor) -> Tensor:
        """Discounted ``V (B, S)`` of a deterministic policy ``(S,)`` / ``(B, S)`` (to ``tol``)."""
        k = kernel.policy(policy)
        r = R.gather(2, policy.to(torch.int64).expand(kernel.B, self.S).unsqueeze(-1))[..., 0]
        V = self._start_values(kernel.B)
        for _ in range(1_000_000):
            V_new = (r + self.gamma * k.expect(V)[..., 0]).masked_fill(self.is_goal, 0.0)
            delta = float((V_new - V).abs().max())
            V = V_new
            if delta < self._bound():
                return V
        raise RuntimeError("policy evaluation did not converge")  # pragma: no cover

    # ---- averaging policy and options (paper §3.1, §3.2) ----------------------------------------

    @cached_property
    def _averaging_q(self) -> Tensor:
        k = self.mean_kernel
        return self.solve(k, self._env_reward(k))[0]

    def averaging_q(self) -> Tensor:
        """Optimal ``Q (S, A)`` of the mean MDP: the averaging policy's values (paper §3.1)."""
        return self._averaging_q

    def averaging_policy(self) -> Tensor:
        """The averaging policy ``(S,)`` int64: greedy in :meth:`averaging_q` (lowest on ties)."""
        return greedy(self.averaging_q(), self.tie_atol)

    @cached_property
    def _option_q(self) -> Tensor:
        k = self.mean_kernel
        return torch.stack([self.solve(k, self._option_reward(k, o))[0] for o in range(self.O)])

    def option_q(self) -> Tensor:
        """``Q_o (O, S, A)``: each exit option's optimal values on the mean MDP, subtask reward."""
        return self._option_q

    def option_policies(self) -> Tensor:
        """``pi^o (O, S)`` int64: greedy in :meth:`option_q`."""
        return greedy(self.option_q(), self.tie_atol)

    def option_objective(self, policies: Tensor | None = None) -> Tensor:
        """``V_o^{pi} (O, S)``: each option's own objective (discounted mean-MDP subtask value)
        for policies ``(O, S)`` (default: the optimal ones, i.e. ``max_a Q_o``)."""
        if policies is None:
            return self.option_q().max(-1).values
        k = self.mean_kernel
        return torch.stack(
            [
                self.evaluate_kernel(k, self._option_reward(k, o), policies[o])[0]
                for o in range(self.O)
            ]
        )

    def averaging_objective(self, policy: Tensor | None = None) -> Tensor:
        """``V^{pi} (S,)`` on the mean MDP, env reward (default: the optimum, ``max_a Q``)."""
        if policy is None:
            return self.averaging_q().max(-1).values
        k = self.mean_kernel
        return self.evaluate_kernel(k, self._env_reward(k), policy)[0]

    # ---- switching and max-values (paper §3.2, §3.3) --------------------------------------------

    def _option_env_values(self, kernel: SparseKernel, policies: Tensor) -> Tensor:
        """``(B, S, O)``: env-reward values of running each ``pi^o`` to the goal (= termination)."""
        R = self._env_reward(kernel)
        return torch.stack(
            [self.evaluate_kernel(kernel, R, policies[o]) for o in range(self.O)], -1
        )

    def switching_q(self, policies: Tensor | None = None) -> Tensor:
        """``Q_mu (S, O)``: mean-MDP value of running ``pi^o`` from s (windy options end at the
        goal, so no continuation with mu_bar is needed; paper §3.2)."""
        if policies is None:
            return self._switching_q
        return snap_ties(self._option_env_values(self.mean_kernel, policies)[0], self.tie_atol)

    @cached_property
    def _switching_q(self) -> Tensor:
        return self.switching_q(self.option_policies())

    def mu_bar(self) -> Tensor:
        """Greedy mu_bar ``(S,)`` int64 (lowest index on ties) in :meth:`switching_q`."""
        return greedy(self.switching_q(), self.tie_atol)

    def v_mu_bar(self) -> Tensor:
        """``V^{mu_bar}(s) = max_o Q_mu(s, o)`` ``(S,)``."""
        return self.switching_q().max(-1).values

    def instance_option_q(self, p: Any, direction: Any, policies: Tensor | None = None) -> Tensor:
        """``Q^{m, mu_bar}(s, o) (B, S, O)``: value of running ``pi^o`` from s in instance m."""
        pol = self.option_policies() if policies is None else policies
        return self._option_env_values(self.kernel(p, direction), pol)

    def max_value(self, instances: Any = None, chunk: int = 64) -> Tensor:
        """``Q_hat (S, O) = max_m Q^{m, mu_bar}(s, o)`` over an instance set (Definition 1); values
        within ``tie_atol`` of ``V^{mu_bar}(s)`` are snapped to it."""
        if instances is None:
            return self._max_value
        return self._max_value_of(*self.instance_set(instances), chunk=chunk)

    def _max_value_of(self, p: Tensor, d: Tensor, chunk: int = 64) -> Tensor:
        q = (
            torch.cat(
                [
                    self.instance_option_q(p[i : i + chunk], d[i : i + chunk]).max(0).values[None]
                    for i in range(0, p.numel(), chunk)
                ]
            )
            .max(0)
            .values
        )  # (S, O)
        v = self.v_mu_bar().unsqueeze(-1)
        return torch.where((q - v).abs() <= self.tie_atol, v.expand_as(q), q)

    @cached_property
    def _max_value(self) -> Tensor:
        return self._max_value_of(*self.instance_set(None))

    def interruption_condition(self, q_hat: Tensor, q_mu: Tensor) -> Tensor:
        """``(S, O)`` bool: Algorithm 1 line 6, ``Q_hat(s, o) < max_q Q_mu(s, q)`` (goal rows
        False), from any tables (exact or learnt)."""
        v = q_mu.max(-1, keepdim=True).values
        return (q_hat < v - self.tie_atol) & ~self.is_goal.view(-1, 1)

    # ---- returns ---------------------------------------------------------------------------------

    def episode_return(self, policy: Tensor, p: Any, direction: Any) -> Tensor:
        """Exact ``horizon``-step undiscounted return ``(B, S)`` of a deterministic policy ``(S,)``
        in instances ``(p, direction)``, from every cell (backward induction over steps-to-go)."""
        k = self.kernel(p, direction).policy(policy)
        V = torch.zeros(k.B, self.S, dtype=torch.float64, device=self.device)
        r = torch.where(self.is_goal, 0.0, -1.0).to(torch.float64)
        for _ in range(self.horizon):
            V = (r + k.expect(V)[..., 0]).masked_fill(self.is_goal, 0.0)
        return V

    def expected_return(
        self, policy: Tensor, instances: Any = None, starts: str | None = "uniform", chunk: int = 64
    ) -> Tensor:
        """``E_m[return]``, instance drawn per episode (quadrature over ``instances``); ``starts``:
        ``"uniform"`` or ``None`` (``(S,)``). Exact with ``quad_nodes = ceil(horizon / 2)``.
        """
        p, d, w = self.quadrature(instances)
        total = torch.zeros(self.S, dtype=torch.float64, device=self.device)
        for i in range(0, p.numel(), chunk):
            ret = self.episode_return(policy, p[i : i + chunk], d[i : i + chunk])
            total = total + (w[i : i + chunk, None] * ret).sum(0)
        if starts is None:
            return total
        if starts != "uniform":
            raise ValueError(f"starts must be 'uniform' or None, got {starts!r}")
        return total[self.start_cells].mean()

    def controller_returns(
        self,
        policies: Tensor,
        q_mu: Tensor,
        q_hat: Tensor | None = None,
        instances: Any = None,
        starts: str | None = "uniform",
        chunk: int = 32,
    ) -> dict[str, Tensor]:
        """Exact expected return and interruptions per episode of the options controller (greedy
        mu_bar), with offline interruption (Algorithm 1, lines 4-11) when ``q_hat`` is given.

        Args:
            policies: ``(O, S)`` greedy option policies. q_mu: ``(S, O)`` switching values.
            q_hat: ``(S, O)`` max-values; ``None``: no interruption.
            starts: ``"uniform"`` (scalars) or ``None`` (``(S,)``).

        Returns:
            ``{"expected_return": ..., "interruptions_per_episode": ...}``.
        """
        O, S = self.O, self.S  # noqa: E741
        pol = policies.to(self.device, torch.int64)
        q_mu = q_mu.to(self.device, torch.float64)
        # the controllers' rule (interruption_decide_of) at every (cell s, carried state z),
        # z = 0 none (line 4), z = o + 1 option o running; pi^o as a greedy one-hot table
        Z, dev = O + 1, self.device
        q_opt = torch.nn.functional.one_hot(pol, self.A).to(torch.float64)  # (O, S, A)
        q_opt = q_opt.permute(0, 2, 1).repeat_interleave(Z, 2)  # (O, A, S Z)
        of = lambda x: x.T.repeat_interleave(Z, 1)  # noqa: E731  (S, O) -> (O, S Z)
        running = torch.arange(Z, device=dev).repeat(S) - 1
        q_hat_of = None if q_hat is None else of(q_hat.to(dev, torch.float64))
        out = interruption_decide_of(q_opt, of(q_mu), q_hat_of, running)
        option = out["option"].view(S, Z)
        best = option[:, 0]  # (S,) line 4
        fire = out[keys.INTERRUPTED].view(S, Z)[:, 1:] & ~self.is_goal.view(-1, 1)  # (S, O)
        keep = torch.arange(O, device=dev).expand(S, O)
        nxt = torch.where(fire, option[:, 1:], keep)  # (S, O): o_run after lines 6-8
        act = pol.gather(0, nxt.T.contiguous()).T  # (S, O): pi^{nxt}(s)
        goal = self.is_goal.view(S, 1).expand(S, O).reshape(1, S * O)
        fr = fire.to(torch.float64).reshape(1, S * O)  # firing indicator per step (goal rows 0)
        p, d, w = self.quadrature(instances)
        ret = torch.zeros(S, dtype=torch.float64, device=self.device)
        fires = torch.zeros(S, dtype=torch.float64, device=self.device)
        start_idx = (torch.arange(S, device=self.device) * O + best).view(1, S)  # line 4's o_run
        for i in range(0, p.numel(), chunk):
            k = self.kernel(p[i : i + chunk], d[i : i + chunk])
            B, K = k.B, k.K
            idx = act.view(1, S, O, 1).expand(B, S, O, K)
            succ, prob = k.succ.gather(2, idx), k.prob.gather(2, idx)  # (B, S, O, K)
            # chain successors (s', o') as per-outcome planes (B, S O): expect_planes
            planes = outcome_planes(succ * O + nxt.view(1, S, O, 1), prob)
            V = torch.zeros(B, S * O, dtype=torch.float64, device=self.device)
            F = torch.zeros_like(V) if q_hat is not None else None
            for _ in range(self.horizon):  # V_k(s, o) = -1 + E[V_{k-1}(s', o')], 0 at the goal
                V = expect_planes(V, *planes).sub_(1.0)
                V.masked_fill_(goal, 0.0)
                if F is not None:  # the same recursion with the firing indicator as reward
                    F = expect_planes(F, *planes).add_(fr)
                    F.masked_fill_(goal, 0.0)
            wi = w[i : i + chunk].view(-1, 1)
            ret = ret + (wi * V.gather(1, start_idx.expand(B, S))).sum(0)
            if F is not None:
                fires = fires + (wi * F.gather(1, start_idx.expand(B, S))).sum(0)
        if starts is None:
            return {"expected_return": ret, "interruptions_per_episode": fires}
        if starts != "uniform":
            raise ValueError(f"starts must be 'uniform' or None, got {starts!r}")
        cells = self.start_cells
        return {
            "expected_return": ret[cells].mean(),
            "interruptions_per_episode": fires[cells].mean(),
        }


def outcome_planes(succ: Tensor, prob: Tensor) -> tuple[list[Tensor], list[Tensor]]:
    """Successor tables ``(B, ..., K)`` as ``K`` contiguous planes ``(B, n)`` of indices and of
    probabilities, for :func:`expect_planes`."""
    B, K = succ.shape[0], succ.shape[-1]
    return (
        [succ[..., j].reshape(B, -1).contiguous() for j in range(K)],
        [prob[..., j].reshape(B, -1).contiguous() for j in range(K)],
    )


def expect_planes(V: Tensor, succ: Sequence[Tensor], prob: Sequence[Tensor]) -> Tensor:
    """``sum_j prob_j * V[succ_j]`` ``(B, n)``: one gather per outcome, bit-equal to ``sum(-1)`` and
    faster on the CPU (docs/benchmarks.md).
    """
    out = V.gather(1, succ[0]).mul_(prob[0])
    for s, p in zip(succ[1:], prob[1:]):
        out.add_(V.gather(1, s).mul_(p))
    return out
