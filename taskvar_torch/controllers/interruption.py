"""Offline interruption (paper §3.3, Definition 1, Algorithm 1) as a batched controller."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDictBase

from taskvar_torch import keys
from taskvar_torch.controllers.base import (
    Controller,
    any0,
    argmax0,
    first_argmax,
    first_argmax_where,
    max0,
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
    initiable: Tensor | None = None,  # (O, B) bool s_t in I_o; None: every option everywhere
    q_avg: Tensor | None = None,  # (A, B) Q_avg(s_t, a): acts where no option is initiable
) -> dict[str, Tensor]:
    """One step of Algorithm 1 for a batch (option-first inputs).

    - lines 3-4: if o_run is empty or has terminated, ``o_run = argmax_o Q_mu(s_t, o)``;
    - lines 6-8: else if ``Q_hat(s_t, o_run) < sum_q mu_bar(s_t, q) Q_mu(s_t, q)``, draw ``o_run ~
      mu_bar(s_t, .)``; ``interrupted`` is this condition;
    - line 11: ``a_t = argmax_a Q_{o_run}(s_t, a)``.

    With ``initiable`` (paper §3.2) mu_bar ranges over the initiable options only (``mu`` as
    :func:`masked_mu_bar`); where none is and an option must be picked, the averaging head acts
    (``q_avg`` needed) with ``option = -1``. Returns ``action``, ``option`` and ``interrupted``,
    each ``(B,)``.
    """
    some = None
    q_pick = q_mu
    if initiable is not None:
        some = any0(initiable)  # (B,) some option can start at s_t
        q_pick = torch.where(initiable, q_mu, float("-inf"))  # mu_bar over I only
    best = argmax0(q_pick)  # (B,) line 4
    empty = running < 0  # (B,)
    if terminated is not None:
        empty = empty | terminated
    if q_hat is None:
        option = torch.where(empty, best, running)
        interrupted = torch.zeros_like(empty)
    else:
        # (B,) V^{mu_bar}(s_t) (-inf where none is initiable with a greedy mu_bar: never below)
        v = max0(q_pick) if mu is None else (mu * q_mu).sum(0)
        below = select0(q_hat, running.clamp(min=0)) < v  # (B,) line 6
        if mu is None:
            option = torch.where(empty | below, best, running)
            interrupted = below & ~empty
        else:
            interrupted = below & ~empty
            if some is not None:
                interrupted = interrupted & some
            drawn = sample_categorical(mu, u, initiable)  # line 7
            option = torch.where(empty, best, torch.where(interrupted, drawn, running))
    if some is None:
        action = argmax0(select0(q_opt, option))  # (B,) line 11
    else:
        if q_avg is None:
            raise ValueError("initiable needs q_avg: the averaging policy acts where none is")
        fallback = empty > some  # (B,) empty & ~some: line 4 with no initiable option
        q_act = torch.where(fallback, q_avg, select0(q_opt, option))  # (A, B): pi^{o_run} or Q_avg
        action = argmax0(q_act)  # (B,) line 11
        option = torch.where(fallback, -1, option)
    return {"action": action, "option": option, keys.INTERRUPTED: interrupted}


def masked_mu_bar(q_mu: Tensor, temperature: float, initiable: Tensor | None) -> Tensor:
    """Softmax mu_bar ``(O, B)`` over dim 0 of ``Q_mu / T``, renormalised over the ``initiable``
    options (zero elsewhere); where none is initiable, over every option (finite, never drawn)."""
    logits = q_mu / temperature
    if initiable is not None:
        allowed = initiable | ~any0(initiable)  # (O, B)
        logits = logits.masked_fill(~allowed, float("-inf"))
    return torch.softmax(logits, dim=0)


class InterruptionController(Controller):
    """Options with offline interruption (Algorithm 1): reads Q_o, Q_mu and Q_hat heads only.

    Writes ``action``, ``option`` (-1 when the averaging head acted), ``interrupted`` (line 6 fired)
    and ``("next", "running_option")``. A softmax mu_bar (``heads.softmax_temperature``) draws from
    the controller's own seeded generator. With ``subtasks`` that define initiation sets the bundle
    needs the averaging head (:func:`interruption_decide_of`).
    """

    name = "interruption"
    required_heads = ("options", "switching", "max_value")
    trace_keys = (keys.OPTION, keys.INTERRUPTED)
    interrupt = True
    reads_initiation = True

    def _softmax(self) -> bool:
        return self.interrupt and self.heads.softmax_temperature is not None

    def extra_inputs(self, td: TensorDictBase) -> dict[str, Tensor]:
        """``initiable`` ``(B, O)`` bool (``Subtasks.initiation``) when the subtasks define it,
        beside the base's inputs (given policies' actions)."""
        out = super().extra_inputs(td)
        if self.honours_initiation:
            out[keys.INITIABLE] = self.subtasks.initiation(td)
        return out

    def decide_of(
        self, values: Mapping[str, Tensor], running: Tensor, terminated: Tensor | None
    ) -> dict[str, Tensor]:
        q_mu = values[keys.OPTION_VALUE]  # (O, B)
        initiable = values.get(keys.INITIABLE)  # (O, B) or None
        mu = u = None
        if self._softmax():
            mu = masked_mu_bar(q_mu, self.heads.softmax_temperature, initiable)  # (O, B)
            g = self.generator(q_mu.device)
            u = torch.rand(q_mu.shape[1], generator=g, device=q_mu.device, dtype=q_mu.dtype)
        q_hat = values[keys.MAX_VALUE] if self.interrupt else None
        q_avg = values.get(keys.ACTION_VALUE) if initiable is not None else None
        return interruption_decide_of(
            values[keys.OPTION_ACTION_VALUE],
            q_mu,
            q_hat,
            running,
            terminated,
            mu,
            u,
            initiable,
            q_avg,
        )

    def decide_scalar(
        self, values: Mapping[str, list], running: int, terminated: bool
    ) -> dict[str, Any]:
        q_mu = values[keys.OPTION_VALUE]  # [O]
        init = values.get(keys.INITIABLE)  # [O] bool or None: I_o at s_t
        best = first_argmax_where(q_mu, init)  # -1: no option is initiable
        interrupted = False
        if running < 0 or terminated:
            if best < 0:  # line 4 has no option: the averaging policy acts
                return {
                    "action": first_argmax(values[keys.ACTION_VALUE]),
                    "option": -1,
                    keys.INTERRUPTED: False,
                }
            option = best  # line 4
        elif not self.interrupt or best < 0:  # no interruption, or no option to interrupt to
            option = running
        else:
            allowed = range(len(q_mu)) if init is None else [k for k, ok in enumerate(init) if ok]
            mu = [0.0] * len(q_mu)  # mu_bar over the initiable options
            if self._softmax():
                T = self.heads.softmax_temperature
                m = max(q_mu[k] for k in allowed)
                w = {k: math.exp((q_mu[k] - m) / T) for k in allowed}
                z = sum(w.values())
                for k in allowed:
                    mu[k] = w[k] / z
                v = sum(mu[k] * q_mu[k] for k in allowed)
            else:
                v = q_mu[best]
            interrupted = values[keys.MAX_VALUE][running] < v  # line 6
            option = running
            if interrupted:
                if self._softmax():
                    u = float(torch.rand(1, generator=self.generator(torch.device("cpu"))))
                    option, acc = allowed[-1], 0.0
                    for k in allowed:
                        acc += mu[k]
                        if acc > u:
                            option = k
                            break
                else:
                    option = best
        action = first_argmax(values[keys.OPTION_ACTION_VALUE][option])  # line 11
        return {"action": action, "option": option, keys.INTERRUPTED: interrupted}
