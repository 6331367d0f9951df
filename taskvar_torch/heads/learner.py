"""The shared replay/update loop of every head: one sample, every head, one step (paper §3.1-3.4).

:class:`MultiHeadLoss` is a TorchRL ``LossModule``: from one sampled batch of raw transitions it
relabels every head's targets (:mod:`taskvar_torch.heads.relabel`), runs each online network once on
``[s; s']`` and each target network once on ``s'``, and returns every head's loss; its target
networks are registered the TorchRL way (``target_<head>_params``) for ``SoftUpdate`` /
``HardUpdate``. Each head's TD target is the double-DQN target, written out in its module (one
``DQNLoss`` cannot hold per-option rewards, masks and the expectile loss); the averaging head's loss
is tested equal to ``DQNLoss(double_dqn=True)``. :class:`MultiHeadLearner` adds the optimiser,
target updates, an optional Polyak average for evaluation and device-side loss sums.
"""

from __future__ import annotations

import copy
import dataclasses
import math

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictParams
from torch import nn
from torchrl.objectives import HardUpdate, LossModule, SoftUpdate

from taskvar_torch.compiling import Compiled
from taskvar_torch.config.schema import TrainConfig
from taskvar_torch.heads.averaging import averaging_loss
from taskvar_torch.heads.bundle import Heads, with_given_policies, with_root_row
from taskvar_torch.heads.max_value import (
    MAX_VALUE_ESTIMATORS,
    OptimismGapHead,
    distinct_rows,
    instance_max_value_loss,
    max_value_loss,
)
from taskvar_torch.heads.networks import StackedHead, StackedMLP, head_network
from taskvar_torch.heads.options import option_greedy_actions, options_loss
from taskvar_torch.heads.relabel import InstanceFeatures, Transitions, relabel
from taskvar_torch.heads.robustness import (
    ROBUSTNESS_TARGETS,
    ROBUSTNESS_UNTIL,
    component_matrix,
    parent_closure,
    robustness_loss,
)
from taskvar_torch.heads.seeds import num_seeds
from taskvar_torch.heads.switching import (
    consistent_with_option,
    mu_bar_probs,
    mu_bar_temperature,
    switching_loss,
)
from taskvar_torch.subtasks.base import Subtasks

_NEEDS = {"switching": ("options",), "max_value": ("options", "switching")}
MATMUL_DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16}
"""``train.matmul_dtype`` -> the dtype the network passes run their matmuls in."""


def _unique_params(module: nn.Module) -> TensorDictParams:
    """A flat ``TensorDictParams`` of the module's parameters, each shared tensor once."""
    params = {name.replace(".", "_"): p for name, p in module.named_parameters()}
    return TensorDictParams(TensorDict(params, batch_size=[]), no_convert=True)


def _stack_members(net: nn.Module) -> list[nn.Module]:
    """The networks a head is made of (an optimism-gap head is its base and its gap)."""
    if isinstance(net, OptimismGapHead):
        return _stack_members(net.base) + _stack_members(net.gap)
    return [net]


def _shared_stack(heads: nn.ModuleDict) -> StackedMLP | None:
    """The :class:`StackedMLP` every head of the paper is made of, if there is one (else
    ``None``)."""
    nets = [m for h in heads.values() for m in _stack_members(head_network(h))]
    if nets and all(isinstance(n, StackedHead) for n in nets):
        if len({id(n.stack) for n in nets}) == 1:
            return nets[0].stack
    return None


