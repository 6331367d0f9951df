"""Controllers as Markov chains on (cell, carried state), evaluated exactly (paper §3.3-3.4,
Algorithms 1-2; docs/oracle.md).

:class:`ControllerChains` is mixed into a family's exact oracle
(:class:`~taskvar_torch.families.windy.oracle.WindyOracle`,
:class:`~taskvar_torch.families.taxi.oracle.TaxiOracle`), which provides the instance models
(``transition(p, direction) -> P, R`` and ``_instances_arg``): it tabulates any
:class:`~taskvar_torch.heads.bundle.Heads` bundle over the cells, builds the controller's decision
kernel by an implementation of Algorithms 1 and 2 independent of ``controllers/``, and gives exact
returns and firing counts by backward induction over steps-to-go (see "Controllers" in the
:mod:`taskvar_torch.families.windy` docstring). :func:`discounted_chain_values`
gives a chain's infinite-horizon discounted values (one linear solve).
"""

from __future__ import annotations

from typing import Any

import torch

from taskvar_torch import keys
from taskvar_torch.heads.bundle import HEAD_OUT_KEYS, Heads
from taskvar_torch.subtasks.base import Hierarchy, Subtasks

CONTROLLER_NAMES = ("averaging", "options", "interruption", "hierarchy")

Tensor = torch.Tensor


