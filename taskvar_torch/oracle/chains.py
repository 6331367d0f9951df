"""Controllers as Markov chains on (cell, carried state), evaluated exactly (paper §3.3-3.4,
Algorithms 1-2; docs/oracle.md).

:class:`ControllerChains`, mixed into a family's exact oracle, tabulates any :class:`Heads` bundle
over the cells, builds the decision kernel from the controller's own rule (so the exact values are
those of the controller that plays), and gives exact returns and firing counts by backward
induction; :func:`discounted_chain_values` a chain's discounted values.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from taskvar_torch import keys
from taskvar_torch.controllers import Controller, InterruptionController, make_controller
from taskvar_torch.controllers.base import option_first
from taskvar_torch.controllers.interruption import masked_mu_bar
from taskvar_torch.heads.bundle import HEAD_OUT_KEYS, Heads
from taskvar_torch.subtasks.base import Hierarchy, Subtasks

CONTROLLER_NAMES = ("averaging", "options", "interruption", "hierarchy")

Tensor = torch.Tensor


class ControllerChains:
    """Exact evaluation of controllers as chains; a mixin of the family oracles, which give ``S``,
    ``device``, ``horizon``, ``is_goal``, ``model``, ``subtasks``, :meth:`heads`,
    :meth:`observation_td`, :meth:`quadrature` and their instance and start helpers.
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
        """The controller (a name in ``CONTROLLER_NAMES`` or a
        :class:`~taskvar_torch.controllers.base.Controller`) as a Markov chain on (cell, carried
        state ``z``: 0 none, ``k + 1`` option k ran last).

        Returns ``decision (S, Z, N)`` (distribution of the acting entry), ``action (S, N)``,
        ``next_state (N,)`` and ``fires (S, Z)`` (Algorithm 1 line 6 fires / Algorithm 2 moves
        control).
        """
        name = controller if isinstance(controller, str) else controller.name
        if name not in CONTROLLER_NAMES:
            raise ValueError(f"controller must be one of {list(CONTROLLER_NAMES)}, got {name!r}")
        if isinstance(controller, str):
            if heads is None:
                heads, subtasks = self.heads(), self.subtasks if subtasks is None else subtasks
            if name == "hierarchy" and (hierarchy is None or tau is None):
                raise ValueError("the hierarchy controller needs a hierarchy and tau")
            controller = make_controller(
                name, heads, subtasks, hierarchy, tau, terminate=subtasks is not None
            )
        t = self.tabulate(controller.heads, obs_encoding)
        if name == "averaging":
            return self._averaging_chain(t)
        return self._decision_chain(controller, t)

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

    def _decision_chain(self, controller: Controller, t: dict[str, Tensor]) -> dict[str, Tensor]:
        """An option-level controller's decision at every ``(s, z)`` by its own rule
        (:meth:`Controller.decide`) on the tabulated heads; entry ``n = O`` is the averaging
        fallback, and a softmax mu_bar's draw is its distribution.
        """
        S, O, dev = self.S, controller.num_options, self.device  # noqa: E741
        Z = O + 1
        cells = torch.arange(S, device=dev).repeat_interleave(Z)  # (S Z,)
        running = torch.arange(Z, device=dev).repeat(S) - 1  # (S Z,): z = 0 is none
        td = self._cells_td(cells)
        values = {
            HEAD_OUT_KEYS[h]: t[HEAD_OUT_KEYS[h]].repeat_interleave(Z, 0)
            for h in controller.required_heads
        }
        values.update(controller.extra_inputs(td))
        g = controller.generator(dev)
        stream = g.get_state()
        out = controller.decide(values, running, controller._terminated(td, running))
        g.set_state(stream)
        fallback = keys.INITIABLE in values  # the averaging action is entry n = O
        N = O + 1 if fallback else O
        option = out["option"]
        n = torch.where(option < 0, O, option)
        decision = nn.functional.one_hot(n, N).to(torch.float64)  # (S Z, N)
        if isinstance(controller, InterruptionController) and controller._softmax():
            initiable = values.get(keys.INITIABLE)
            mu = masked_mu_bar(
                option_first(values[keys.OPTION_VALUE]),
                controller.heads.softmax_temperature,
                None if initiable is None else option_first(initiable),
            ).T.to(torch.float64)  # (S Z, O) mu_bar over the initiable options
            drawn = out[keys.INTERRUPTED].unsqueeze(-1)  # line 7 draws where line 6 fired
            decision[:, :O] = torch.where(drawn, mu, decision[:, :O])
        act = t[keys.OPTION_ACTION_VALUE].argmax(-1)  # (S, O): pi^o(s)
        if controller.root_index is not None:  # pi^root = pi^avg (paper §3.4.2)
            act[:, controller.root_index] = t[keys.ACTION_VALUE].argmax(-1)
        next_state = torch.arange(1, O + 1, device=dev)
        if fallback:
            act = torch.cat([act, t[keys.ACTION_VALUE].argmax(-1, keepdim=True)], 1)  # (S, N)
            next_state = torch.cat([next_state, torch.zeros_like(next_state[:1])])
        if not torch.equal(
            act.repeat_interleave(Z, 0).gather(1, n.unsqueeze(-1))[:, 0], out["action"]
        ):
            raise RuntimeError(f"{controller.name}: an entry's action is not its greedy one")
        return {
            "decision": decision.view(S, Z, N),
            "action": act,
            "next_state": next_state,
            "fires": out[keys.INTERRUPTED].view(S, Z),
        }

    def controller_return(
        self, controller: Any, p: Any, direction: Any, start: Any = None, **kwargs: Any
    ) -> Tensor:
        """Exact expected ``horizon``-step return of a controller in instance(s), by backward
        induction on :meth:`controller_chain` (``start`` as in :meth:`episode_return`).
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
    """Discounted values ``V (B, S, Z)`` of a controller chain, ``V(s, z) = sum_n D[s,z,n] (R(s,
    a_n) + gamma sum_s' P(s, a_n, s') V(s', z'_n))``, one linear solve.
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
