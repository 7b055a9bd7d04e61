"""The TD3 family's Learner (ITD3's as it is): one update reads top to bottom, as CleanRL's ``td3_continuous_action.py``.

One update (:meth:`Td3TorchLearner.update_module`) on one sampled batch:
    1. the critics: TD targets from the target networks (no grad), then each critic's loss steps
       its own network only (TD3: the twin critic; children add theirs, ``critic_losses``);
    2. the delayed actor: every ``policy_delay``-th update (once ``actor_start_steps`` env steps
       past the warm-up), the actor loss on the critics just updated steps the actor only
       (``update_order="joint"``: the actor loss is taken before the critics step, and all step together);
    3. the targets: on the same ``policy_delay`` schedule, every target network moves by ``tau``.
Each loss's gradient is taken with ``torch.autograd.grad`` on its own network's parameters, so
nothing leaks into another network; an optimizer whose network got no gradient leaves it untouched.
``num_updates`` counts the updates: the policy-delay phase, and what the algorithm reads to give the
env runners a changed actor.

``precision="bf16"`` runs every loss's forward pass under ``torch.autocast(bfloat16)`` on the
module's device (``"auto"``: bf16 where that device multiplies bf16 natively, else fp32:
:func:`resolve_precision`); the losses widen the network outputs to fp32 (``losses.py``), so parameters,
gradients, Adam state, TD targets, loss reductions and soft updates stay fp32. Nothing here
creates a tensor on a fixed device, so the learner runs where RLlib puts its module
(``num_gpus_per_learner``), in the algorithm process or as one remote learner (``num_learners=1``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
from typing import Any

import torch
from ray.rllib.core.rl_module.apis import TargetNetworkAPI
from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch
from ray.rllib.utils.metrics import NUM_ENV_STEPS_SAMPLED_LIFETIME

from coin_app.algorithms.choices import TD3_PRECISIONS
from coin_app.algorithms.gradient_step import FastGradientStep, fused_adam
from coin_app.algorithms.td3.connector import JointState
from coin_app.algorithms.td3.losses import LossConfig, actor_loss, local_critic_loss, td_target

STATE_KEY = "cig_td3"  # the learner-state key of the counter, targets and RNG (the name checkpoints have carried from the start)

# {optimizer name: (loss, the network it trains)}: what one optimizer step takes
Losses = dict[str, tuple[torch.Tensor, torch.nn.Module]]


@functools.cache
def native_bf16(device: torch.device) -> bool:
    """Whether ``device`` multiplies bfloat16 matrices natively: a CUDA GPU with bf16 (compute capability 8.0 on), a CPU
    with oneDNN's bf16 kernels (AVX-512 or AMX); elsewhere bf16 runs on slow fallback kernels (docs/reference/speed.md)."""
    if device.type == "cuda":
        with torch.cuda.device(device):
            return torch.cuda.is_bf16_supported(including_emulation=False)
    if device.type == "cpu":
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    return False


def resolve_precision(precision: str, device: torch.device) -> str:
    """The precision an update on ``device`` runs in: ``precision`` itself, or for "auto" "bf16" if :func:`native_bf16`, else "fp32"."""
    if precision not in TD3_PRECISIONS:
        raise ValueError(f"precision={precision!r}; allowed: {' | '.join(TD3_PRECISIONS)}")
    if precision == "auto":
        return "bf16" if native_bf16(device) else "fp32"
    return precision


def autocast(module: torch.nn.Module, precision: str) -> contextlib.AbstractContextManager:
    """The context the loss forward passes of ``module`` run in: bfloat16 autocast on its device for "bf16" (or "auto"
    resolved to it, :func:`resolve_precision`), else nothing."""
    device = next(module.parameters()).device
    if resolve_precision(precision, device) == "fp32":
        return contextlib.nullcontext()
    return torch.autocast(device_type=device.type, dtype=torch.bfloat16)


def loss_config(config: Any) -> LossConfig:
    """The TD3 loss constants of a TD3-family config."""
    return LossConfig(
        gamma=config.gamma,
        target_noise=config.target_noise,
        target_noise_clip=config.target_noise_clip,
        preact_penalty=config.actor_preact_penalty,
        preact_threshold=config.actor_preact_threshold,
        timeout_bootstrap=config.timeout_bootstrap,
    )


def loss_fields(config: Any) -> dict[str, Any]:
    """The TD3 loss constants of a TD3-family config as keyword arguments (the children's loss configs extend them)."""
    return dataclasses.asdict(loss_config(config))


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


