"""The TD3 family's base on RLlib's new API stack, ITD3 as it is: config, algorithm and spec in one file (as RLlib's ``sac.py``).

``Td3Config`` holds the TD3 hyper-parameters every member of the family takes, declared once in
``settings.py`` (``Td3Settings``) with COIN's defaults (COIN §5.1: "consistent with TD3" for ITD3, TraCo and
COIN; where the official code differs, its value is noted, and ``docs/decisions.md`` §2.1 says which
side coin_app follows). ITD3 is this config as it is: independent TD3 with parameter sharing.
CIG-TD3 (``cig_td3/``) and TraCo (``traco/``) subclass the config, the module and the learner and add
their critics, as RLlib's TQC extends SAC.

``Td3`` runs sample -> joint-step replay -> learner updates -> weight sync. Each
``training_step``: the env runners sample ``rollout_fragment_length`` env steps, a chunk of K
(uniform random actions during the warm-up, from the module's seeded exploration), the episodes are turned into
per-agent transitions and added to the joint-step replay buffer, then ``updates_per_env_step`` gradient updates
per sampled env step past the warm-up run on batches of ``train_batch_size_per_learner`` transitions
(:func:`update_schedule`: the updates, their env-step clocks and the credit of K single steps; a local learner's
metrics reduced once per training step; the learner's connector, ``connector.JointState``, gathers the other
agents' states, actions and next observations and the global reward from the replay's joint records by env
step), and, when an update moved the actor (the
learner's update counter crossed a multiple of ``policy_delay``), the actor weights go back to the
env runners. The buffer, its RNG and the update credit are part of the algorithm's checkpoint
state, so a resumed run continues exactly. The replay stays in the algorithm process; the learner
runs there too (``num_learners=0``) or as one remote learner actor that each sampled batch is
sent to with the joint records' rows written since the previous update (``num_learners=1``; more
would need more than one replay), on a GPU with
``num_gpus_per_learner=1``. ``precision="bf16"`` runs the learner's loss forward passes in
bfloat16 (``learner.py``).

``ITD3``, its :class:`~coin_app.algorithms.spec.AlgorithmSpec` entry, is in ``settings.py``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar

import torch
from ray.rllib.algorithms.algorithm import Algorithm
from ray.rllib.algorithms.algorithm_config import AlgorithmConfig, NotProvided
from ray.rllib.core.rl_module.rl_module import RLModuleSpec
from ray.rllib.execution.rollout_ops import synchronous_parallel_sample
from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch
from ray.rllib.utils.metrics import (
    ENV_RUNNER_RESULTS,
    ENV_RUNNER_SAMPLING_TIMER,
    LEARNER_RESULTS,
    LEARNER_UPDATE_TIMER,
    NUM_AGENT_STEPS_SAMPLED_LIFETIME,
    NUM_ENV_STEPS_SAMPLED_LIFETIME,
    REPLAY_BUFFER_ADD_DATA_TIMER,
    REPLAY_BUFFER_SAMPLE_TIMER,
    SYNCH_WORKER_WEIGHTS_TIMER,
    TIMERS,
)

from coin_app.adapters.rllib_env import ENV_IDS, env_config_of, register_envs
from coin_app.algorithms.common import (
    SHARED_MODULE_ID,
    ProgressReporting,
    backend_errors,
    policy_mapping_fn,
    scenario_config_of,
    set_on_envs,
)
from coin_app.algorithms.td3.buffer import JointStepReplayBuffer
from coin_app.algorithms.td3.learner import Td3TorchLearner
from coin_app.algorithms.td3.rl_module import Td3TorchRLModule
from coin_app.algorithms.td3.settings import RLLIB_KEYS, Td3Settings
from coin_app.algorithms.td3.transitions import episodes_to_transitions
from coin_app.sim import schema
from coin_app.sim.config import ScenarioConfig
from coin_app.sim.road_map import load_map
from coin_app.sim.scenarios import scenario_name
from coin_app.sim.simulator import MAX_RESPAWN_PER_STEP


class Td3Config(AlgorithmConfig):
    """Configuration of TD3 with parameter sharing (ITD3) on RLlib's new API stack; the base of every TD3-family config."""

    SETTINGS: ClassVar[type[Td3Settings]] = Td3Settings  # this config's settings (children have theirs)
    LABEL: ClassVar[str] = "ITD3"  # the name in error messages

    def __init__(self, algo_class: type | None = None):
        super().__init__(algo_class=algo_class or Td3)
        for name, value in self.SETTINGS().values().items():  # every setting at its declared default, RLlib's keys too
            setattr(self, name, value)
        self.min_sample_timesteps_per_iteration = 500
        self.lr = None  # one optimizer per network; see actor_lr, critic_lr (and the children's rates)
        self.multi_agent(policies={SHARED_MODULE_ID}, policy_mapping_fn=policy_mapping_fn)  # parameter sharing
        # the learner gets replay batches, never episodes: its connector pipeline is JointState alone (learner.py)
        self.add_default_connectors_to_learner_pipeline = False

    def training(self, **kwargs: Any) -> Td3Config:
        """Set training options; this algorithm's keys are its ``SETTINGS``' own (not RLlib's), the rest go to RLlib."""
        own = {k: kwargs.pop(k) for k in list(kwargs) if k in self.SETTINGS.keys() and k not in RLLIB_KEYS}
        super().training(**kwargs)
        for name, value in own.items():
            if value is not NotProvided:
                setattr(self, name, value)
        return self

    # ---------------------------------------------------------------- env facts
    def scenario_config(self) -> ScenarioConfig:
        """The scenario config this algorithm trains on: the typed one ``env_config`` carries (parsed once), or parsed from overrides."""
        return scenario_config_of(self)

    @property
    def max_others(self) -> int:
        """Padded number of other agents per transition: everyone who can be present at t+1."""
        return self.scenario_config().num_agents + MAX_RESPAWN_PER_STEP

    # ---------------------------------------------------------------- validation
    def validate(self) -> None:
        """Refuse bad values and invalid combinations before any work starts."""
        super().validate()
        errors = self.SETTINGS.value_errors({key: getattr(self, key) for key in self.SETTINGS.keys()})  # types, ranges, choices
        if errors:  # the combinations below assume well-typed values
            raise ValueError(f"invalid {self.LABEL} config: " + "; ".join(errors))
        errors = self.combination_errors()
        if self.num_learners > 1:
            errors.append(
                f"num_learners={self.num_learners}; allowed: 0 (local learner) or 1 (one remote learner: one replay, one learner)"
            )
        try:
            errors += self.curriculum_errors(self.scenario_config())
        except ValueError as exc:
            errors.append(str(exc))
        errors += backend_errors(self)
        if errors:
            raise ValueError(f"invalid {self.LABEL} config: " + "; ".join(errors))

    def curriculum_errors(self, scenario: ScenarioConfig) -> list[str]:
        """One line per invalid curriculum setting on ``scenario`` (both keys set or neither; fewer vehicles; native simulator)."""
        agents, steps = self.curriculum_agents, self.curriculum_steps
        if (agents > 0) != (steps > 0):
            return [f"curriculum_agents={agents} with curriculum_steps={steps}; allowed: both > 0 (a curriculum) or both 0 (none)"]
        if agents == 0:
            return []
        errors = []
        if agents >= scenario.num_agents:
            errors.append(f"curriculum_agents={agents}; allowed: 1 to {scenario.num_agents - 1} (fewer than the scenario's num_agents)")
        if scenario.backend != "native":
            errors.append(f"curriculum_agents={agents} with backend {scenario.backend!r}; allowed: a curriculum on backend 'native'")
        return errors

    def curriculum_phase(self, env_steps: int) -> int:
        """Vehicles at reset for episodes started after ``env_steps`` lifetime env steps (the scenario's after the first phase)."""
        if self.curriculum_agents > 0 and env_steps < self.curriculum_steps:
            return self.curriculum_agents
        return self.scenario_config().num_agents

    def combination_errors(self) -> list[str]:
        """One line per invalid combination of well-typed keys (none in TD3; the children's switches have theirs)."""
        return []

    # ---------------------------------------------------------------- RLlib wiring
    def get_default_rl_module_spec(self) -> RLModuleSpec:
        """The TD3 torch RLModule."""
        return RLModuleSpec(module_class=Td3TorchRLModule)

    def get_default_learner_class(self) -> type:
        """The TD3 torch Learner."""
        return Td3TorchLearner

    @property
    def _model_config_auto_includes(self) -> dict[str, Any]:
        """The model-config entries of every TD3-family module: widths, map scale, exploration and warm-up (children add theirs)."""
        scenario = self.scenario_config() if isinstance(self.env, str) and self.env in ENV_IDS else None
        return super()._model_config_auto_includes | {
            "hidden": self.hidden,
            "actor_layers": self.actor_layers,
            "critic_feature_norm": self.critic_feature_norm,
            "position_scale": load_map(scenario.scenario).scale if scenario else 1.0,
            "exploration_noise": self.exploration_noise,
            "exploration_noise_initial": self.exploration_noise_initial,
            "exploration_noise_decay_steps": self.exploration_noise_decay_steps,
            "exploration_noise_decay_start": self.exploration_noise_decay_start,
            "warmup_steps": self.warmup_steps,
        }


