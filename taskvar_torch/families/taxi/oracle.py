"""The Taxi family's exact oracle, :class:`TaxiOracle` (paper §3.1-3.3, Definition 1, Algorithm 1).

Taxi-v4 with a hidden instance ``(q, f)`` (rain, fickle passenger), with the windy oracle's
interface where it applies (docs/taxi.md#the-exact-oracle). Taxi's own decisions:

- **Augmented states** ``x = s + 500 k``: ``k = 1`` while the fickle redraw is pending (no step has
  yet started with the passenger aboard and moved the taxi), the belief MDP of an agent that knows
  the instance but not the passenger's coin (tested against Gymnasium's ``step``); ``informed=True``
  augments by the coin itself. Heads and controllers see the 500 states.
- **Delivered states absorb** with reward 0, as windy's goal cells.
- **Mean MDP over the 500 observed states** (§3.1): the prior averages the augmented kernel exactly;
  the projection weighs the pending status ``w(s)`` on the 16 states with the passenger aboard on a
  landmark, by the averaging policy's own occupancy iterated to a fixed point
  (``fickle_weights="visits"``) or ``w = 1`` (``"pickup"``).
- **Initiation sets**: mu_bar and ``V^{mu_bar}`` range over the options initiable at s; the
  averaging fallback acts only at delivered states.
- **Q_hat** (Definition 1): max over ``q_grid`` x the extreme f of the training support (values are
  affine in f) and the hidden fickle status.
- **Returns**: exact ``horizon``-step sums by backward induction; expectations are exact (affine in
  f, Gauss-Legendre in q).

Instance models and the per-instance optimum are
:class:`~taskvar_torch.families.taxi.oracle_models.TaxiModels`, the mean MDP and heads
:class:`~taskvar_torch.families.taxi.oracle_mean.TaxiMeanMDP`; this module adds the controllers as
chains and their exact returns.
"""

from __future__ import annotations

from functools import cached_property
from typing import Any

import torch

from taskvar_torch.controllers import make_controller
from taskvar_torch.families.taxi.dynamics import taxi_instances
from taskvar_torch.families.taxi.oracle_mean import TaxiMeanMDP
from taskvar_torch.oracle.chains import CONTROLLER_NAMES
from taskvar_torch.oracle.mdp import gauss_legendre

Tensor = torch.Tensor


class TaxiOracle(TaxiMeanMDP):
    """Exact solver of the Taxi family (module docstring).

    Args:
        gamma: discount of the values compared against the networks.
        horizon: episode length of the returns (Taxi-v4: 200).
        train_instances: the training distribution (name, dict or :class:`TaxiInstances`).
        end_penalty: navigation options' cost of delivering away from their landmark.
        q_grid: Q_hat's q values: an int (evenly spaced over ``[q_low, q_high]``) or the values.
        fickle_weights: ``"visits"`` or ``"pickup"`` (module docstring).
        mu_temperature: ``None`` for a greedy mu_bar, else a softmax mu_bar's temperature.
        quad_nodes: Gauss-Legendre nodes in q (default ``ceil(horizon / 2)``: exact for returns).
        tol: certified error of the iterative solves.
        device: torch device of the tables.
        obs_encoding: the observation learnt heads read, where a controller's heads are tabulated.
    """

    # ---- controllers as chains (Algorithm 1 with initiation sets) -------------------------------

    def controller_chain(self, controller: Any, **kwargs: Any) -> dict[str, Tensor]:
        """The controller as a chain on (Taxi state, carried state), initiation sets honoured
        (:meth:`ControllerChains.controller_chain`, with one more acting entry ``n = O`` for the
        averaging fallback).
        """
        name = controller if isinstance(controller, str) else controller.name
        if name not in CONTROLLER_NAMES or name == "hierarchy":
            raise ValueError(
                f"controller must be one of ['averaging', 'options', 'interruption'], got {name!r}"
            )
        heads, subtasks = kwargs.get("heads"), kwargs.get("subtasks")
        if not isinstance(controller, str):
            heads, subtasks = controller.heads, controller.subtasks
        if isinstance(controller, str) or subtasks is None:
            controller = make_controller(
                name,
                self.heads() if heads is None else heads,
                self.subtasks if subtasks is None else subtasks,
                seed=getattr(controller, "seed", 0),
            )
        encoding = kwargs.get("obs_encoding") or self.obs_encoding
        return super().controller_chain(controller, obs_encoding=encoding)

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
        """:meth:`_chain_values` for many instances: solved at f = 0 and f = 1 per distinct q and
        interpolated (values are affine in f).
        """
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
        """Exact expected ``horizon``-step return ``(B, S)`` of a controller (a name or a
        :class:`~taskvar_torch.controllers.base.Controller`) in instances ``(q, f)``, from each
        start (``start``: ``None`` all, ``"uniform"`` Taxi-v4's starts, or a state).
        """
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
        """The per-instance optimum's expected return over a distribution, by quadrature over q and
        f (the optimum is not affine in f); an approximation, as it is only piecewise polynomial.
        """
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
