"""What the learnt heads converge to: the fixed-instance objective and the first-visit replay MDP
(docs/oracle.md#which-reference-the-learnt-heads-should-reach); mixed into ``WindyOracle``.
"""

from __future__ import annotations

from typing import Any

import torch

from taskvar_torch.oracle.mdp import TIE_ATOL, greedy, solve_mdp

Tensor = torch.Tensor


class ReplayReference:
    """Fixed-instance values and policies, visit probabilities, replay MDPs and their fixed points;
    a mixin of :class:`WindyOracle`, whose tables and solvers it uses."""

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
        """Best Markov policy ``(S,)`` for the fixed-instance objective ``E_m[V^{m, pi}]`` (env
        reward or option ``option``'s), by single-cell policy search from the mean-MDP optimum (a
        local optimum)."""
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
        """``(B, S, A)``: probability that an episode of ``behaviour (S, A)`` takes a at s at least
        once, per instance (how often a first-visit replay holds (s, a))."""
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
        """``(P, R)`` a Q-learner sees in a first-visit replay: next states from the instance
        mixture weighted by :meth:`visit_probability` under ``behaviour``; env or option
        ``option``'s reward."""
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
        """The Q-learning fixed point ``(S,)`` on its own epsilon-greedy first-visit replay
        (iterated until the policy repeats or ``max_iter``)."""
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