class MultiHeadLoss(LossModule):
    """Losses of every head in a :class:`Heads` bundle from one sample (paper §3.1-3.4).

    Args:
        heads: the online heads (trained in place).
        subtasks: the family's options, used to relabel transitions.
        settings: the run's ``train`` config, whose discounts, double-Q, targets, expectile level,
            mu_bar, max-value estimator and matmul dtype the losses read.
        instance_features: the family's instance features, read by the ``instance`` max-value
            estimator only.

    ``forward`` returns a ``TensorDict`` of scalar losses ``loss_<head>`` for the heads present.
    """

    def __init__(
        self,
        heads: Heads,
        subtasks: Subtasks,
        settings: TrainConfig,
        instance_features: InstanceFeatures | None = None,
    ):
        super().__init__()
        self.instance_features = instance_features
        for name, needs in _NEEDS.items():
            missing = [n for n in needs if heads.has(name) and not heads.has(n)]
            if missing:
                raise ValueError(f"the {name} head needs the {missing} head(s) in the bundle")
        if settings.robustness_target not in ROBUSTNESS_TARGETS:
            raise ValueError(
                f"robustness_target must be one of {list(ROBUSTNESS_TARGETS)}, "
                f"got {settings.robustness_target!r}"
            )
        if (
            heads.has("robustness")
            and settings.robustness_target == "option"
            and not heads.has("options")
        ):
            raise ValueError(
                "the robustness head with robustness_target='option' needs the ['options'] head(s) "
                "in the bundle (its target follows pi^o)"
            )
        if settings.robustness_until not in ROBUSTNESS_UNTIL:
            raise ValueError(
                f"robustness_until must be one of {list(ROBUSTNESS_UNTIL)}, "
                f"got {settings.robustness_until!r}"
            )
        if settings.hierarchy_root_policy not in ("averaging", "option"):
            raise ValueError(
                "hierarchy_root_policy must be one of ['averaging', 'option'], "
                f"got {settings.hierarchy_root_policy!r}"
            )
        # the composed root whose policy is pi^avg (paper §3.4.2), or None: its intra-option
        # transitions (switching, max-value) and its robustness target follow the averaging head
        self.avg_root = None
        if (
            settings.hierarchy_root_policy == "averaging"
            and subtasks.hierarchy is not None
            and heads.has("options")
        ):
            if not heads.has("averaging"):
                raise ValueError("root_policy='averaging' needs the ['averaging'] head")
            self.avg_root = list(subtasks.names).index(subtasks.hierarchy.root)
        if settings.max_value_estimator not in MAX_VALUE_ESTIMATORS:
            raise ValueError(
                f"max_value_estimator must be one of {list(MAX_VALUE_ESTIMATORS)}, "
                f"got {settings.max_value_estimator!r}"
            )
        if settings.max_value_estimator == "instance" and heads.has("max_value"):
            if getattr(head_network(heads.heads["max_value"]), "critic", None) is None:
                raise ValueError(
                    "max_value_estimator='instance' needs a max-value head with an instance "
                    "critic (factory.build_heads with train.max_value_estimator=instance)"
                )
        if settings.matmul_dtype not in MATMUL_DTYPES:
            raise ValueError(
                f"matmul_dtype must be one of {sorted(MATMUL_DTYPES)}, "
                f"got {settings.matmul_dtype!r}"
            )
        if tuple(heads.option_names) != tuple(subtasks.names):
            raise ValueError(
                f"heads.option_names {heads.option_names} differ from subtasks.names {subtasks.names}"
            )
        self.heads = heads
        self.subtasks = subtasks
        self.settings = settings
        self.mu_bar_temperature = mu_bar_temperature(settings)  # None: greedy mu_bar
        self.head_names = tuple(heads.heads.keys())
        # one deepcopy, so heads that share a StackedMLP share it in the targets too
        self.target_heads = copy.deepcopy(heads.heads).requires_grad_(False)
        # TorchRL naming (<name>_params / target_<name>_params), so SoftUpdate/HardUpdate find the
        # targets; unique parameters only, so a stacked network is updated once
        self._has_update_associated["heads"] = False
        self.heads_params = _unique_params(heads.heads)
        self.target_heads_params = _unique_params(self.target_heads)
        self.stack = _shared_stack(heads.heads)  # StackedMLP of every head, or None
        self.target_stack = _shared_stack(self.target_heads)
        self.seeds = num_seeds(heads)  # S independent runs' heads (heads/seeds.py), usually 1
        if self.seeds > 1 and self.stack is None:
            raise ValueError("a bundle of several seeds needs its heads in one StackedMLP")
        self.register_buffer(
            "components", component_matrix(subtasks.names, subtasks.hierarchy), persistent=False
        )

    def _head_outputs(
        self, obs: torch.Tensor, next_obs: torch.Tensor, far_obs: torch.Tensor | None = None
    ) -> tuple[dict[str, torch.Tensor], ...]:
        """Every head at s (with gradient), at s' (online, detached; target), and with ``far_obs``
        the averaging and option heads at ``s_{t+k}``; the max-value head's loss trains its gap
        only.
        """
        B = obs.shape[0]
        ahead = next_obs if far_obs is None else torch.cat([next_obs, far_obs])  # (B or 2B, D)
        if self.stack is not None:  # fused: one batched pass for every head
            out = self.stack(obs)  # (K, B, max_out), with gradient
            with torch.no_grad():  # s' values are only read detached: no backward through them
                if self.seeds > 1 and far_obs is not None:  # keep each pass's rows seed-major
                    out_ahead = torch.cat([self.stack(next_obs), self.stack(far_obs)], 1)
                    target_ahead = torch.cat(
                        [self.target_stack(next_obs), self.target_stack(far_obs)], 1
                    )
                elif (distinct := self._distinct_next(ahead)) is not None:
                    rows, index = distinct  # s' values on its distinct rows, gathered back
                    out_ahead = self.stack(rows)[:, index]  # (K, B, max_out)
                    target_ahead = self.target_stack(rows)[:, index]
                else:
                    out_ahead = self.stack(ahead)  # (K, B or 2B, max_out)
                    target_ahead = self.target_stack(ahead)
            outs = {
                "cur": out,
                "next": out_ahead[:, :B],
                "target": target_ahead[:, :B],
                "far": out_ahead[:, B:],
                "far_target": target_ahead[:, B:],
            }

            def run(net: nn.Module, which: str) -> torch.Tensor:
                if isinstance(net, OptimismGapHead):
                    return OptimismGapHead.combine(
                        run(net.base, which).detach(), run(net.gap, which)
                    )
                return net.select(outs[which]).reshape(B, *net.out_shape)

        else:  # independent networks
            both = torch.cat([obs, ahead])  # (2B or 3B, D)

            def run(net: nn.Module, which: str) -> torch.Tensor:
                if isinstance(net, OptimismGapHead):
                    return OptimismGapHead.combine(
                        run(net.base, which).detach(), run(net.gap, which)
                    )
                if which in ("target", "far_target"):
                    y = net(ahead)
                    return y[:B] if which == "target" else y[B:]
                y = net(both)
                return y[:B] if which == "cur" else y[B : 2 * B] if which == "next" else y[2 * B :]

        cur, nxt, nxt_target, far, far_target = {}, {}, {}, {}, {}
        for n in self.head_names:
            online, target = head_network(self.heads.heads[n]), head_network(self.target_heads[n])
            cur[n] = run(online, "cur")
            nxt[n] = run(online, "next").detach()
            with torch.no_grad():
                nxt_target[n] = run(target, "target")
                if far_obs is not None and n in ("averaging", "options"):
                    far[n] = run(online, "far")
                    far_target[n] = run(target, "far_target")
        return cur, nxt, nxt_target, far, far_target

    def _distinct_next(self, ahead: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
        """``ahead``'s distinct rows and the index back, for the detached s' passes on the CPU
        outside ``torch.compile``; else ``None`` (every row runs).
        """
        if ahead.device.type != "cpu" or torch.compiler.is_compiling():
            return None
        return distinct_rows(ahead, self.seeds)

    def _forward_value_estimator_keys(self, **kwargs) -> None:  # LossModule hook; no estimator
        pass

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        return TensorDict(self.losses(self.relabel(tensordict)), batch_size=[])

    def relabel(self, tensordict: TensorDictBase) -> Transitions:
        """The sampled batch relabelled for every head (:func:`relabel`); a bundle of ``S`` seeds
        (heads/seeds.py) reads it as ``S`` seed-major groups of rows (``Transitions.seeds``)."""
        batch = relabel(
            tensordict,
            self.subtasks,
            robustness=self.heads.has("robustness"),
            instance_features=self.instance_features,
        )
        if self.seeds > 1:
            batch = dataclasses.replace(batch, seeds=self.seeds)
        return batch

    def losses(self, batch: Transitions) -> dict[str, torch.Tensor]:
        """Every head's loss ``{"loss_<head>": scalar}`` on a relabelled batch: plain tensors in
        and out (what :class:`MultiHeadLearner` compiles with ``compile=True``)."""
        s = self.settings
        far_obs = batch.nstep.observation if batch.nstep is not None else None
        obs = batch.observation
        dtype = MATMUL_DTYPES[s.matmul_dtype]
        # matmul_dtype=bfloat16: the network passes (and so their backward) under autocast, every
        # head's values back in float32 before any target or loss
        with torch.autocast(obs.device.type, dtype=dtype, enabled=dtype != torch.float32):
            outputs = self._head_outputs(obs, batch.next_observation, far_obs)
        cur, nxt, nxt_target, far, far_target = (
            {k: v.float() for k, v in out.items()} for out in outputs
        )
        if batch.given_next is not None and "options" in nxt:  # given-policy options: pi_o(s')
            nxt["options"] = with_given_policies(nxt["options"], batch.given_next)
            nxt_target["options"] = with_given_policies(nxt_target["options"], batch.given_next)

        losses: dict[str, torch.Tensor] = {}
        if "averaging" in cur:
            losses["loss_averaging"] = averaging_loss(
                cur["averaging"],
                nxt["averaging"],
                nxt_target["averaging"],
                batch,
                s.gamma,
                s.double_q,
                far.get("averaging"),
                far_target.get("averaging"),
            )
        if "options" in cur:
            losses["loss_options"] = options_loss(
                cur["options"],
                nxt["options"],
                nxt_target["options"],
                batch,
                s.gamma,
                s.double_q,
                far.get("options"),
                far_target.get("options"),
            )
        if "switching" in cur:
            q_options = with_given_policies(cur["options"].detach(), batch.given)  # (B, O, A)
            if self.avg_root is not None:  # pi^root = pi^avg
                q_options = with_root_row(q_options, cur["averaging"].detach(), self.avg_root)
            consistent = consistent_with_option(batch.action, q_options, batch.initiation)  # (B, O)
            mu_next = mu_bar_probs(
                nxt["switching"], batch.initiation_next, self.mu_bar_temperature
            )  # (B, O)
            losses["loss_switching"] = switching_loss(
                cur["switching"], nxt_target["switching"], mu_next, consistent, batch, s.gamma
            )
            if "max_value" in cur and s.max_value_estimator == "instance":
                loss_critic, loss_hat = instance_max_value_loss(
                    cur["max_value"],
                    head_network(self.heads.heads["max_value"]).critic,
                    head_network(self.target_heads["max_value"]).critic,
                    mu_next,
                    consistent,
                    batch,
                    s.gamma,
                    s.max_value_instances,
                )  # both train parts of the max-value head (its critic, its gap): one entry
                losses["loss_max_value"] = loss_critic + loss_hat
            elif "max_value" in cur:
                losses["loss_max_value"] = max_value_loss(
                    cur["max_value"],
                    nxt_target["max_value"],
                    mu_next,
                    consistent,
                    batch,
                    s.gamma,
                    s.max_value_expectile,
                )
        if "robustness" in cur:
            mask = parent_closure(batch.initiation, self.components)  # (B, O)
            next_action = None  # "greedy": Q-learning on R
            if s.robustness_target == "option":  # R of following o: its own action at s'
                next_action = option_greedy_actions(nxt["options"])  # (B, O)
                if self.avg_root is not None:  # the root follows pi^avg (paper §3.4.2)
                    next_action = next_action.clone()
                    next_action[:, self.avg_root] = nxt["averaging"].argmax(-1)
            losses["loss_robustness"] = robustness_loss(
                cur["robustness"],
                nxt["robustness"],
                nxt_target["robustness"],
                mask,
                batch,
                s.robustness_gamma,
                s.double_q,
                next_action,
                until_termination=s.robustness_until == "termination",
            )
        return losses


class ForeachSoftUpdate(SoftUpdate):
    """TorchRL ``SoftUpdate`` (``target <- eps * target + (1 - eps) * source``) whose ``step`` lerps
    every target tensor in one ``torch._foreach_lerp_``.
    """

    def init_(self) -> None:
        super().init_()
        keys_ = list(self._sources.keys(True, True))
        self._source_list = [self._sources.get(k) for k in keys_]
        self._target_list = [self._targets.get(("target_" + k[0], *k[1:])) for k in keys_]

    @torch.no_grad()
    def step(self) -> None:
        torch._foreach_lerp_(self._target_list, self._source_list, 1.0 - self.eps)


def clip_grad_norm_per_group(groups: list[list[torch.Tensor]], max_norm: float) -> None:
    """``clip_grad_norm_`` applied to each parameter group separately, in two foreach calls."""
    params = [p for g in groups for p in g if p.grad is not None]
    if not params:
        return
    grads = [p.grad for p in params]
    norms = torch._foreach_norm(grads)  # one scalar per tensor
    coefs, i = [], 0
    for g in groups:
        n = sum(p.grad is not None for p in g)
        total = torch.linalg.vector_norm(torch.stack(norms[i : i + n]))
        coef = (max_norm / (total + 1e-6)).clamp(max=1.0)
        coefs.extend([coef] * n)
        i += n
    torch._foreach_mul_(grads, coefs)


def clip_grad_norm_stacked(params: list[torch.Tensor], max_norm: float) -> None:
    """``clip_grad_norm_`` per member of stacked parameters (leading dimension = member)."""
    grads = [p.grad for p in params if p.grad is not None]
    if not grads:
        return
    sq = torch.stack([g.pow(2).flatten(1).sum(1) for g in grads]).sum(0)  # (K,)
    coef = (max_norm / (sq.sqrt() + 1e-6)).clamp(max=1.0)  # (K,)
    for g in grads:
        g.mul_(coef.view(-1, *([1] * (g.dim() - 1))))


class CompiledLosses(Compiled):
    """:meth:`MultiHeadLoss.losses` and their backward through ``torch.compile``, with an eager
    fallback (:class:`~taskvar_torch.compiling.Compiled`; docs/benchmarks.md).
    """

    def __init__(self, loss: MultiHeadLoss):
        super().__init__(loss.losses, "the learner")


class MultiHeadLearner:
    """Optimiser, target updates and loss bookkeeping around a :class:`MultiHeadLoss`.

    Args:
        loss: the fused loss (owns the heads and their targets).
        lr: Adam learning rate.
        max_grad_norm: per-head gradient-norm clip (``None``: no clipping).
        target_update: ``"soft"`` (Polyak, ``target_tau``) or ``"hard"`` (copy every
            ``target_period`` updates).
        compile: run the losses through ``torch.compile`` (:class:`CompiledLosses`); same losses up
            to float rounding; falls back to eager with a warning.
        eval_ema_tau: keep :attr:`eval_heads`, a Polyak average of the heads' weights (``ema <- ema
            + tau (online - ema)`` per update) that evaluation reads; ``None``: :attr:`eval_heads`
            is :attr:`heads`.
    """

    def __init__(
        self,
        loss: MultiHeadLoss,
        lr: float = 1e-3,
        max_grad_norm: float | None = 10.0,
        target_update: str = "soft",
        target_tau: float = 0.01,
        target_period: int = 500,
        compile: bool = False,
        eval_ema_tau: float | None = None,
    ):
        self.loss = loss
        self.losses = CompiledLosses(loss) if compile else loss.losses
        self.heads = loss.heads
        self.max_grad_norm = max_grad_norm
        self._stacked = loss.stack is not None
        self._groups = (
            [list(loss.stack.parameters())]
            if self._stacked
            else [list(m.parameters()) for m in self.heads.paper_heads().values()]
        )
        self.optimizer = torch.optim.Adam(self.heads.parameters(), lr=lr, fused=True)
        if target_update == "soft":
            self.target_updater = ForeachSoftUpdate(loss, tau=target_tau)
        elif target_update == "hard":
            if target_period < 1:
                raise ValueError(f"target_period must be >= 1, got {target_period}")
            # TorchRL's HardUpdate copies when its counter, counting 0, 1, ..., reaches the
            # interval, i.e. every interval + 1 steps: interval P - 1 copies at updates P, 2P, ...
            self.target_updater = HardUpdate(loss, value_network_update_interval=target_period - 1)
        else:
            raise ValueError(
                f"target_update must be one of ['hard', 'soft'], got {target_update!r}"
            )
        self.eval_ema_tau = eval_ema_tau
        self.eval_heads = self.heads  # the weights evaluation reads
        if eval_ema_tau is not None:
            if not 0.0 < eval_ema_tau <= 1.0:
                raise ValueError(f"eval_ema_tau must be in (0, 1] or None, got {eval_ema_tau}")
            self.eval_heads = copy.deepcopy(self.heads).requires_grad_(False)
            self._ema = list(self.eval_heads.parameters())
            self._ema_source = list(self.heads.parameters())
        self.num_updates = 0
        self._loss_sum: TensorDict | None = None  # device-side sums since the last pop_losses
        self._loss_count = 0

    def update(self, sample: TensorDictBase) -> TensorDict:
        """One gradient step of every head on one shared sample; returns the (detached) losses."""
        losses = self.losses(self.loss.relabel(sample))
        total = sum(losses.values())
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        if self.max_grad_norm is not None:
            if self._stacked:  # each member of the stack is one head
                clip_grad_norm_stacked(self._groups[0], self.max_grad_norm)
            else:
                clip_grad_norm_per_group(self._groups, self.max_grad_norm)
        self.optimizer.step()
        self.target_updater.step()
        if self.eval_ema_tau is not None:
            with torch.no_grad():
                torch._foreach_lerp_(self._ema, self._ema_source, self.eval_ema_tau)
        losses = TensorDict(losses, batch_size=[]).detach()
        self._loss_sum = losses.clone() if self._loss_sum is None else self._loss_sum.add_(losses)
        self._loss_count += 1
        self.num_updates += 1
        return losses

    def set_lr(self, lr: float) -> None:
        """The Adam learning rate of every head from the next update on (``train.lr_end``)."""
        for group in self.optimizer.param_groups:
            group["lr"] = lr

    def pop_losses(self) -> dict[str, float]:
        """Mean of each loss since the last call (one host sync), then reset the sums.

        Raises:
            FloatingPointError: a loss was NaN or infinite (names the heads).
        """
        if self._loss_sum is None:
            return {}
        names = list(self._loss_sum.keys())
        values = torch.stack([self._loss_sum[k] for k in names]) / self._loss_count
        values = values.tolist()  # the one host sync of the logging interval
        self._loss_sum, self._loss_count = None, 0
        bad = [k for k, v in zip(names, values) if not math.isfinite(v)]
        if bad:
            raise FloatingPointError(
                f"non-finite loss in {bad} after {self.num_updates} updates: training diverged"
            )
        return dict(zip(names, values))

    # ---- checkpointing -----------------------------------------------------------------------

    def state_dict(self) -> dict:
        """Target networks, optimiser, target-updater and loss-sum state (heads saved apart)."""
        return {
            "targets": self.loss.target_heads.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "target_updater": self.target_updater.state_dict(),
            "num_updates": self.num_updates,
            "loss_sum": None if self._loss_sum is None else self._loss_sum.to_dict(),
            "loss_count": self._loss_count,
        }

    def load_state_dict(self, state: dict) -> None:
        self.loss.target_heads.load_state_dict(state["targets"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.target_updater.load_state_dict(state["target_updater"])
        self.num_updates = int(state["num_updates"])
        ls = state["loss_sum"]
        self._loss_sum = None if ls is None else TensorDict(ls, batch_size=[])
        self._loss_count = int(state["loss_count"])
