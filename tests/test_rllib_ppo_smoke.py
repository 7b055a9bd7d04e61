"""Smoke test: RLlib's own PPO (new API stack) trains one shared module on the respawning env."""

import math

import pytest
from fixtures import NO_BRAKES
from ray.rllib.algorithms.ppo import PPOConfig
from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig

from coin_app.adapters.rllib_env import register_envs
from coin_app.algorithms.common import policy_mapping_fn

NUM_AGENTS = 4
# Cars without brakes or rolling resistance: under a random initial policy some leave the
# road or crash within a few steps and are replaced mid-episode (delay_done=0), so the
# PPO run sees agents that appear during an episode, not only the initial ones.
RESPAWN_CONFIG = {"num_agents": NUM_AGENTS, "horizon": 30, "max_agent_steps": 30, "delay_done": 0, "dynamics": NO_BRAKES}
# Normal cars barely move under a random policy, so all four time out together at step 20
# while replacements spawn in that step: every episode ends through the adapter's "every
# acting agent is done" rule, which drops the replacements.
TOGETHER_CONFIG = {"num_agents": NUM_AGENTS, "horizon": 40, "max_agent_steps": 20, "delay_done": 0}
TRAIN_BATCH = 200


@pytest.fixture(scope="module", autouse=True)
def envs():
    register_envs()


@pytest.mark.parametrize("case", ["respawn", "together"])
def test_ppo_trains_shared_module_for_two_iterations(ray_session, case):
    env_config = RESPAWN_CONFIG if case == "respawn" else TOGETHER_CONFIG
    config = (
        PPOConfig()
        .environment("coin-intersection-v0", env_config=env_config)
        .env_runners(num_env_runners=0, rollout_fragment_length=100)
        .training(train_batch_size_per_learner=TRAIN_BATCH, minibatch_size=100, num_epochs=1)
        .multi_agent(policies={"shared"}, policy_mapping_fn=policy_mapping_fn)
        .rl_module(model_config=DefaultModelConfig(fcnet_hiddens=[32, 32]))
        .debugging(seed=0)
    )
    algo = config.build_algo()
    try:
        sampled = []
        for _ in range(2):
            result = algo.train()
            sampled.append(result["env_runners"]["num_env_steps_sampled_lifetime"])
            learner = result["learners"]["shared"]
            for key in ("total_loss", "policy_loss", "vf_loss", "entropy", "mean_kl_loss"):
                assert math.isfinite(float(learner[key])), (key, learner[key])
            assert learner["num_module_steps_trained"] > 0
            assert set(result["learners"]) == {"shared", "__all_modules__"}
            assert result["env_runners"]["num_episodes"] > 0  # episodes did end (and reset)
        assert sampled[0] >= TRAIN_BATCH and sampled[1] >= sampled[0] + TRAIN_BATCH
        runners = result["env_runners"]
        per_agent = runners["num_agent_steps_sampled_lifetime"]
        # every agent's steps went through the one shared module
        assert runners["num_module_steps_sampled_lifetime"] == {"shared": sum(per_agent.values())}
        if case == "respawn":  # agents that spawned mid-episode were sampled too
            assert any(int(aid.removeprefix("agent")) >= NUM_AGENTS for aid in per_agent), sorted(per_agent)
        else:  # only the initial agents, 20 steps each per episode; the replacements were dropped
            assert set(per_agent) == {f"agent{i}" for i in range(NUM_AGENTS)}
            assert runners["episode_len_mean"] == 20
            assert set(per_agent.values()) == {sampled[1]}
    finally:
        algo.stop()
