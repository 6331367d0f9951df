"""Generic exact MDP machinery of the oracle (paper §3.1; docs/oracle.md): :func:`solve_mdp`, policy
kernels, tie-snapping (:func:`snap_ties`, :func:`greedy`) and Gauss-Legendre quadrature; float64,
batched over leading dimensions.
"""

from __future__ import annotations

import numpy as np
import torch

TIE_ATOL = 1e-9
"""Values closer than this are treated as equal ("Ties" in the package docstring)."""

Tensor = torch.Tensor


def snap_ties(q: Tensor, atol: float = TIE_ATOL) -> Tensor:
    """Set entries within ``atol`` of their row maximum (last dim) to that maximum."""
    m = q.max(-1, keepdim=True).values  # (..., 1)
    return torch.where(q >= m - atol, m.expand_as(q), q)


def greedy(q: Tensor, atol: float = TIE_ATOL) -> Tensor:
    """``argmax`` over the last dim, lowest index among entries within ``atol`` of the maximum."""
    return snap_ties(q, atol).argmax(-1)


def gauss_legendre(n: int, low: float, high: float) -> tuple[Tensor, Tensor]:
    """Nodes and weights (summing to 1) of ``n``-point Gauss-Legendre for the uniform law on [low, high]."""
    if high <= low:
        return torch.tensor([float(low)], dtype=torch.float64), torch.ones(1, dtype=torch.float64)
    x, w = np.polynomial.legendre.leggauss(int(n))
    p = 0.5 * (high - low) * x + 0.5 * (high + low)
    return torch.as_tensor(p, dtype=torch.float64), torch.as_tensor(w / 2.0, dtype=torch.float64)


def policy_kernel(P: Tensor, policy: Tensor) -> Tensor:
    """``P_pi[b, s, s']`` for a deterministic ``(S,)`` / ``(B, S)`` or stochastic ``(S, A)`` policy."""
    B, S, A, _ = P.shape
    if policy.is_floating_point():  # (S, A) probabilities
        return torch.einsum("bsat,sa->bst", P, policy.to(P.dtype))
    pol = policy.to(torch.int64).expand(B, S)  # (B, S)
    return P.gather(2, pol.view(B, S, 1, 1).expand(B, S, 1, S)).squeeze(2)  # (B, S, S)


def policy_reward(R: Tensor, policy: Tensor) -> Tensor:
    """``r_pi[b, s]`` from ``R (B, S, A)``."""
    B, S, _ = R.shape
    if policy.is_floating_point():
        return (R * policy.to(R.dtype)).sum(-1)
    return R.gather(2, policy.to(torch.int64).expand(B, S).unsqueeze(-1)).squeeze(-1)


def solve_mdp(
    P: Tensor,  # (..., S, A, S')
    R: Tensor,  # (..., S, A)
    gamma: float,
    cont: Tensor | None = None,  # (..., S') in [0, 1]: 1 - termination of the next state
    tol: float = 1e-10,
    max_iter: int = 1_000_000,
) -> Tensor:
    """Optimal ``Q (..., S, A)`` of a discounted MDP, ``Q(s,a) = R(s,a) + gamma sum_s' P(s,a,s')
    cont(s') max_a' Q(s',a')``: value iteration to ``tol``, then a policy-iteration polish.
    """
    if not 0.0 <= gamma < 1.0:
        raise ValueError(f"gamma must be in [0, 1), got {gamma}")
    batch = P.shape[:-3]
    S, A = P.shape[-3], P.shape[-2]
    Pf = P.reshape(-1, S, A, S)  # (B, S, A, S)
    Rf = R.reshape(-1, S, A)  # (B, S, A)
    c = torch.ones(Pf.shape[0], S, dtype=P.dtype, device=P.device)
    if cont is not None:
        c = c * cont.reshape(-1, S)
    Pc = Pf * c.unsqueeze(1).unsqueeze(1)  # (B, S, A, S): discount-free continuation kernel
    V = torch.zeros(Pf.shape[0], S, dtype=P.dtype, device=P.device)
    bound = tol * (1.0 - gamma) / max(gamma, 1e-300)
    for _ in range(max_iter):
        Q = Rf + gamma * torch.einsum("bsat,bt->bsa", Pc, V)
        V_new = Q.max(-1).values
        delta = (V_new - V).abs().max()
        V = V_new
        if gamma == 0.0 or bool(delta < bound):
            break
    else:  # pragma: no cover - a contraction always converges
        raise RuntimeError("value iteration did not converge")
    pi = greedy(Q)  # (B, S)
    eye = torch.eye(S, dtype=P.dtype, device=P.device)
    for _ in range(1000):  # policy iteration polish: exact values of the greedy policy
        Ppi = policy_kernel(Pc, pi)  # (B, S, S)
        rpi = policy_reward(Rf, pi)  # (B, S)
        Vpi = torch.linalg.solve(eye - gamma * Ppi, rpi.unsqueeze(-1)).squeeze(-1)  # (B, S)
        Q = Rf + gamma * torch.einsum("bsat,bt->bsa", Pc, Vpi)
        pi_new = greedy(Q)
        # keep the current action unless another is better by more than the tie tolerance
        cur = Q.gather(-1, pi.unsqueeze(-1)).squeeze(-1)
        better = Q.max(-1).values > cur + TIE_ATOL
        if not bool(better.any()):
            break
        pi = torch.where(better, pi_new, pi)
    return snap_ties(Q).reshape(*batch, S, A)
