"""Offline interruption (paper §3.3, Definition 1, Algorithm 1) as a batched controller."""

from __future__ import annotations

from collections.abc import Mapping

import torch

from taskvar_torch import keys
from taskvar_torch.controllers.base import (
    Controller,
    argmax_last,
    max_last,
    sample_categorical,
    take_row,
)

Tensor = torch.Tensor


def interruption_decide(
    q_opt: Tensor,  # (B, O, A) Q_o(s_t, a): option policies pi^o (greedy)
    q_mu: Tensor,  # (B, O) Q_mu(s_t, o)
    q_hat: Tensor | None,  # (B, O) Q_hat(s_t, o); None: no interruption (plain options)
    running: Tensor,  # (B,) int64 o_run, -1 = empty
    terminated: Tensor | None = None,  # (B,) bool beta_{o_run}(s_t) = 1
    mu: Tensor | None = None,  # (B, O) softmax mu_bar(s_t, .); None: greedy mu_bar
    u: Tensor | None = None,  # (B,) uniforms for drawing o ~ mu_bar (softmax only)
) -> dict[str, Tensor]:
    """One step of Algorithm 1 for a batch; returns ``action``, ``option`` (new o_run), ``interrupted``.

    - lines 3-4: if o_run is empty (episode start) or has terminated, ``o_run = argmax_o Q_mu(s_t, o)``
      (an argmax even when mu_bar is a softmax, as line 4 says);
    - lines 6-8: else if ``Q_hat(s_t, o_run) < sum_q mu_bar(s_t, q) Q_mu(s_t, q)``, draw
      ``o_run ~ mu_bar(s_t, .)`` (greedy mu_bar: the argmax). ``interrupted`` is this condition, even
      when the draw returns the same option;
    - line 11: ``a_t = argmax_a Q_{o_run}(s_t, a)``.
    """
    best = argmax_last(q_mu)  # (B,) line 4
    empty = running < 0  # (B,)
    if terminated is not None:
        empty = empty | terminated
    if q_hat is None:
        option = torch.where(empty, best, running)
        interrupted = torch.zeros_like(empty)
    else:
        v = max_last(q_mu) if mu is None else (mu * q_mu).sum(-1)  # (B,) V^{mu_bar}(s_t)
        q_run = take_row(q_hat, running.clamp(min=0))  # (B,) Q_hat(s_t, o_run)
        interrupted = (q_run < v) & ~empty  # line 6
        if mu is None:
            option = torch.where(empty | interrupted, best, running)
        else:
            drawn = sample_categorical(mu, u)  # line 7
            option = torch.where(empty, best, torch.where(interrupted, drawn, running))
    action = argmax_last(take_row(q_opt, option))  # (B,) line 11
    return {"action": action, "option": option, keys.INTERRUPTED: interrupted}


class InterruptionController(Controller):
    """Options with offline interruption (Algorithm 1): reads Q_o, Q_mu and Q_hat heads only.

    Writes ``action``, ``option`` (the option that ran), ``interrupted`` (line 6 fired) and
    ``("next", "running_option")``. A softmax mu_bar (``heads.softmax_temperature``) draws from the
    controller's own seeded generator.

    Examples:
        >>> oracle = WindyOracle("whole_column_windy")
        >>> ctrl = InterruptionController(oracle.heads())
        >>> env = TransformedEnv(WindyGridEnv(num_envs=4, layout="whole_column_windy"), ctrl.primer())
        >>> td = env.rollout(20, ctrl, break_when_any_done=False)
        >>> td["interrupted"].shape
        torch.Size([4, 20])
    """

    name = "interruption"
    required_heads = ("options", "switching", "max_value")
    trace_keys = (keys.OPTION, keys.INTERRUPTED)
    interrupt = True

    def decide(
        self, values: Mapping[str, Tensor], running: Tensor, terminated: Tensor | None
    ) -> dict[str, Tensor]:
        q_mu = values[keys.OPTION_VALUE]  # (B, O)
        mu = u = None
        if self.interrupt and self.heads.softmax_temperature is not None:
            mu = self.heads.mu_bar(q_mu)  # (B, O)
            g = self.generator(q_mu.device)
            u = torch.rand(q_mu.shape[0], generator=g, device=q_mu.device, dtype=q_mu.dtype)
        q_hat = values[keys.MAX_VALUE] if self.interrupt else None
        return interruption_decide(
            values[keys.OPTION_ACTION_VALUE], q_mu, q_hat, running, terminated, mu, u
        )
