"""CIG-TD3 Algorithm: sample -> joint-step replay -> learner updates -> weight sync.

Each ``training_step``: the env runners sample ``rollout_fragment_length`` env steps
(uniform random actions during the warm-up, from the module's seeded exploration), the
episodes are turned into per-agent transitions and added to the joint-step replay buffer
(the centralized-critic connector: it attaches the other agents' states, actions and next
observations by env step at sample time), then ``updates_per_env_step`` gradient updates per
sampled env step run on batches of ``train_batch_size_per_learner`` transitions, and the
actor weights go back to the env runners. The buffer, its RNG and the update credit are
part of the algorithm's checkpoint state, so a resumed run continues exactly.
"""

from __future__ import annotations

from typing import Any

import torch
from ray.rllib.algorithms.algorithm import Algorithm
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

from coin_app.adapters.rllib_env import register_envs
from coin_app.algorithms.cig_td3.config import CigTd3Config
from coin_app.algorithms.cig_td3.replay import JointStepReplayBuffer, episodes_to_transitions
from coin_app.algorithms.cig_td3.rl_module import STATE_DIM
from coin_app.algorithms.common import SHARED_MODULE_ID
from coin_app.sim.seeds import validation_seeds

REPLAY_STATE_KEY = "cig_td3_replay"


class CigTd3(Algorithm):
    """Counterfactual individual-global TD3 (COIN) with a shared policy for all agents."""

    @classmethod
    def get_default_config(cls) -> CigTd3Config:
        """A default ``CigTd3Config``."""
        return CigTd3Config()

    def setup(self, config: CigTd3Config) -> None:
        """Register the envs, build runners and learners, then the seeded joint-step buffer."""
        register_envs()
        torch.set_num_threads(config.learner_threads)
        super().setup(config)
        scen = self.config.scenario_config()
        seed = 0 if self.config.seed is None else int(self.config.seed)
        self.replay = JointStepReplayBuffer(
            capacity=self.config.replay_capacity,
            obs_dim=scen.obs_dim,
            state_dim=STATE_DIM,
            act_dim=2,
            max_others=self.config.max_others,
            seed=seed,
            # one step entry per env step: with few agents there are nearly as many steps as transitions
            step_capacity=max(self.config.replay_capacity // 2 + 64, self.config.replay_capacity // max(1, scen.num_agents - 1)),
        )
        self._update_credit = 0.0
        self._num_updates = 0

    def training_step(self) -> None:
        """One sample -> replay -> update(s) -> sync cycle."""
        cfg = self.config
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
        lifetime = self.metrics.peek((ENV_RUNNER_RESULTS, NUM_ENV_STEPS_SAMPLED_LIFETIME), default=0)
        batch_size = cfg.train_batch_size_per_learner
        if lifetime < cfg.warmup_steps or len(self.replay) < batch_size:
            return
        self._update_credit += env_steps * cfg.updates_per_env_step
        n_updates = int(self._update_credit)
        self._update_credit -= n_updates
        for _ in range(n_updates):
            with self.metrics.log_time((TIMERS, REPLAY_BUFFER_SAMPLE_TIMER)):
                sample = self.replay.sample(batch_size)
            batch = MultiAgentBatch({SHARED_MODULE_ID: SampleBatch(sample)}, env_steps=batch_size)
            with self.metrics.log_time((TIMERS, LEARNER_UPDATE_TIMER)):
                results = self.learner_group.update(
                    batch=batch,
                    timesteps={
                        NUM_ENV_STEPS_SAMPLED_LIFETIME: lifetime,
                        NUM_AGENT_STEPS_SAMPLED_LIFETIME: self.metrics.peek(
                            (ENV_RUNNER_RESULTS, NUM_AGENT_STEPS_SAMPLED_LIFETIME), default=0
                        ),
                    },
                )
            self.metrics.aggregate(results, key=LEARNER_RESULTS)
        done_before, self._num_updates = self._num_updates, self._num_updates + n_updates
        if done_before // cfg.policy_delay != self._num_updates // cfg.policy_delay:  # the actor changed
            with self.metrics.log_time((TIMERS, SYNCH_WORKER_WEIGHTS_TIMER)):
                self.env_runner_group.sync_weights(
                    from_worker_or_learner_group=self.learner_group, policies=[SHARED_MODULE_ID], inference_only=True
                )

    def step(self) -> dict[str, Any]:
        """One training iteration, plus the periodic deterministic evaluation on validation seeds."""
        results = super().step()
        every = self.config.eval_every
        if every and (self.iteration + 1) % every == 0:
            results["coin_eval"] = self.evaluate_actor(validation_seeds(self.config.eval_episodes))
        return results

    def evaluate_actor(self, seeds: list[int]) -> dict[str, float]:
        """Mean of the six metrics (and counts) of the current deterministic actor over ``seeds``."""
        from coin_app.algorithms.registry import evaluate_algorithm

        return evaluate_algorithm(self, seeds)

    # ------------------------------------------------------------------ checkpoints
    def get_state(self, *args: Any, **kwargs: Any) -> dict[str, Any]:
        """Algorithm state plus the replay buffer (RLlib's new stack leaves it out)."""
        state = super().get_state(*args, **kwargs)
        state[REPLAY_STATE_KEY] = {
            "buffer": self.replay.get_state(),
            "update_credit": self._update_credit,
            "num_updates": self._num_updates,
        }
        return state

    def set_state(self, state: dict[str, Any]) -> None:
        """Restore the algorithm and its replay buffer."""
        super().set_state(state)
        extra = state.get(REPLAY_STATE_KEY)
        if extra is not None:
            self.replay.set_state(extra["buffer"])
            self._update_credit = float(extra["update_credit"])
            self._num_updates = int(extra["num_updates"])
