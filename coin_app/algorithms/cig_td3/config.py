"""``CigTd3Config``: every CIG-TD3 hyper-parameter, documented, with the paper's defaults.

Defaults follow the COIN paper (§5.1) and ``shared/reference/decisions.md``; where the
official code differs, its value is noted. ``global_critic=False`` is ITD3, the independent
TD3 baseline with parameter sharing (``CigTd3Config.itd3()``).
"""

from __future__ import annotations

from typing import Any

from ray.rllib.algorithms.algorithm_config import AlgorithmConfig, NotProvided
from ray.rllib.core.rl_module.rl_module import RLModuleSpec

from coin_app.adapters.rllib_env import ENV_IDS
from coin_app.algorithms.common import SHARED_MODULE_ID, backend_errors, policy_mapping_fn, scenario_config_of
from coin_app.sim.config import ScenarioConfig
from coin_app.sim.road_map import load_map
from coin_app.sim.simulator import MAX_RESPAWN_PER_STEP

LOCAL_MODULES = ("cvae", "attention", "none")
GLOBAL_MODULES = ("gat", "gcn", "graphsage", "none")

# name -> (default, meaning); the single source of the documentation and of training() kwargs
HYPERPARAMETERS: dict[str, tuple[Any, str]] = {
    "actor_lr": (2e-4, "Adam learning rate of the actor (paper; official code 1e-4)"),
    "critic_lr": (3e-4, "Adam learning rate of the twin local critics"),
    "central_critic_lr": (3e-4, "Adam learning rate of the centralized critic: twin global Q, baseline V and CVAE (official 2e-4)"),
    "tau": (0.005, "soft target update rate of actor, local and global critics"),
    "policy_delay": (5, "actor and target updates every this many critic updates (official code 3)"),
    "exploration_noise": (0.05, "std of the Gaussian noise added to actions while collecting"),
    "target_noise": (0.1, "std of the target-policy smoothing noise (Eq. 8)"),
    "target_noise_clip": (0.5, "clip of the target-policy smoothing noise"),
    "warmup_steps": (30_000, "env steps with uniform random actions before the policy acts (official code)"),
    "replay_capacity": (1_000_000, "agent transitions kept in the joint-step replay buffer"),
    "updates_per_env_step": (1.0, "gradient updates per sampled env step (official: one per env step)"),
    "global_critic": (True, "use the centralized critic (False = ITD3)"),
    "counterfactual_baseline": (True, "subtract the counterfactual baseline V in the actor loss (Eq. 12)"),
    "local_module": ("cvae", "pairwise interaction module: cvae | attention (Table B.1) | none (w/o VAE)"),
    "global_module": ("gat", "global interaction module: gat | gcn | graphsage | none (w/o GAT: mean-pool)"),
    "graph": ("full", "'full' graph, or a radius in metres for a sparse graph (Tables B.2/B.3: 40)"),
    "global_weight": (1.0, "weight of the global term in the actor loss (paper 1.0; official 0.8)"),
    "vae_weight": (1.0, "weight of the CVAE loss in the centralized-critic loss (official 0.01)"),
    "kl_beta": (1.0, "weight of the KL term inside the CVAE loss"),
    "hidden": (256, "width of actor, local-critic and CVAE layers"),
    "latent_dim": (20, "CVAE latent size"),
    "node_width": (128, "GAT node feature width"),
    "learner_threads": (2, "torch threads for updates in the training process (2 cores here; use 1 if env runners share the cores)"),
    "eval_every": (25, "training iterations between deterministic evaluations on validation seeds (0 = off)"),
    "eval_episodes": (5, "validation episodes (seeds) per periodic evaluation"),
}