class Td3TorchLearner(FastGradientStep):
    """Torch learner of TD3 with parameter sharing (ITD3); CIG-TD3's and TraCo's extend its networks and losses."""

    def build(self) -> None:
        """Build module, optimizers and the connector pipeline (``JointState``), then the target networks (``learner_threads`` threads)."""
        torch.set_num_threads(self.config.learner_threads)  # also in a remote learner's own process
        super().build()
        self.joint_state = JointState()  # reads a copy of the replay's joint records until the algorithm gives it the replay
        self._learner_connector.append(self.joint_state)
        self.module.foreach_module(lambda mid, mod: mod.make_target_networks() if isinstance(mod, TargetNetworkAPI) else None)
        self.num_updates = 0
        self.env_steps = 0  # the lifetime env-step count of the current update (before_gradient_based_update)

    # ------------------------------------------------------------------ what the children extend
    def optimizer_groups(self, module: Any, config: Any) -> list[tuple[str, torch.nn.Module, float]]:
        """(optimizer name, network, learning rate) of every network this learner trains: the actor and the twin critic."""
        return [("actor", module.actor, config.actor_lr), ("local_critic", module.local_q, config.critic_lr)]

    def loss_config(self, module: Any, config: Any) -> LossConfig:
        """The loss constants of ``config`` for ``module``."""
        return loss_config(config)

    def critic_losses(self, module: Any, config: Any, batch: dict[str, Any]) -> tuple[Losses, dict[str, Any]]:
        """The critics' losses {optimizer name: (loss, network)} and their stats: TD3's y and L_Q (Eqs. 7-8)."""
        with autocast(module, config.precision):
            y = td_target(batch, module.actor_target, module.local_q_target, self.loss_config(module, config))
            loss, stats = local_critic_loss(module.local_q, batch, y)
        return {"local_critic": (loss, module.local_q)}, stats

    def actor_loss(self, module: Any, config: Any, batch: dict[str, Any]) -> tuple[torch.Tensor, dict[str, Any]]:
        """The actor's loss and its stats: TD3's L_pi (Eq. 12's individual term)."""
        return actor_loss(module.actor, module.local_q, batch, self.loss_config(module, config))

    # ------------------------------------------------------------------ one update
    def update_module(self, module_id: str, batch: dict[str, Any]) -> torch.Tensor:
        """The ``num_updates``-th update of ``module_id`` on ``batch``: critics, delayed actor, targets; the critics' summed loss."""
        module, config = self.module[module_id].unwrapped(), self.config.get_config_for_module(module_id)
        policy_step = self.num_updates % config.policy_delay == 0
        actor_learns = policy_step and self.env_steps >= config.warmup_steps + config.actor_start_steps
        joint = config.update_order == "joint"

        # 1. the critics, each on its own network
        critics, stats = self.critic_losses(module, config, batch)
        self.log(module_id, {f"{name}_loss": loss.detach() for name, (loss, _) in critics.items()} | stats)
        total = sum(loss.detach() for loss, _ in critics.values())
        if actor_learns and joint:  # the actor loss on the critics before their step; all step together
            critics["actor"] = (self.logged_actor_loss(module_id, module, config, batch), module.actor)
        self.step(critics)

        # 2. the delayed actor, on the critics just updated
        if actor_learns and not joint:
            self.step({"actor": (self.logged_actor_loss(module_id, module, config, batch), module.actor)})

        # 3. the targets, on the actor's schedule
        if policy_step:
            for main_net, target_net in module.get_target_network_pairs():
                soft_update(main_net, target_net, config.tau)
            self.metrics.log_value((module_id, "num_target_updates"), 1, reduce="lifetime_sum")
        return total

    def logged_actor_loss(self, module_id: str, module: Any, config: Any, batch: dict[str, Any]) -> torch.Tensor:
        """The actor's loss (under the configured precision), its value and stats logged."""
        with autocast(module, config.precision):
            loss, stats = self.actor_loss(module, config, batch)
        self.log(module_id, {"actor_loss": loss.detach()} | stats)
        return loss

    def step(self, losses: Losses) -> None:
        """One optimizer step on ``losses``: each loss's gradient w.r.t. its own network's parameters only."""
        for optim in self._optimizer_parameters:
            optim.zero_grad(set_to_none=True)
        grads: dict[Any, torch.Tensor] = {}
        for loss, net in losses.values():
            params = list(net.parameters())
            for p, g in zip(params, torch.autograd.grad(loss, params, allow_unused=True)):
                if g is not None:
                    grads[self.get_param_ref(p)] = g
        self.apply_gradients(self.postprocess_gradients(grads))

    def log(self, module_id: str, values: dict[str, Any]) -> None:
        """Log each value under ``(module_id, key)``, the last one of this update (window 1)."""
        for key, value in values.items():
            self.metrics.log_value((module_id, key), value, window=1)

    # ------------------------------------------------------------------ RLlib's hooks
    def update(self, *args: Any, joint_delta: Any = None, **kwargs: Any) -> Any:
        """RLlib's update; a remote learner's copy of the replay's joint records first takes ``joint_delta`` (new rows)."""
        if joint_delta is not None:
            self.joint_state.records.apply(joint_delta)
        return super().update(*args, **kwargs)

    def _make_batch_if_necessary(self, training_data: Any) -> Any:
        """The replay's batch through the learner connector pipeline (``JointState``), then RLlib's tensor conversion.

        RLlib runs the pipeline only on episodes; the family's learner gets replay batches. Without
        RLlib's per-piece timers (``metrics=None``): per update they cost more than the gather itself
        (``docs/decisions.md`` §6.4; ``benchmarks/offpolicy_step.py`` times the pipeline).
        """
        batch = training_data.batch
        if isinstance(batch, MultiAgentBatch) and self._learner_connector is not None:
            out = self._learner_connector(
                rl_module=self.module, batch=dict(batch.policy_batches), episodes=[], shared_data={}, metrics=None
            )
            rows = {mid: b if isinstance(b, SampleBatch) else SampleBatch(b) for mid, b in out.items()}
            training_data.batch = MultiAgentBatch(rows, env_steps=batch.env_steps())
        return super()._make_batch_if_necessary(training_data)

    def _uncompiled_update(self, batch: dict[str, Any], **kwargs: Any) -> tuple[Any, Any, dict[str, Any]]:
        """RLlib's step on one minibatch: count the update, then one TD3 update of each module (:meth:`update_module`)."""
        self._compute_off_policyness(batch)
        self.num_updates += 1
        return {}, {module_id: self.update_module(module_id, module_batch) for module_id, module_batch in batch.items()}, {}

    def compute_loss_for_module(self, *, module_id: str, config: Any, batch: dict[str, Any], fwd_out: dict[str, Any]) -> torch.Tensor:
        """Not used: a TD3 update takes several optimizer steps, so it runs in :meth:`update_module`."""
        raise NotImplementedError("a TD3-family learner computes its losses in update_module")

    def configure_optimizers_for_module(self, module_id: str, config: Any = None) -> None:
        """One Adam optimizer per network of :meth:`optimizer_groups`."""
        self.register_adam(module_id, self.optimizer_groups(self.module[module_id].unwrapped(), config))

    def register_adam(self, module_id: str, groups: list[tuple[str, torch.nn.Module, float]]) -> None:
        """One Adam optimizer per (name, network, learning rate) of ``groups``, on the config's decay schedule if any.

        Each steps with the fused kernel (``gradient_step.py``).
        """
        config = self.config.get_config_for_module(module_id)
        for name, net, lr in groups:
            params = self.get_parameters(net)
            optimizer = fused_adam(params)
            schedule = lr_schedule(lr, config)
            self.register_optimizer(
                module_id=module_id, optimizer_name=name, optimizer=optimizer, params=params, lr_or_lr_schedule=schedule
            )
            # RLlib starts a scheduled rate as a float32 tensor (its schedule's variable) until the first update's hook sets
            # the python float: the first step then rounds unlike a constant rate's. The schedule starts at lr, so a
            # decay leaves every update before it equal to the constant-rate run's, bit for bit (tested).
            for group in optimizer.param_groups:
                group["lr"] = float(lr)

    def before_gradient_based_update(self, *, timesteps: dict[str, Any]) -> None:
        """Remember the lifetime env-step count (the actor's start after the warm-up depends on it)."""
        super().before_gradient_based_update(timesteps=timesteps)
        self.env_steps = int(timesteps.get(NUM_ENV_STEPS_SAMPLED_LIFETIME, 0))

    # ------------------------------------------------------------------ checkpoints
    def get_state(self, *args: Any, **kwargs: Any) -> dict[str, Any]:
        """Learner state plus the update counter, target networks and torch RNG, the CUDA one too on a GPU (exact resume)."""
        state = super().get_state(*args, **kwargs)
        state[STATE_KEY] = {
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
        extra = state.get(STATE_KEY)
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
