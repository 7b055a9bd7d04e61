"""IPPO's learner batch on a hand-built three-vehicle episode against GAE computed by hand (issue 56).

One vehicle crashes (terminated), one reaches its own step limit (truncated by the env) and one is
cut by the end of the sampling chunk. Every real row's value target and standardized advantage must
be the hand-computed GAE (gamma 0.99, lambda 0.95): the crash and, by default, the time-out
bootstrap with 0 (Ray 1.x), the chunk cut with V(o_T); with ``timeout_bootstrap`` the time-out
bootstraps with V(o_T) too. The stored actions reach the loss unclipped (many lie outside [-1, 1]),
and the loss's log-probability of them under the acting weights is the stored one.
"""

import uuid
from collections import defaultdict

import gymnasium as gym
import numpy as np
import pytest
import torch
from ray.rllib.core.columns import Columns
from ray.rllib.env.single_agent_episode import SingleAgentEpisode
from ray.rllib.env.utils.infinite_lookback_buffer import InfiniteLookbackBuffer
from ray.rllib.evaluation.postprocessing import Postprocessing

from coin_app.adapters.episodes import OrderedMultiAgentEpisode
from coin_app.algorithms.common import SHARED_MODULE_ID
from coin_app.training import build_config

GAMMA, LAMBDA = 0.99, 0.95
SETTINGS = {"num_agents": 3, "horizon": 40, "max_agent_steps": 40, "hidden": 16}
SETTINGS |= {"train_batch_size_per_learner": 40, "rollout_fragment_length": 20, "minibatch_size": 20}
# agent, rewards, terminated, truncated
VEHICLES = (
    ("agent0", [1.0, 1.0, 1.0, -10.0], True, False),  # crash in its 4th step
    ("agent1", [0.5] * 5, False, True),  # its own step limit
    ("agent2", [2.0, 2.0, 2.0], False, False),  # still driving at the chunk's end
)


def hand_gae(rewards: np.ndarray, values: np.ndarray, bootstrap: float) -> np.ndarray:
    """Raw GAE advantages of one vehicle's rows; ``values`` has one more entry than ``rewards`` (unused: ``bootstrap``)."""
    n = len(rewards)
    next_values = np.append(values[1:n], bootstrap)
    delta = rewards + GAMMA * next_values - values[:n]
    adv, running = np.zeros(n), 0.0
    for t in reversed(range(n)):
        running = delta[t] + GAMMA * LAMBDA * running
        adv[t] = running
    return adv


@pytest.mark.parametrize("timeout_bootstrap", [False, True])
def test_value_targets_advantages_and_log_probs_of_a_hand_built_episode(timeout_bootstrap):
    cfg = build_config("ippo", "intersection", {**SETTINGS, "timeout_bootstrap": timeout_bootstrap}, 0)
    obs_space = gym.spaces.Box(0.0, 1.0, (91,), np.float32)
    act_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    learner = cfg.build_learner(spaces={SHARED_MODULE_ID: (obs_space, act_space)})
    module = learner.module[SHARED_MODULE_ID].unwrapped()
    torch.manual_seed(0)
    with torch.no_grad():  # values and log stds far from their initial ~0
        for p in module.parameters():
            p.add_(0.3 * torch.randn_like(p))
    rng = np.random.default_rng(0)
    agents, data = {}, {}
    for aid, rewards, terminated, truncated in VEHICLES:
        n = len(rewards)
        obs = rng.uniform(0.0, 1.0, (n + 1, 91)).astype(np.float32)
        actions = (2.0 * rng.standard_normal((n, 2))).astype(np.float32)
        with torch.no_grad():
            inputs = module.forward_exploration({Columns.OBS: torch.from_numpy(obs[:n])})[Columns.ACTION_DIST_INPUTS]
            logp = module.get_exploration_action_dist_cls().from_logits(inputs).logp(torch.from_numpy(actions)).numpy()
        data[aid] = (obs, actions, np.array(rewards, np.float32), terminated, truncated, logp)
        agents[aid] = SingleAgentEpisode(
            id_=uuid.uuid4().hex,
            observations=InfiniteLookbackBuffer(obs),
            infos=InfiniteLookbackBuffer([{}] * (n + 1)),
            actions=InfiniteLookbackBuffer(actions),
            rewards=InfiniteLookbackBuffer(np.array(rewards, np.float32)),
            extra_model_outputs={
                Columns.ACTION_LOGP: InfiniteLookbackBuffer(logp),
                Columns.ACTION_DIST_INPUTS: InfiniteLookbackBuffer(inputs.numpy()),
            },
            terminated=terminated,
            truncated=truncated,
            t_started=0,
            len_lookback_buffer=0,
            agent_id=aid,
            module_id=SHARED_MODULE_ID,
            multi_agent_episode_id="ep0",
        )
    episode = OrderedMultiAgentEpisode(id_="ep0", env_t_started=0, agent_to_module_mapping_fn=cfg.policy_mapping_fn)
    episode.env_t = max(len(r) for _, r, _, _ in VEHICLES)
    episode.agent_episodes = agents
    episode._agent_to_module_mapping = dict.fromkeys(agents, SHARED_MODULE_ID)
    episode.agent_t_started = defaultdict(int, dict.fromkeys(agents, 0))

    batch = learner._learner_connector(rl_module=learner.module, batch={}, episodes=[episode], shared_data={})[SHARED_MODULE_ID]

    real = batch[Columns.LOSS_MASK].numpy().astype(bool)
    targets, advantages, row = [], [], 0
    for obs, actions, rewards, terminated, truncated, _ in data.values():  # the batch's order: agents sorted by id
        n = len(rewards)
        with torch.no_grad():
            values = module.compute_values({Columns.OBS: torch.from_numpy(obs)}).numpy()
        bootstrap = 0.0 if terminated or (truncated and not timeout_bootstrap) else float(values[n])
        adv = hand_gae(rewards, values, bootstrap)
        targets.append(adv + values[:n])
        advantages.append(adv)
        np.testing.assert_array_equal(batch[Columns.OBS].numpy()[row : row + n], obs[:n])
        np.testing.assert_array_equal(batch[Columns.ACTIONS].numpy()[row : row + n], actions)  # unclipped
        row += n + 1  # RLlib's one bootstrap row per vehicle
    assert row == len(real)
    np.testing.assert_allclose(batch[Postprocessing.VALUE_TARGETS].numpy()[real], np.concatenate(targets), atol=1e-5)
    raw = np.concatenate(advantages)
    np.testing.assert_allclose(batch[Postprocessing.ADVANTAGES].numpy()[real], (raw - raw.mean()) / raw.std(), atol=1e-5)

    stored = np.concatenate([d[5] for d in data.values()])
    assert (np.abs(np.concatenate([d[1] for d in data.values()])) > 1.0).any(axis=1).mean() > 0.5
    mask = torch.from_numpy(real)
    with torch.no_grad():
        inputs = module.forward_train(batch)[Columns.ACTION_DIST_INPUTS][mask]
    logp = module.get_train_action_dist_cls().from_logits(inputs).logp(batch[Columns.ACTIONS][mask]).numpy()
    np.testing.assert_allclose(logp, stored, rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(batch[Columns.ACTION_LOGP].numpy()[real], stored, atol=0)