class ControllerChains:
    """Exact evaluation of controllers as chains; a mixin of :class:`WindyOracle`.

    Uses the host's ``S``, ``device``, ``horizon``, ``is_goal``, ``model``, ``subtasks``,
    :meth:`heads`, :meth:`observation_td`, :meth:`quadrature` and its private instance and start
    helpers.
    """

    def _step_trace(
        self, instances: int, cells: Any, actions: Any, alive: Any
    ) -> tuple[Tensor, Tensor, Tensor]:
        """``step_regret``'s inputs as ``(B, T)`` tensors ``(cells, actions, alive)`` on the
        oracle's device (``alive`` None: all live), checked against ``instances`` episodes and the
        horizon, each mismatch one line."""
        s = torch.as_tensor(cells, dtype=torch.int64, device=self.device)
        a = torch.as_tensor(actions, dtype=torch.int64, device=self.device)
        live = (
            torch.ones_like(s, dtype=torch.bool)
            if alive is None
            else torch.as_tensor(alive, dtype=torch.bool, device=self.device)
        )
        if s.dim() != 2 or instances != s.shape[0] or a.shape != s.shape or live.shape != s.shape:
            raise ValueError(
                f"step_regret needs one instance per episode and (B, T) cells, actions, alive; "
                f"got {instances} instances, {tuple(s.shape)}, {tuple(a.shape)}, "
                f"{tuple(live.shape)}"
            )
        if s.shape[1] > self.horizon:
            raise ValueError(
                f"episodes of {s.shape[1]} steps exceed the oracle's horizon {self.horizon}"
            )
        return s, a, live

    @torch.no_grad()
    def tabulate(self, heads: Heads, obs_encoding: str = "onehot") -> dict[str, Tensor]:
        """Every head's output at every cell, ``{out_key: (S, ...)}`` (heads may read cell or observation)."""
        param = next(iter(heads.parameters()), None)  # heads may live on another device
        device = self.device if param is None else param.device
        td = heads(self.observation_td(obs_encoding).to(device))
        return {
            HEAD_OUT_KEYS[h]: td.get(HEAD_OUT_KEYS[h]).to(self.device) for h in heads.paper_heads()
        }

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
        if name == "averaging":
            return self._averaging_chain(t)
        if name in ("options", "interruption"):
            return self._option_chain(t, heads, subtasks, interrupt=name == "interruption")
        return self._hierarchy_chain(t, heads, hierarchy, tau, subtasks)

    def _averaging_chain(self, t: dict[str, Tensor]) -> dict[str, Tensor]:
        """The averaging policy (paper §3.1) as a one-state chain: greedy in ``action_value``."""
        S = self.S
        act = t[keys.ACTION_VALUE].argmax(-1).unsqueeze(-1)  # (S, 1)
        one = torch.ones(S, 1, 1, dtype=torch.float64, device=self.device)
        return {
            "decision": one,
            "action": act,
            "next_state": torch.zeros(1, dtype=torch.int64, device=self.device),
            "fires": torch.zeros(S, 1, dtype=torch.bool, device=self.device),
        }

    def _empty_option_chain(self, t: dict[str, Tensor]) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``(action (S, O), decision (S, O + 1, O), fires (S, O + 1), next_state (O,))``: greedy
        option actions, an all-zero decision kernel and firing table, ``z' = n + 1``."""
        S = self.S
        q_opt = t[keys.OPTION_ACTION_VALUE]  # (S, O, A)
        O = q_opt.shape[1]  # noqa: E741
        act = q_opt.argmax(-1)  # (S, O)
        decision = torch.zeros(S, O + 1, O, dtype=torch.float64, device=self.device)
        fires = torch.zeros(S, O + 1, dtype=torch.bool, device=self.device)
        next_state = torch.arange(1, O + 1, device=self.device)
        return act, decision, fires, next_state

    def _initiation_table(
        self, subtasks: Subtasks | None, method: str = "initiation"
    ) -> Tensor | None:
        """``(S, O)`` bool ``subtasks.<method>`` at every cell (``initiation``: I_o; ``startable``:
        where o can take control in the hierarchy), or None where the subtasks define no
        initiation sets (then every option may start everywhere)."""
        if subtasks is None or type(subtasks).initiation is Subtasks.initiation:
            return None
        cells = torch.arange(self.S, device=self.device)
        return getattr(subtasks, method)(self._cells_td(cells)).to(torch.bool)

    def _option_chain(
        self, t: dict[str, Tensor], heads: Heads, subtasks: Subtasks | None, interrupt: bool
    ) -> dict[str, Tensor]:
        """Options: the option greedy in ``option_value`` at the start and at termination
        (Algorithm 1 line 4); with ``interrupt``, also Algorithm 1's interruption (lines 6-8).

        With ``subtasks`` that define initiation sets, mu_bar ranges over the options initiable at
        s (line 4's argmax, line 6's ``V^{mu_bar}(s)``, line 7's distribution renormalised over
        them). Where none is: line 6 does not fire, and where line 4 must pick, the averaging
        policy acts and the carried state stays empty: the chain then has ``N = O + 1`` columns,
        the last one ``argmax_a Q_avg(s, a)`` with ``z' = 0``.
        """
        S = self.S
        act, decision, fires, next_state = self._empty_option_chain(t)
        O = act.shape[1]  # noqa: E741
        q_mu = t[keys.OPTION_VALUE]  # (S, O)
        mu = heads.mu_bar(q_mu).to(torch.float64)  # (S, O)
        v = (heads.mu_bar(q_mu) * q_mu).sum(-1)  # (S,)
        best = q_mu.argmax(-1)  # (S,) line 4
        init = self._initiation_table(subtasks)  # (S, O) or None
        none = torch.zeros(S, dtype=torch.bool, device=self.device)
        if init is not None:  # mu_bar over the initiable options only
            none = ~init.any(-1)  # (S,)
            q_in = q_mu.masked_fill(~init, float("-inf"))  # (S, O)
            best = q_in.argmax(-1)
            mu_in = heads.mu_bar(q_in).masked_fill(none.unsqueeze(-1), 0.0)  # (S, O) renormalised
            mu = mu_in.to(torch.float64)
            v = (mu_in * q_mu).sum(-1)  # (S,) (unused where none is initiable)
            # the fallback column: the averaging policy acts, o_run stays empty
            act = torch.cat([act, t[keys.ACTION_VALUE].argmax(-1, keepdim=True)], 1)  # (S, O + 1)
            decision = torch.cat([decision, torch.zeros_like(decision[..., :1])], -1)
            next_state = torch.cat([next_state, torch.zeros_like(next_state[:1])])
        beta = torch.zeros(S, O, dtype=torch.bool, device=self.device)
        if subtasks is not None:
            beta = subtasks.termination(self._cells_td(torch.arange(S, device=self.device)))
        for s in range(S):
            for z in range(O + 1):
                if z == 0 or bool(beta[s, z - 1]):
                    decision[s, z, O if bool(none[s]) else best[s]] = 1.0  # line 4 / fallback
                elif interrupt and not bool(none[s]) and bool(t[keys.MAX_VALUE][s, z - 1] < v[s]):
                    decision[s, z, :O] = mu[s]  # lines 6-8
                    fires[s, z] = True
                else:
                    decision[s, z, z - 1] = 1.0
        return {"decision": decision, "action": act, "next_state": next_state, "fires": fires}

    def _hierarchy_chain(
        self,
        t: dict[str, Tensor],
        heads: Heads,
        hierarchy: Hierarchy | None,
        tau: float | None,
        subtasks: Subtasks | None = None,
    ) -> dict[str, Tensor]:
        """Algorithm 2 (hierarchical search), literally, with greedy option policies.

        With ``subtasks`` (a hierarchy controller that honours them), as that controller: a
        running subtask whose termination holds hands control to its parent first, and the descent
        (line 10) only considers components that can take control at s (``Subtasks.startable``:
        in I_q and not terminated); a composed node none of whose components can keeps control.
        """
        S = self.S
        act, decision, fires, next_state = self._empty_option_chain(t)
        O = act.shape[1]  # noqa: E741
        if hierarchy is None or tau is None:
            raise ValueError("the hierarchy controller needs a hierarchy and tau")
        names = list(heads.option_names)
        rob = t[keys.ROBUSTNESS]  # (S, O, A)
        can = self._initiation_table(subtasks, "startable")  # (S, O) or None
        beta = torch.zeros(S, O, dtype=torch.bool, device=self.device)
        if subtasks is not None:
            beta = subtasks.termination(self._cells_td(torch.arange(S, device=self.device)))

        def parent_of(o: int) -> int | None:
            p = hierarchy.parent(names[o])
            return None if p is None else names.index(p)

        def search(s: int, o_run: int, p: int | None) -> int:
            """HierarchicalSearch(K, o_run, p, tau, s): the option whose action is returned."""
            if p is not None and float(rob[s, p, act[s, p]]) > tau:  # lines 1-3
                return p
            a = int(act[s, o_run])  # line 5
            kids = [names.index(k) for k in hierarchy.components(names[o_run])]
            if can is not None:
                kids = [k for k in kids if bool(can[s, k])]
            if not kids or float(rob[s, o_run, a]) > tau:  # line 6
                return o_run
            q_star = max(kids, key=lambda q: (float(rob[s, q, a]), -q))  # line 10 (first on ties)
            return search(s, q_star, o_run)  # line 11

        root = names.index(hierarchy.root)
        for s in range(S):
            for z in range(O + 1):
                o_run = root if z == 0 else z - 1
                ended = z > 0 and bool(beta[s, z - 1])
                if ended and parent_of(o_run) is not None:  # control returns up the tree
                    o_run = parent_of(o_run)
                n = search(s, o_run, parent_of(o_run))
                decision[s, z, n] = 1.0
                fires[s, z] = z > 0 and n != z - 1 and not ended
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
        P, R = self.transition(pt, d)  # the family oracle's exact models (float64)
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
        P, R = self.transition(pt, d)  # the family oracle's exact models (float64)
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