REPLAY_STATE_KEY = "cig_td3_replay"  # the algorithm-state key of the replay (the name checkpoints have carried from the start)


class Td3(ProgressReporting, Algorithm):
    """TD3 with a shared policy for all agents (ITD3) on the joint-step replay; the base of CIG-TD3 and TraCo."""

    @classmethod
    def get_default_config(cls) -> Td3Config:
        """A default ``Td3Config``."""
        return Td3Config()

    def setup(self, config: Td3Config) -> None:
        """Register the envs, build runners and learners, then the seeded joint-step buffer."""
        register_envs()
        torch.set_num_threads(config.learner_threads)
        super().setup(config)
        scen = self.config.scenario_config()
        seed = 0 if self.config.seed is None else int(self.config.seed)
        self.replay = JointStepReplayBuffer(
            capacity=self.config.replay_capacity,
            obs_dim=scen.obs_dim,
            state_dim=schema.STATE_DIM,
            act_dim=schema.ACT_DIM,
            max_others=self.config.max_others,
            seed=seed,
            # one step entry per env step: with few agents there are nearly as many steps as transitions
            step_capacity=max(self.config.replay_capacity // 2 + 64, self.config.replay_capacity // max(1, scen.num_agents - 1)),
        )
        self._update_credit = 0.0
        self._phase_sent: tuple[int, int] | None = None  # (vehicles, iteration) the env runners were last given the curriculum
        learner = getattr(self.learner_group, "_learner", None)  # None when the learner is a remote actor
        if learner is not None:  # the learner connector reads the replay's joint records in place
            learner.joint_state.records = self.replay
        self._joint_written: tuple[int, int] | None = None  # the replay's write counts a remote learner's copy is current with

    def training_step(self) -> None:
        """One sample -> replay -> update(s) -> sync cycle: ``rollout_fragment_length`` env steps, then their updates."""
        cfg = self.config
        self._sync_env_steps()
        self._set_curriculum_phase()
        self.report_progress("sampling", 0, 0)
        with self.metrics.log_time((TIMERS, ENV_RUNNER_SAMPLING_TIMER)):
            episodes, runner_results = synchronous_parallel_sample(
                worker_set=self.env_runner_group,
                concat=True,
                sample_timeout_s=cfg.sample_timeout_s,
                _uses_new_env_runners=True,
                _return_metrics=True,
            )
        self.metrics.aggregate(runner_results, key=ENV_RUNNER_RESULTS)
        with self.metrics.log_time((TIMERS, REPLAY_BUFFER_ADD_DATA_TIMER)):
            self.replay.add(episodes_to_transitions(episodes))
        env_steps = sum(len(e) for e in episodes)
        lifetime = int(self.metrics.peek((ENV_RUNNER_RESULTS, NUM_ENV_STEPS_SAMPLED_LIFETIME), default=0))
        batch_size = cfg.train_batch_size_per_learner
        if lifetime < cfg.warmup_steps or len(self.replay) < batch_size:  # the chunk is all warm-up, or no batch yet
            return
        schedule, self._update_credit = update_schedule(
            lifetime - env_steps, env_steps, cfg.warmup_steps, cfg.updates_per_env_step, self._update_credit
        )
        n_updates = len(schedule)
        agent_steps = self.metrics.peek((ENV_RUNNER_RESULTS, NUM_AGENT_STEPS_SAMPLED_LIFETIME), default=0)
        local = self.learner_group.is_local
        for i, env_step in enumerate(schedule):
            self.report_progress("updates", i, n_updates)
            with self.metrics.log_time((TIMERS, REPLAY_BUFFER_SAMPLE_TIMER)):
                sample = self.replay.sample(batch_size)
            batch = MultiAgentBatch({SHARED_MODULE_ID: SampleBatch(sample)}, env_steps=batch_size)
            last = i == n_updates - 1  # a local learner reduces its metrics once, after the step's last update
            with self.metrics.log_time((TIMERS, LEARNER_UPDATE_TIMER)):
                results = self.learner_group.update(
                    batch=batch,
                    timesteps={NUM_ENV_STEPS_SAMPLED_LIFETIME: env_step, NUM_AGENT_STEPS_SAMPLED_LIFETIME: agent_steps},
                    **({} if last or not local else {"_no_metrics_reduce": True}),
                    **self.joint_delta(),
                )
            if last or not local:
                self.metrics.aggregate(results, key=LEARNER_RESULTS)
        self.report_progress("updates", n_updates, n_updates)
        if n_updates:
            updates = self.learner_updates()
            if (updates - n_updates) // cfg.policy_delay != updates // cfg.policy_delay:  # a policy step: the actor changed
                with self.metrics.log_time((TIMERS, SYNCH_WORKER_WEIGHTS_TIMER)):
                    self._sync_actor()

    def _set_curriculum_phase(self) -> None:
        """Give every env runner the curriculum's vehicle count for its next episodes when the phase changes, and once an
        iteration (a runner RLlib restarted starts at the scenario's count); no curriculum: nothing."""
        if self.config.curriculum_agents == 0:
            return
        lifetime = int(self.metrics.peek((ENV_RUNNER_RESULTS, NUM_ENV_STEPS_SAMPLED_LIFETIME), default=0))
        agents = self.config.curriculum_phase(lifetime)
        sent = (agents, self.iteration)
        if sent != self._phase_sent:
            self.env_runner_group.foreach_env_runner(lambda runner: set_on_envs(runner, "set_num_agents", agents), local_env_runner=True)
            self._phase_sent = sent
        self.metrics.log_value("curriculum_agents", agents, window=1)

    def joint_delta(self) -> dict[str, Any]:
        """The learner update's keyword for a remote learner: the replay's joint records written since the last update ({} if local)."""
        if self.learner_group.is_local:
            return {}
        delta = self.replay.joint_delta(self._joint_written)
        self._joint_written = delta["written"]
        return {"joint_delta": delta}

    def learner_updates(self) -> int:
        """The learner's update counter (``Td3TorchLearner.num_updates``, checkpointed with the learner), local or remote."""
        learner = getattr(self.learner_group, "_learner", None)  # None when the learner is a remote actor
        if learner is not None:
            return int(learner.num_updates)
        return int(next(iter(self.learner_group.foreach_learner(lambda remote: remote.num_updates))).get())

    def _sync_actor(self) -> None:
        """Give the env runners the learner's actor weights: copied in place when learner and runner share this process.

        With no remote env runner and a local learner (``num_learners=0``, the reduced protocol), RLlib's
        ``sync_weights`` would still build the module's state, put it into Ray's object store and load it
        back (a training step takes 0.925x the time without it: ``benchmarks/weight_sync.py``); the in-place
        copy gives the runner the same weights bit for bit (RLlib's DreamerV3 reaches the local learner's
        module the same way).
        """
        learner = getattr(self.learner_group, "_learner", None)  # None when the learner is a remote actor
        runner = self.env_runner
        if learner is not None and runner is not None and self.env_runner_group.num_remote_env_runners() == 0:
            copy_weights(learner.module[SHARED_MODULE_ID].unwrapped(), runner.module[SHARED_MODULE_ID].unwrapped())
            return
        self.sync_actor_through_rllib()

    def sync_actor_through_rllib(self) -> None:
        """RLlib's own weight sync of the actor to every env runner (module state -> object store -> load)."""
        self.env_runner_group.sync_weights(
            from_worker_or_learner_group=self.learner_group, policies=[SHARED_MODULE_ID], inference_only=True
        )

    def _sync_env_steps(self) -> None:
        """Give the env runners the exact lifetime env-step count before they sample (an exact warm-up boundary).

        RLlib syncs the runners' count only at the end of an iteration, so exploration's ``t``
        would otherwise lag by up to an iteration (the whole first one uniform random).
        """
        lifetime = int(self.metrics.peek((ENV_RUNNER_RESULTS, NUM_ENV_STEPS_SAMPLED_LIFETIME), default=0))
        if self.env_runner_group.num_remote_env_runners() == 0:
            self.env_runner.num_env_steps_sampled_lifetime = lifetime
        else:
            self.env_runner_group.sync_env_runner_states(config=self.config, env_steps_sampled=lifetime)

    # ------------------------------------------------------------------ checkpoints
    def get_state(self, *args: Any, **kwargs: Any) -> dict[str, Any]:
        """Algorithm state plus the replay buffer (RLlib's new stack leaves it out)."""
        state = super().get_state(*args, **kwargs)
        state[REPLAY_STATE_KEY] = {
            "buffer": self.replay.get_state() if self.config.checkpoint_replay else None,
            "update_credit": self._update_credit,
        }
        return state

    def set_state(self, state: dict[str, Any]) -> None:
        """Restore the algorithm and its replay buffer (an older checkpoint's update count here is unused: the learner has its own)."""
        super().set_state(state)
        extra = state.get(REPLAY_STATE_KEY)
        if extra is not None:
            if extra["buffer"] is not None:  # None: saved with checkpoint_replay=False, the buffer starts empty
                self.replay.set_state(extra["buffer"])
                self._joint_written = None  # a remote learner's copy of the joint records is sent again in full
            self._update_credit = float(extra["update_credit"])


def update_schedule(lifetime: int, env_steps: int, warmup_steps: int, ratio: float, credit: float) -> tuple[list[int], float]:
    """The updates ``env_steps`` new env steps earn after ``lifetime`` earlier ones, and the credit left.

    Env step ``t`` (1-based lifetime count) earns ``ratio`` updates once ``t >= warmup_steps``, the
    fractions carried in ``credit``; each update is labelled with the count ``t`` of the env step
    that earned it (its learner's env-step clock). Step by step as one env step per training step
    would: a chunk of K steps gets the updates, the labels and the credit of K single steps.
    """
    schedule: list[int] = []
    for t in range(max(lifetime + 1, warmup_steps), lifetime + env_steps + 1):
        credit += ratio
        n = int(credit)
        credit -= n
        schedule += [t] * n
    return schedule, credit


def copy_weights(source: torch.nn.Module, dest: torch.nn.Module) -> None:
    """Copy each of ``dest``'s parameters and buffers from ``source``'s of the same name, in place (any devices)."""
    with torch.no_grad():
        for name, tensor in dest.named_parameters():
            tensor.copy_(source.get_parameter(name))
        for name, tensor in dest.named_buffers():
            tensor.copy_(source.get_buffer(name))


def config_builder(config_class: type[Td3Config]) -> Callable[[ScenarioConfig, dict[str, Any], int], Td3Config]:
    """The spec builder of a TD3-family config class: a validated config on a parsed scenario."""

    def build(scenario: ScenarioConfig, algo_cfg: dict[str, Any], seed: int) -> Td3Config:
        """A validated ``config_class`` config on the parsed ``scenario``."""
        cfg = config_class().environment(f"coin-{scenario_name(scenario)}-v0", env_config=env_config_of(scenario)).debugging(seed=seed)
        cfg = cfg.env_runners(
            num_env_runners=algo_cfg.pop("num_env_runners", 0), rollout_fragment_length=algo_cfg.pop("rollout_fragment_length", 1)
        )
        cfg = cfg.evaluation(evaluation_interval=None)
        return cfg.training(**algo_cfg)

    return build


build_itd3_config = config_builder(Td3Config)  # ITD3's spec (td3/settings.py) names it
