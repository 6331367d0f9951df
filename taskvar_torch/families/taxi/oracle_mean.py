"""The mean-MDP values of the Taxi family's exact oracle (paper §3.1-3.3, Definition 1): the mean
MDP, averaging policy, options, switching values, mu_bar, Q_hat and the tabulated heads; the middle
layer of :class:`~taskvar_torch.families.taxi.oracle.TaxiOracle`.
"""

from __future__ import annotations

import math
from functools import cached_property
from typing import Any

import torch
from tensordict import TensorDict
from torch import nn

from taskvar_torch import keys
from taskvar_torch.families.taxi import dynamics as taxi
from taskvar_torch.families.taxi.env import observation_table
from taskvar_torch.families.taxi.oracle_models import _K, TaxiModels
from taskvar_torch.families.taxi.subtasks import state_parts
from taskvar_torch.oracle.mdp import greedy, snap_ties, solve_mdp
from taskvar_torch.oracle.tables import DerivedTables

Tensor = torch.Tensor


class TaxiMeanMDP(DerivedTables, TaxiModels):
    """The mean MDP, options, switching values and heads of
    :class:`~taskvar_torch.families.taxi.oracle.TaxiOracle` (its arguments: that class)."""

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
        """``Q^{m, mu}(x, o) (B, *, O)``: run pi^o from x, then ``mu (S, O)`` where o terminates
        (iterative, to ``tol``).
        """
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

    def instance_option_q(self, q: Any, f: Any) -> Tensor:
        """``Q^{m, mu_bar}((s, k), o)`` ``(B, 2, S, O)`` (``k`` = pending) in instances ``(q, f)``."""
        qt, ft, scalar = self._instances_arg(q, f)
        out = self._smdp_values(self.kernel_probs(qt, ft), True, self.mu_bar(), tol=1e-8)
        out = out.reshape(-1, 2, self.S, self.O)
        return out[0] if scalar else out

    def _max_value(self, q: Tensor, f: Tensor) -> Tensor:
        chunks = [
            self.instance_option_q(q[i : i + 16], f[i : i + 16]).amax((0, 1))
            for i in range(0, q.numel(), 16)
        ]
        q_hat = torch.stack(chunks).amax(0)  # (S, O)
        v = self.v_mu_bar().unsqueeze(-1)
        return torch.where((q_hat - v).abs() <= 1e-7, v.expand_as(q_hat), q_hat)

    def observation_td(self, obs_encoding: str = "onehot") -> TensorDict:
        """A ``(S,)`` tensordict of every Taxi state's ``cell`` and ``observation`` in
        ``obs_encoding``.
        """
        cells = torch.arange(self.S, device=self.device)
        obs = torch.as_tensor(observation_table(obs_encoding), device=self.device)
        return TensorDict(
            {keys.CELL: cells, keys.OBSERVATION: obs}, batch_size=[self.S], device=self.device
        )
