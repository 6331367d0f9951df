"""The exploration behaviour that generates the one stream of experience every head learns from.

At every reset a sub-environment draws its *behaviour mode*: with probability ``1 - option_prob``
the epsilon-greedy averaging policy (``behaviour = -1``), else options as the options controller
runs them (paper §3.2), an option picked epsilon-greedily from mu_bar among the initiable ones
(uniformly with probability ``max(epsilon, option_coverage)``; docs/scale.md) and run until beta_o
(``behaviour = o``). The mode is carried in the tensordict like a recurrent state.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Categorical
from torchrl.modules import EGreedyModule

from taskvar_torch import keys
from taskvar_torch.compiling import Compiled
from taskvar_torch.heads.bundle import HEAD_OUT_KEYS, Heads, with_given_policies, with_root_row
from taskvar_torch.heads.networks import head_network
from taskvar_torch.heads.snapshots import HeadValues
from taskvar_torch.heads.switching import mu_bar_probs
from taskvar_torch.subtasks.base import Subtasks

BEHAVIOUR = "behaviour"
"""Key of the carried behaviour mode: -1 averaging policy, o >= 0 running option o."""
IS_INIT = "is_init"


class BehaviourPolicy(TensorDictModuleBase):
    """Epsilon-greedy mixture of the averaging policy and mu_bar-run options (a collector policy).

    Args:
        heads: bundle with at least the averaging head; options and switching heads enable the
            option mode.
        subtasks: initiation and termination of the options.
        action_spec: the env's action spec (``Categorical``), for uniform exploratory actions.
        option_prob: probability that an episode is run by options.
        eps: initial epsilon.
        root_policy: the composition hierarchy root's head, ``"averaging"`` or ``"option"``
            (§3.4.2).
        option_coverage: least probability that an option pick is uniform over the initiable
            options.
        stacked: read every head from one pass of their ``StackedMLP`` (:class:`HeadValues`);
            ``False``: each head on its own.
        generators: ``S`` generators, one per run of equal row blocks, each block drawing every
            random number from its own (docs/seeds.md); ``None``: the global stream and
            ``EGreedyModule``.
        compile: run the heads and the choice of action and mode through ``torch.compile`` (the same
            bits; the random draws stay eager).
    """

    def __init__(
        self,
        heads: Heads,
        subtasks: Subtasks,
        action_spec: Categorical,
        option_prob: float = 0.5,
        eps: float = 1.0,
        root_policy: str = "option",
        option_coverage: float = 0.0,
        stacked: bool = True,
        compile: bool = False,
        generators: list[torch.Generator] | None = None,
    ):
        super().__init__()
        if not 0.0 <= option_prob <= 1.0:
            raise ValueError(f"option_prob must be in [0, 1], got {option_prob}")
        if not 0.0 <= option_coverage <= 1.0:
            raise ValueError(f"option_coverage must be in [0, 1], got {option_coverage}")
        self.option_coverage = float(option_coverage)
        self.heads = heads
        self.subtasks = subtasks
        self.use_options = heads.has("options") and heads.has("switching") and option_prob > 0
        self.option_prob = option_prob if self.use_options else 0.0
        tree = subtasks.hierarchy
        self.root = (
            list(heads.option_names).index(tree.root)
            if root_policy == "averaging" and tree is not None and self.use_options
            else None
        )
        self.in_keys = [keys.OBSERVATION, IS_INIT]
        self.out_keys = [keys.ACTION, BEHAVIOUR]
        self.egreedy = EGreedyModule(action_spec, eps_init=float(eps), eps_end=0.0)
        names = ["averaging", "switching", "options"] if self.use_options else ["averaging"]
        # every head the behaviour reads from one stacked pass (each head's values bit-equal to
        # running it on its own: heads/snapshots.py), or each head on its own
        self._values = (
            HeadValues(heads, names) if stacked and HeadValues.supports(heads, names) else None
        )
        self._compiled = Compiled(self._decide_eager, "the behaviour policy") if compile else None
        self.generators = list(generators) if generators is not None else None
        self.active: list[bool] | None = None  # generators: blocks that draw (None: all)
        self.num_actions = int(action_spec.n)

    @property
    def epsilon(self) -> float:
        """The exploration rate (its mean where it is set per row)."""
        return float(self.egreedy.eps.float().mean())

    def set_epsilon(self, eps: float | torch.Tensor) -> None:
        """Set the exploration rate (the trainer's schedule owns it): one float, or one per row
        (``(N,)``, e.g. each run of a batch at its own point of the schedule)."""
        if isinstance(eps, torch.Tensor) and eps.ndim > 0:
            self.egreedy.eps = eps.to(self.egreedy.eps.device, torch.float32)
        else:
            if self.egreedy.eps.ndim > 0:
                self.egreedy.eps = torch.zeros((), device=self.egreedy.eps.device)
            self.egreedy.eps.fill_(float(eps))

    def set_active(self, active: list[bool] | None) -> None:
        """With ``generators``: which blocks draw at the next steps (a block whose episodes have
        all ended draws nothing, as its run alone would have stopped; its rows get zeros)."""
        self.active = active

    def _blocks(self, draw, m: int) -> list[torch.Tensor]:
        """``draw(generator, s)`` for each active block ``s``, zeros of ``m`` rows for the others."""
        act = self.active or [True] * len(self.generators)
        return [
            draw(g, s) if a else torch.zeros(m, dtype=torch.int64)
            for s, (g, a) in enumerate(zip(self.generators, act))
        ]

    def _rand(self, n: int, device: torch.device) -> torch.Tensor:
        """``(n,)`` uniforms: the global stream, or block ``s`` from ``generators[s]``."""
        if self.generators is None:
            return torch.rand(n, device=device)
        m = n // len(self.generators)
        blocks = self._blocks(lambda g, s: torch.rand(m, generator=g), m)
        return torch.cat([b.to(torch.float32) for b in blocks]).to(device)

    def _pick(self, allowed: torch.Tensor) -> torch.Tensor:
        """One index per row of ``allowed`` ``(n, O)``, uniform over its nonzero entries."""
        if self.generators is None:
            return torch.multinomial(allowed, 1).squeeze(-1)
        rows = allowed.cpu().chunk(len(self.generators))
        m = rows[0].shape[0]
        blocks = self._blocks(lambda g, s: torch.multinomial(rows[s], 1, generator=g)[:, 0], m)
        return torch.cat(blocks).to(allowed.device)

    def _explore(self, td: TensorDictBase) -> TensorDictBase:
        """Epsilon-greedy: ``EGreedyModule``, or (``generators``) the same rule on their draws."""
        if self.generators is None:
            return self.egreedy(td)
        action = td.get(keys.ACTION)
        n = action.shape[0]
        cond = self._rand(n, action.device) < self.egreedy.eps
        m = n // len(self.generators)
        draw = lambda g, s: torch.randint(self.num_actions, (m,), generator=g)  # noqa: E731
        uniform = torch.cat(self._blocks(draw, m)).to(action.device)
        td.set(keys.ACTION, torch.where(cond, uniform.to(action.dtype), action))
        return td

    def _decide_eager(
        self,
        obs: torch.Tensor,  # (N, D)
        mode: torch.Tensor,  # (N,) int64 behaviour mode before the step
        init: torch.Tensor | None = None,  # (N, O) bool initiation
        is_init: torch.Tensor | None = None,  # (N,) bool new episode
        uniform: torch.Tensor | None = None,  # (N,) a uniform initiable option
        explore: torch.Tensor | None = None,  # (N,) bool pick the option uniformly
        run_options: torch.Tensor | None = None,  # (N,) bool a new episode runs options
        ended: torch.Tensor | None = None,  # (N, O) bool termination beta_o(s)
        given: torch.Tensor
        | None = None,  # (N, O) int64 given-policy options' actions (-1: learnt)
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The greedy action and the behaviour mode from the heads and the step's draws (no random
        draws: a pure function, what ``compile=True`` compiles)."""
        values = None if self._values is None or self._values.stack is None else self._values(obs)

        def head(name: str) -> torch.Tensor:
            if values is not None:
                return values[HEAD_OUT_KEYS[name]]
            return head_network(self.heads.heads[name])(obs)

        q_avg = head("averaging")  # (N, A)
        action = q_avg.argmax(-1)  # (N,)
        if not self.use_options:
            return action, mode
        q_mu = head("switching")  # (N, O)
        greedy = mu_bar_probs(q_mu, init).argmax(-1)  # (N,)
        picked = torch.where(explore, uniform, greedy)  # (N,) eps-greedy mu_bar
        running = mode.clamp_min(0)
        ended = ended.gather(-1, running.unsqueeze(-1)).squeeze(-1)
        mode = torch.where(
            is_init,
            torch.where(run_options, picked, torch.full_like(picked, -1)),
            torch.where((mode >= 0) & ended, picked, mode),
        )  # (N,)
        q_opt = head("options")  # (N, O, A)
        if self.root is not None:  # pi^root = pi^avg
            q_opt = with_root_row(q_opt, q_avg, self.root)
        q_opt = with_given_policies(q_opt, given)  # a given controller's own action
        opt_action = q_opt.argmax(-1).gather(-1, mode.clamp(0, init.shape[-1] - 1).unsqueeze(-1))
        return torch.where(mode >= 0, opt_action.squeeze(-1), action), mode  # (N,), (N,)

    @torch.no_grad()
    def forward(self, td: TensorDictBase) -> TensorDictBase:
        obs = td.get(keys.OBSERVATION)  # (N, D)
        N = obs.shape[0]
        is_init = td.get(IS_INIT).reshape(N)  # (N,) bool
        mode = td.get(BEHAVIOUR, None)  # (N,) int64, absent before the first step
        if mode is None:
            mode = torch.full((N,), -1, dtype=torch.int64, device=obs.device)
        decide = self._decide_eager if self._compiled is None else self._compiled
        if not self.use_options:  # every episode is the averaging policy's: mode -1 always
            action, _ = decide(obs, mode)
            mode = torch.full((N,), -1, dtype=torch.int64, device=obs.device)
        else:
            # the random draws, in their fixed order (the networks draw nothing): uniform options,
            # exploration, option episodes; then EGreedyModule's
            init = self.subtasks.initiation(td)  # (N, O) bool
            allowed = (init | ~init.any(-1, keepdim=True)).to(torch.float32)  # (N, O)
            uniform = self._pick(allowed)  # (N,)
            explore = self._rand(N, obs.device) < self.egreedy.eps.clamp_min(self.option_coverage)
            run_options = self._rand(N, obs.device) < self.option_prob
            ended = self.subtasks.termination(td)  # (N, O) bool
            given = self.subtasks.given_actions(td)  # (N, O) or None
            action, mode = decide(
                obs, mode, init, is_init, uniform, explore, run_options, ended, given
            )
        td.set(keys.ACTION, action)
        td.set(BEHAVIOUR, mode)
        return self._explore(td)
