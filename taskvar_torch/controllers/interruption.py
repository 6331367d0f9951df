"""Offline interruption (paper §3.3, Definition 1, Algorithm 1) as a batched controller."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import torch

from taskvar_torch import keys
from taskvar_torch.controllers.base import (
    Controller,
    argmax0,
    first_argmax,
    max0,
    option_first,
    sample_categorical,
    select0,
)

Tensor = torch.Tensor


def interruption_decide_of(
    q_opt: Tensor,  # (O, A, B) Q_o(s_t, a), option-first: option policies pi^o (greedy)
    q_mu: Tensor,  # (O, B) Q_mu(s_t, o)
    q_hat: Tensor | None,  # (O, B) Q_hat(s_t, o); None: no interruption (plain options)
    running: Tensor,  # (B,) int64 o_run, -1 = empty
    terminated: Tensor | None = None,  # (B,) bool beta_{o_run}(s_t) = 1
    mu: Tensor | None = None,  # (O, B) softmax mu_bar(s_t, .); None: greedy mu_bar
    u: Tensor | None = None,  # (B,) uniforms for drawing o ~ mu_bar (softmax only)
) -> dict[str, Tensor]:
    """One step of Algorithm 1 for a batch (option-first inputs).

    - lines 3-4: if o_run is empty (episode start) or has terminated, ``o_run = argmax_o Q_mu(s_t, o)``
      (an argmax even when mu_bar is a softmax, as line 4 says);
    - lines 6-8: else if ``Q_hat(s_t, o_run) < sum_q mu_bar(s_t, q) Q_mu(s_t, q)``, draw
      ``o_run ~ mu_bar(s_t, .)`` (greedy mu_bar: the argmax). ``interrupted`` is this condition, even
      when the draw returns the same option;
    - line 11: ``a_t = argmax_a Q_{o_run}(s_t, a)``.

    Returns ``action``, ``option`` (the new o_run) and ``interrupted``, each ``(B,)``.
    """
    best = argmax0(q_mu)  # (B,) line 4
    empty = running < 0  # (B,)
    if terminated is not None:
        empty = empty | terminated
    if q_hat is None:
        option = torch.where(empty, best, running)
        interrupted = torch.zeros_like(empty)
    else:
        v = max0(q_mu) if mu is None else (mu * q_mu).sum(0)  # (B,) V^{mu_bar}(s_t)
        below = select0(q_hat, running.clamp(min=0)) < v  # (B,) line 6
        if mu is None:
            option = torch.where(empty | below, best, running)
            interrupted = below & ~empty
        else:
            interrupted = below & ~empty
            drawn = sample_categorical(mu, u)  # line 7
            option = torch.where(empty, best, torch.where(interrupted, drawn, running))
    action = argmax0(select0(q_opt, option))  # (B,) line 11
    return {"action": action, "option": option, keys.INTERRUPTED: interrupted}


def interruption_decide(
    q_opt: Tensor,  # (B, O, A)
    q_mu: Tensor,  # (B, O)
    q_hat: Tensor | None,  # (B, O)
    running: Tensor,  # (B,)
    terminated: Tensor | None = None,  # (B,)
    mu: Tensor | None = None,  # (B, O)
    u: Tensor | None = None,  # (B,)
) -> dict[str, Tensor]:
    """:func:`interruption_decide_of` for head outputs in the bundle layout (batch first)."""
    return interruption_decide_of(
        option_first(q_opt),
        option_first(q_mu),
        None if q_hat is None else option_first(q_hat),
        running,
        terminated,
        None if mu is None else option_first(mu),
        u,
    )


class InterruptionController(Controller):
    """Options with offline interruption (Algorithm 1): reads Q_o, Q_mu and Q_hat heads only.

    Writes ``action``, ``option`` (the option that ran), ``interrupted`` (line 6 fired) and
    ``("next", "running_option")``. A softmax mu_bar (``heads.softmax_temperature``) draws from the
    controller's own seeded generator.

    Examples:
        >>> oracle = WindyOracle("whole_column_windy", train_instances="south")
        >>> ctrl = InterruptionController(oracle.heads())
        >>> env = TransformedEnv(WindyGridEnv(4, "whole_column_windy", "north"), ctrl.primer())
        >>> td = env.rollout(20, ctrl, break_when_any_done=False)
        >>> td["interrupted"].shape
        torch.Size([4, 20])
    """

    name = "interruption"
    required_heads = ("options", "switching", "max_value")
    trace_keys = (keys.OPTION, keys.INTERRUPTED)
    interrupt = True

    def _softmax(self) -> bool:
        return self.interrupt and self.heads.softmax_temperature is not None

    def decide_of(
        self, values: Mapping[str, Tensor], running: Tensor, terminated: Tensor | None
    ) -> dict[str, Tensor]:
        q_mu = values[keys.OPTION_VALUE]  # (O, B)
        mu = u = None
        if self._softmax():
            mu = torch.softmax(q_mu / self.heads.softmax_temperature, dim=0)  # (O, B)
            g = self.generator(q_mu.device)
            u = torch.rand(q_mu.shape[1], generator=g, device=q_mu.device, dtype=q_mu.dtype)
        q_hat = values[keys.MAX_VALUE] if self.interrupt else None
        return interruption_decide_of(
            values[keys.OPTION_ACTION_VALUE], q_mu, q_hat, running, terminated, mu, u
        )

    def decide_scalar(
        self, values: Mapping[str, list], running: int, terminated: bool
    ) -> dict[str, Any]:
        q_mu = values[keys.OPTION_VALUE]  # [O]
        best = first_argmax(q_mu)
        interrupted = False
        if running < 0 or terminated:
            option = best  # line 4
        elif not self.interrupt:
            option = running
        else:
            if self._softmax():
                T = self.heads.softmax_temperature
                m = max(q_mu)
                w = [math.exp((q - m) / T) for q in q_mu]
                z = sum(w)
                mu = [x / z for x in w]
                v = sum(p * q for p, q in zip(mu, q_mu))
            else:
                v = q_mu[best]
            interrupted = values[keys.MAX_VALUE][running] < v  # line 6
            option = running
            if interrupted:
                if self._softmax():
                    u = float(torch.rand(1, generator=self.generator(torch.device("cpu"))))
                    option, acc = len(mu) - 1, 0.0
                    for k, pk in enumerate(mu):
                        acc += pk
                        if acc > u:
                            option = k
                            break
                else:
                    option = best
        action = first_argmax(values[keys.OPTION_ACTION_VALUE][option])  # line 11
        return {"action": action, "option": option, keys.INTERRUPTED: interrupted}
