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

Layers: the instance models and the per-instance optimum are
:class:`~taskvar_torch.families.taxi.oracle_models.TaxiModels`, the mean MDP, options, switching
values and heads :class:`~taskvar_torch.families.taxi.oracle_mean.TaxiMeanMDP`; this module adds
the controllers as chains (Algorithm 1 with initiation sets) and their exact returns.

Examples:
    >>> oracle = TaxiOracle()
    >>> oracle.averaging_policy().shape, oracle.option_q().shape
    (torch.Size([500]), torch.Size([6, 500, 6]))
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

    # ---- controllers as chains (Algorithm 1 with initiation sets) -------------------------------

    def controller_chain(self, controller: Any, **kwargs: Any) -> dict[str, Tensor]:
        """The controller as a chain on (Taxi state, carried state) with initiation sets honoured.

        :meth:`ControllerChains.controller_chain` (``decision (S, Z, N)``, ``action (S, N)``,
        ``next_state (N,)``, ``fires (S, Z)``; ``Z = O + 1``) with the oracle's subtasks where the
        controller has none, and the oracle's ``obs_encoding`` unless given: one more acting
        entry ``n = O``, the averaging action holding no option (``z' = 0``), where no option is
        initiable. No hierarchy (Taxi's options are flat).
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