def discounted_chain_values(
    P: torch.Tensor, R: torch.Tensor, chain: dict[str, torch.Tensor], gamma: float
) -> torch.Tensor:
    """Discounted values ``V (B, S, Z)`` of a controller chain (``WindyOracle.controller_chain``).

    ``V(s, z) = sum_n D[s,z,n] (R(s, a_n) + gamma sum_s' P(s, a_n, s') V(s', z'_n))``, solved as a
    linear system; ``z = 0`` is an empty carried state, ``z = o + 1`` option ``o`` running.
    """
    D, act, nz = chain["decision"], chain["action"], chain["next_state"]  # (S,Z,N) (S,N) (N,)
    B, S = P.shape[0], P.shape[1]
    N, Z = act.shape[1], D.shape[1]
    Pn = P.gather(2, act.view(1, S, N, 1).expand(B, S, N, S))  # (B, S, N, S')
    rn = R.gather(2, act.unsqueeze(0).expand(B, S, N))  # (B, S, N)
    r = torch.einsum("szn,bsn->bsz", D, rn).reshape(B, S * Z)
    to_z = torch.nn.functional.one_hot(nz, Z).to(P.dtype)  # (N, Z')
    M = torch.einsum("szn,bsnt,nw->bsztw", D, Pn, to_z).reshape(B, S * Z, S * Z)
    eye = torch.eye(S * Z, dtype=P.dtype)
    return torch.linalg.solve(eye - gamma * M, r.unsqueeze(-1)).reshape(B, S, Z)