class CigTd3Config(AlgorithmConfig):
    """Configuration of CIG-TD3 (and ITD3) on RLlib's new API stack."""

    def __init__(self, algo_class: type | None = None):
        from coin_app.algorithms.cig_td3.algorithm import CigTd3

        super().__init__(algo_class=algo_class or CigTd3)
        for name, (default, _) in HYPERPARAMETERS.items():
            setattr(self, name, default)
        self.gamma = 0.99
        self.train_batch_size_per_learner = 256
        self.rollout_fragment_length = 1
        self.min_sample_timesteps_per_iteration = 500
        self.lr = None  # separate optimizers; see actor_lr, critic_lr, central_critic_lr
        self.multi_agent(policies={SHARED_MODULE_ID}, policy_mapping_fn=policy_mapping_fn)  # parameter sharing

    def training(self, **kwargs: Any) -> CigTd3Config:
        """Set training options; CIG-TD3 keys are those of ``HYPERPARAMETERS``, the rest go to RLlib."""
        own = {k: kwargs.pop(k) for k in list(kwargs) if k in HYPERPARAMETERS}
        super().training(**kwargs)
        for name, value in own.items():
            if value is not NotProvided:
                setattr(self, name, value)
        return self

    def itd3(self) -> CigTd3Config:
        """Switch to ITD3: no centralized critic, only the individual twin critics."""
        return self.training(global_critic=False, counterfactual_baseline=False, local_module="none", global_module="none", vae_weight=0.0)

    # ---------------------------------------------------------------- env facts
    def scenario_config(self) -> ScenarioConfig:
        """The scenario config this algorithm trains on (from ``env`` and ``env_config``; native or MetaDrive backend)."""
        return scenario_config_of(self)

    @property
    def max_others(self) -> int:
        """Padded number of other agents per transition: everyone who can be present at t+1."""
        return self.scenario_config().num_agents + MAX_RESPAWN_PER_STEP

    # ---------------------------------------------------------------- validation
    def validate(self) -> None:
        """Refuse bad values and invalid ablation combinations before any work starts."""
        super().validate()
        errors = []
        if self.local_module not in LOCAL_MODULES:
            errors.append(f"local_module={self.local_module!r}; allowed: {' | '.join(LOCAL_MODULES)}")
        if self.global_module not in GLOBAL_MODULES:
            errors.append(f"global_module={self.global_module!r}; allowed: {' | '.join(GLOBAL_MODULES)}")
        if not (self.graph == "full" or (isinstance(self.graph, (int, float)) and not isinstance(self.graph, bool) and self.graph > 0)):
            errors.append(f"graph={self.graph!r}; allowed: 'full' or a radius in metres > 0")
        for name in ("actor_lr", "critic_lr", "central_critic_lr", "tau", "updates_per_env_step"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not v > 0:
                errors.append(f"{name}={v!r}; allowed: a number > 0")
        for name in ("exploration_noise", "target_noise", "target_noise_clip", "global_weight", "vae_weight", "kl_beta"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or v < 0:
                errors.append(f"{name}={v!r}; allowed: a number >= 0")
        for name in ("policy_delay", "hidden", "latent_dim", "node_width", "replay_capacity", "eval_episodes", "learner_threads"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                errors.append(f"{name}={v!r}; allowed: an integer >= 1")
        if not isinstance(self.eval_every, int) or self.eval_every < 0:
            errors.append(f"eval_every={self.eval_every!r}; allowed: an integer >= 0 (0 = off)")
        if not isinstance(self.warmup_steps, int) or self.warmup_steps < 0:
            errors.append(f"warmup_steps={self.warmup_steps!r}; allowed: an integer >= 0")
        if not self.tau <= 1:
            errors.append(f"tau={self.tau!r}; allowed: 0 < tau <= 1")
        # ablation combinations
        if not self.global_critic:
            if self.counterfactual_baseline:
                errors.append("counterfactual_baseline=True needs global_critic=True (ITD3 has no global critic; use .itd3())")
            if self.local_module != "none" or self.global_module != "none":
                errors.append(
                    "local_module/global_module configure the global critic; with global_critic=False set both to 'none' (.itd3())"
                )
            if self.vae_weight > 0:
                errors.append("vae_weight > 0 needs global_critic=True (the CVAE lives in the global critic)")
        elif self.local_module != "cvae" and self.vae_weight > 0:
            errors.append(f"vae_weight={self.vae_weight} but local_module={self.local_module!r} has no CVAE; set vae_weight=0")
        if self.graph != "full" and self.global_module == "none":
            errors.append("a sparse graph radius needs a graph module (gat | gcn | graphsage), not global_module='none'")
        if self.num_learners != 0:
            errors.append(f"num_learners={self.num_learners}; CIG-TD3 runs its learner in the algorithm process (num_learners=0)")
        try:
            self.scenario_config()
        except ValueError as exc:
            errors.append(str(exc))
        errors += backend_errors(self)
        if errors:
            raise ValueError("invalid CIG-TD3 config: " + "; ".join(errors))

    # ---------------------------------------------------------------- RLlib wiring
    def get_default_rl_module_spec(self) -> RLModuleSpec:
        """The CIG-TD3 torch RLModule."""
        from coin_app.algorithms.cig_td3.rl_module import CigTd3TorchRLModule

        return RLModuleSpec(module_class=CigTd3TorchRLModule)

    def get_default_learner_class(self) -> type:
        """The CIG-TD3 torch Learner."""
        from coin_app.algorithms.cig_td3.learner import CigTd3TorchLearner

        return CigTd3TorchLearner

    @property
    def _model_config_auto_includes(self) -> dict[str, Any]:
        """Hyper-parameters the RLModule needs to build its networks and exploration."""
        scenario = self.scenario_config() if isinstance(self.env, str) and self.env in ENV_IDS else None
        return super()._model_config_auto_includes | {
            "hidden": self.hidden,
            "latent_dim": self.latent_dim,
            "node_width": self.node_width,
            "global_critic": self.global_critic,
            "counterfactual_baseline": self.counterfactual_baseline,
            "local_module": self.local_module,
            "global_module": self.global_module,
            "graph_radius": None if self.graph == "full" else float(self.graph),
            "position_scale": load_map(scenario.scenario).scale if scenario else 1.0,
            "exploration_noise": self.exploration_noise,
            "warmup_steps": self.warmup_steps,
        }
