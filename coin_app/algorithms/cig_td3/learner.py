"""CIG-TD3 Learner: three optimizers, policy delay, soft target updates, no gradient leaks.

One ``update`` = one gradient step on one sampled batch:
    1. targets y^l, y^G with the target networks (no grad);
    2. local critic loss -> grads of ``local_q`` only;
    3. centralized-critic loss (twin Q^g + V + CVAE) -> grads of ``central`` only;
    4. every ``policy_delay``-th update (once ``actor_start_steps`` env steps past the warm-up):
       actor loss -> grads of ``actor`` only (taken with ``torch.autograd.grad`` on the actor's
       parameters, so nothing leaks into critics), then soft updates of all target networks with
       ``tau``. With ``update_order="critic_first"`` (default: TD3 and the official COIN code) the
       critics step before the actor loss is computed, so it is taken on the updated critics;
       ``"joint"`` computes it from the critics before the update and applies all steps together.
On other updates the actor's parameters get no gradient, so Adam leaves them untouched.

``precision="bf16"`` runs every loss's forward pass under ``torch.autocast(bfloat16)`` on the
module's device; the losses widen the network outputs to fp32 (``losses.py``), so parameters,
gradients, Adam state, TD targets, loss reductions and soft updates stay fp32. Nothing here
creates a tensor on a fixed device, so the learner runs where RLlib puts its module
(``num_gpus_per_learner``), in the algorithm process or as one remote learner (``num_learners=1``).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from typing import Any

import torch
from ray.rllib.core.learner.torch.torch_learner import TorchLearner
from ray.rllib.core.rl_module.apis import TargetNetworkAPI
from ray.rllib.utils.metrics import NUM_ENV_STEPS_SAMPLED_LIFETIME

from coin_app.algorithms.choices import PRECISIONS  # noqa: F401 (re-exported)
from coin_app.algorithms.cig_td3.losses import LossConfig, actor_loss, central_critic_loss, local_critic_loss, td_targets


def autocast(module: torch.nn.Module, precision: str) -> contextlib.AbstractContextManager:
    """The context the loss forward passes of ``module`` run in: bfloat16 autocast on its device for "bf16", else nothing."""
    if precision == "fp32":
        return contextlib.nullcontext()
    if precision != "bf16":
        raise ValueError(f"precision={precision!r}; allowed: {' | '.join(PRECISIONS)}")
    return torch.autocast(device_type=next(module.parameters()).device.type, dtype=torch.bfloat16)


def loss_config(config: Any) -> LossConfig:
    """The loss constants of a ``CigTd3Config``."""
    return LossConfig(
        gamma=config.gamma,
        target_noise=config.target_noise,
        target_noise_clip=config.target_noise_clip,
        global_critic=config.global_critic,
        counterfactual_baseline=config.counterfactual_baseline,
        global_weight=config.global_weight,
        vae_weight=config.vae_weight,
        kl_beta=config.kl_beta,
        preact_penalty=config.actor_preact_penalty,
        preact_threshold=config.actor_preact_threshold,
        timeout_bootstrap=config.timeout_bootstrap,
    )


def lr_schedule(lr: float, config: Any) -> float | list[list[float]]:
    """``lr``, or RLlib's piecewise schedule [[env step, lr], ...] when ``config.lr_decay_steps`` > 0.

    Constant until ``lr_decay_start`` env steps, then linear to ``lr * lr_final_fraction`` over
    ``lr_decay_steps`` env steps, constant after. Each update's rate is set from the lifetime
    env-step count (``Learner.after_gradient_based_update``), so a resumed run continues on it.
    """
    steps = config.lr_decay_steps
    if steps <= 0:
        return lr
    start = config.lr_decay_start
    points = [[0, lr]] + ([[start, lr]] if start > 0 else []) + [[start + steps, lr * config.lr_final_fraction]]
    return points


@torch.no_grad()
def soft_update(main_net: torch.nn.Module, target_net: torch.nn.Module, tau: float) -> None:
    """target <- tau * main + (1 - tau) * target for every floating-point tensor of the state, in one fused call.

    The same update as RLlib's ``update_target_network`` (which rebuilds the state dict each
    time), up to float rounding; other buffers are copied.
    """
    main = main_net.state_dict(keep_vars=True)
    pairs = [(t, main[name]) for name, t in target_net.state_dict(keep_vars=True).items()]
    floats = [(t, m) for t, m in pairs if t.is_floating_point()]
    if floats:
        torch._foreach_lerp_([t for t, _ in floats], [m for _, m in floats], tau)
    for t, m in pairs:
        if not t.is_floating_point():
            t.copy_(m)


def _cpu_state(net: torch.nn.Module) -> dict[str, torch.Tensor]:
    """``net``'s state dict with every tensor on the CPU (a checkpoint readable without the learner's GPU)."""
    return {k: v.cpu() for k, v in net.state_dict().items()}


class CigTd3TorchLearner(TorchLearner):
    """Torch learner of CIG-TD3 (and ITD3 when the module has no centralized critic)."""

    def build(self) -> None:
        """Build module and optimizers, then the target networks (with ``learner_threads`` torch threads)."""
        torch.set_num_threads(self.config.learner_threads)  # also in a remote learner's own process
        super().build()
        self.module.foreach_module(lambda mid, mod: mod.make_target_networks() if isinstance(mod, TargetNetworkAPI) else None)
        self.num_updates = 0
        self.env_steps = 0  # the lifetime env-step count of the current update (before_gradient_based_update)
        self._grads: dict[str, Any] = {}
        self._actor_losses: dict[str, Callable[[], tuple[torch.Tensor, dict[str, Any]]]] = {}

    def configure_optimizers_for_module(self, module_id: str, config: Any = None) -> None:
        """One Adam optimizer each for actor, local critics and centralized critic."""
        module = self.module[module_id].unwrapped()
        groups = [("actor", module.actor, config.actor_lr), ("local_critic", module.local_q, config.critic_lr)]
        if module.central is not None:
            groups.append(("central_critic", module.central, config.central_critic_lr))
        self.register_adam(module_id, groups)

    def register_adam(self, module_id: str, groups: list[tuple[str, torch.nn.Module, float]]) -> None:
        """One Adam optimizer per (name, network, learning rate) of ``groups``, on the config's decay schedule if any.

        The fused kernel (CPU and CUDA) steps all of a network's tensors at once: the same update
        as the per-tensor loop up to float rounding, and several times faster for these small
        networks, whose per-tensor overhead dominated the optimizer step.
        """
        config = self.config.get_config_for_module(module_id)
        for name, net, lr in groups:
            params = self.get_parameters(net)
            optimizer = torch.optim.Adam(params, fused=True)
            schedule = lr_schedule(lr, config)
            self.register_optimizer(
                module_id=module_id, optimizer_name=name, optimizer=optimizer, params=params, lr_or_lr_schedule=schedule
            )

    def is_policy_step(self, config: Any) -> bool:
        """Whether the current update also updates the actor and the targets."""
        return (self.num_updates + 1) % config.policy_delay == 0

    def actor_learns(self, config: Any) -> bool:
        """Whether the actor is updated in this update: a policy step, ``actor_start_steps`` env steps after the warm-up."""
        return self.is_policy_step(config) and self.env_steps >= config.warmup_steps + config.actor_start_steps

    def before_gradient_based_update(self, *, timesteps: dict[str, Any]) -> None:
        """Remember the lifetime env-step count (the actor's start after the warm-up depends on it)."""
        super().before_gradient_based_update(timesteps=timesteps)
        self.env_steps = int(timesteps.get(NUM_ENV_STEPS_SAMPLED_LIFETIME, 0))

    def compute_loss_for_module(self, *, module_id: str, config: Any, batch: dict[str, Any], fwd_out: dict[str, Any]) -> torch.Tensor:
        """All losses of this update; the per-network gradients are taken here, one loss each (critics, then the actor)."""
        module = self.module[module_id].unwrapped()
        grads, stats = self.critic_losses(module, config, batch)
        total = sum(loss.detach() for loss, _ in grads.values())
        for name, (loss, _) in grads.items():
            self.metrics.log_value((module_id, f"{name}_loss"), loss.detach(), window=1)
        if self.actor_learns(config):

            def actor_objective() -> tuple[torch.Tensor, dict[str, Any]]:
                with autocast(module, config.precision):
                    return self.actor_loss(module, config, batch)

            if config.update_order == "joint":  # every loss from the critics before this update
                loss_pi, pi_stats = actor_objective()
                grads["actor"] = (loss_pi, list(module.actor.parameters()))
                self._log_actor(module_id, loss_pi, pi_stats)
            else:  # critic_first: computed in compute_gradients, after the critics have stepped
                self._actor_losses[module_id] = actor_objective
        for key, value in stats.items():
            self.metrics.log_value((module_id, key), value, window=1)
        self._grads[module_id] = grads
        return total

    def critic_losses(self, module: Any, config: Any, batch: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
        """CIG-TD3's critic losses as {optimizer name: (loss, its network's parameters)} and their stats (Eqs. 7-11, 3)."""
        cfg = loss_config(config)
        with autocast(module, config.precision):
            y_local, y_global = td_targets(batch, module.actor_target, module.local_q_target, module.central_target, cfg)
            loss_l, stats = local_critic_loss(module.local_q, batch, y_local)
        grads: dict[str, Any] = {"local_critic": (loss_l, list(module.local_q.parameters()))}
        if module.central is not None:
            with autocast(module, config.precision):
                loss_g, g_stats = central_critic_loss(module.central, batch, y_global, cfg)
            grads["central_critic"] = (loss_g, list(module.central.parameters()))
            stats.update(g_stats)
        return grads, stats

    def actor_loss(self, module: Any, config: Any, batch: dict[str, Any]) -> tuple[torch.Tensor, dict[str, Any]]:
        """CIG-TD3's actor loss (Eq. 12) and its stats."""
        return actor_loss(module.actor, module.local_q, module.central, batch, loss_config(config))

    def _log_actor(self, module_id: str, loss: torch.Tensor, stats: dict[str, Any]) -> None:
        """Log the actor loss and its stats."""
        self.metrics.log_value((module_id, "actor_loss"), loss.detach(), window=1)
        for key, value in stats.items():
            self.metrics.log_value((module_id, key), value, window=1)

    def _gradients(self, grads: dict[str, tuple[torch.Tensor, list[torch.nn.Parameter]]]) -> dict[Any, torch.Tensor]:
        """Gradients of each loss w.r.t. its own network's parameters only, by parameter reference."""
        out: dict[Any, torch.Tensor] = {}
        for loss, params in grads.values():
            for p, g in zip(params, torch.autograd.grad(loss, params, allow_unused=True)):
                if g is not None:
                    out[self.get_param_ref(p)] = g
        return out

    def compute_gradients(self, loss_per_module: dict[str, torch.Tensor], **kwargs: Any) -> dict[Any, torch.Tensor]:
        """Gradients of each loss w.r.t. its own network's parameters only.

        With ``update_order="critic_first"`` (TD3, official COIN code) the critics step here first;
        the actor loss is then computed on the updated critics and only the actor's gradients are
        returned for RLlib's optimizer step.
        """
        for optim in self._optimizer_parameters:
            optim.zero_grad(set_to_none=True)
        out: dict[Any, torch.Tensor] = {}
        for grads in self._grads.values():
            out.update(self._gradients(grads))
        self._grads = {}
        if self._actor_losses:
            self.apply_gradients(out)  # the critic step (the actor has no gradient yet, so its optimizer skips it)
            for optim in self._optimizer_parameters:
                optim.zero_grad(set_to_none=True)
            out = {}
            for module_id, objective in self._actor_losses.items():
                loss_pi, pi_stats = objective()
                self._log_actor(module_id, loss_pi, pi_stats)
                out.update(self._gradients({"actor": (loss_pi, list(self.module[module_id].unwrapped().actor.parameters()))}))
            self._actor_losses = {}
        return out

    def apply_gradients(self, gradients_dict: dict[Any, torch.Tensor]) -> None:
        """RLlib's optimizer steps, with one finiteness check over all gradients instead of two per tensor.

        RLlib's ``TorchLearner.apply_gradients`` checks every gradient twice, each check a host
        sync: about 300 syncs per update for these networks, a large share of a small update's
        time. When every gradient is finite (one check) the result is the same as RLlib's: the
        gradients are set and every optimizer steps. Otherwise, or with grad scalers or lr
        scheduler classes, RLlib's own method runs (its warning, zeroed non-finite gradients).
        """
        if not gradients_dict or self._grad_scalers is not None or self._lr_scheduler_classes is not None:
            return super().apply_gradients(gradients_dict)
        if not bool(torch.isfinite(torch.cat([g.reshape(-1) for g in gradients_dict.values()])).all()):
            return super().apply_gradients(gradients_dict)
        for pid, grad in gradients_dict.items():
            self._params[pid].grad = grad
        for optimizer in self._named_optimizers.values():
            optimizer.step()
        return None

    def after_gradient_based_update(self, *, timesteps: dict[str, Any]) -> None:
        """Count the update; on policy steps soft-update every target network."""
        super().after_gradient_based_update(timesteps=timesteps)
        for module_id, module in self.module.items():
            config = self.config.get_config_for_module(module_id)
            if self.is_policy_step(config):
                for main_net, target_net in module.unwrapped().get_target_network_pairs():
                    soft_update(main_net, target_net, config.tau)
                self.metrics.log_value((module_id, "num_target_updates"), 1, reduce="lifetime_sum")
        self.num_updates += 1

    def get_state(self, *args: Any, **kwargs: Any) -> dict[str, Any]:
        """Learner state plus the update counter, target networks and torch RNG, the CUDA one too on a GPU (exact resume)."""
        state = super().get_state(*args, **kwargs)
        state["cig_td3"] = {
            "num_updates": self.num_updates,
            "torch_rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state(self._device) if self._device.type == "cuda" else None,
            "targets": {
                mid: {name: None if net is None else _cpu_state(net) for name, net in m.unwrapped().target_networks().items()}
                for mid, m in self.module.items()
            },
        }
        return state

    def set_state(self, state: dict[str, Any]) -> None:
        """Restore learner state saved by :meth:`get_state`."""
        super().set_state(state)
        for optimizer in self._named_optimizers.values():  # a checkpoint from before the fused step brings fused=None
            for group in optimizer.param_groups:
                group["fused"], group["foreach"] = True, None
        extra = state.get("cig_td3")
        if extra:
            self.num_updates = int(extra["num_updates"])
            torch.set_rng_state(extra["torch_rng"])
            if extra.get("cuda_rng") is not None and self._device.type == "cuda":
                torch.cuda.set_rng_state(extra["cuda_rng"], self._device)
            for mid, targets in extra["targets"].items():
                nets = self.module[mid].unwrapped().target_networks()
                for name, saved in targets.items():
                    if saved is not None:
                        nets[name].load_state_dict(saved)
