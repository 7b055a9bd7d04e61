"""The critic probe (``coin_app probe``) against critics whose preferences are known by construction."""

import math

import numpy as np
import pytest
import torch
from torch import nn

from coin_app.evaluation.critic_probe import env_mates, probe_stopped
from coin_app.sim.config import ScenarioConfig

CONFIG = ScenarioConfig(scenario="intersection", num_agents=3, horizon=40, max_agent_steps=40)


class Brake(nn.Module):
    """Straight ahead at full brake, whatever it observes: every vehicle stops and stays stopped."""

    def forward(self, obs):
        return torch.tensor([0.0, -1.0]).expand(len(obs), 2).clone()


class ThrottleQ(nn.Module):
    """Q^l_1(o, a) = the throttle: the individual critic prefers driving on."""

    def q1_only(self, obs, act):
        return act[:, 1]


class BrakeGlobalQ(nn.Module):
    """Q^G_1 = 3 x the brake + the number of others: the global critic prefers braking, three times as strongly."""

    def q1(self, obs, state, action, others_state, others_action, mask):
        assert others_state.shape[:2] == mask.shape and bool((others_action[~mask] == 0).all())
        return -3.0 * action[:, 1] + mask.sum(1)


def test_env_mates_lists_every_other_vehicle_of_each_rows_env_nearest_first_and_pads():
    pos = np.array([[0.0, 0.0], [5.0, 0.0], [3.0, 0.0], [1.0, 0.0], [9.0, 9.0]])
    take, mask = env_mates(pos, np.array([0, 1, 0, 0, 2]))  # env 0: rows 0, 2, 3; env 1: row 1 alone; env 2: row 4 alone
    assert mask.tolist() == [[True, True], [False, False], [True, True], [True, True], [False, False]]
    assert take[0].tolist() == [3, 2] and take[2].tolist() == [3, 0] and take[3].tolist() == [0, 2]  # nearest first
    assert take[1].tolist() == [0, 0] and take[4].tolist() == [0, 0]  # pads point at row 0, masked
    take, mask = env_mates(pos[:2], np.array([0, 1]))  # one vehicle per env: one empty slot each
    assert take.shape == mask.shape == (2, 1) and not mask.any()


def test_probe_reports_the_individual_critics_preference_for_driving_on():
    probe = probe_stopped(Brake(), ThrottleQ(), None, CONFIG, [200000, 200001])
    assert probe.stopped_steps > 0 and probe.stopped_steps <= probe.vehicle_steps
    assert probe.policy_action.tolist() == [0.0, -1.0] and probe.policy_q_local == -1.0
    t = probe.table.set_index("throttle")
    assert t["q_local"].tolist() == [-1.0, 0.0, 0.5, 1.0]  # Q^l = the throttle put in
    # a throttle above the policy's full brake beats it at every stopped vehicle-step; the brake itself never does
    assert t["local_prefers"].tolist() == [0.0, 1.0, 1.0, 1.0] and t["objective_prefers"].tolist() == [0.0, 1.0, 1.0, 1.0]
    assert all(math.isnan(x) for x in t["global_prefers"]) and math.isnan(probe.policy_q_global)
    assert np.isnan(probe.policy_preact_abs).all()  # this actor has no pre-tanh output


def test_probe_reports_the_actors_pre_tanh_magnitude():
    class PreBrake(Brake):
        def preactivation(self, obs):
            return torch.tensor([0.5, -3.0]).expand(len(obs), 2)

        def forward(self, obs):
            return torch.tanh(self.preactivation(obs))

    probe = probe_stopped(PreBrake(), ThrottleQ(), None, CONFIG, [200000])
    assert probe.policy_preact_abs.tolist() == pytest.approx([0.5, 3.0])
    assert probe.policy_action.tolist() == pytest.approx([math.tanh(0.5), math.tanh(-3.0)], abs=1e-6)  # float32


def test_probe_weighs_the_global_critic_as_the_actor_does():
    probe = probe_stopped(Brake(), ThrottleQ(), BrakeGlobalQ(), CONFIG, [200000, 200001], global_weight=1.0)
    t = probe.table.set_index("throttle")
    assert t["global_prefers"].tolist() == [0.0, 0.0, 0.0, 0.0]  # the global critic: nothing beats full brake
    # objective at throttle x: x - 3x = -2x (plus the same count of others) against the brake's +2: braking wins
    assert t["objective_prefers"].tolist() == [0.0, 0.0, 0.0, 0.0] and t["local_prefers"].tolist() == [0.0, 1.0, 1.0, 1.0]
    light = probe_stopped(Brake(), ThrottleQ(), BrakeGlobalQ(), CONFIG, [200000, 200001], global_weight=0.2)
    # x - 0.6x = 0.4x against -0.4: every throttle above the brake wins
    assert light.table["objective_prefers"].tolist() == [0.0, 1.0, 1.0, 1.0]


@pytest.mark.parametrize(("kwargs", "message"), [({"speed_below": 0.0}, "bad speed_below 0.0"), ({"throttles": [2.0]}, "bad throttles")])
def test_probe_refuses_bad_input(kwargs, message):
    with pytest.raises(ValueError, match=message):
        probe_stopped(Brake(), ThrottleQ(), None, CONFIG, [200000], **kwargs)


def test_the_global_critic_sees_every_other_vehicle_of_the_egos_env_and_not_the_ego():
    """3 braking vehicles per env (none leaves): every stopped row has exactly 2 others, none at the ego's position (normalised)."""
    seen = []

    class Record(nn.Module):
        def q1(self, obs, state, action, others_state, others_action, mask):
            seen.append((mask.sum(1), (others_state[..., :2] - state[:, None, :2]).norm(dim=-1)[mask]))
            return torch.zeros(len(obs))

    probe = probe_stopped(Brake(), ThrottleQ(), Record(), CONFIG, [200000, 200001])
    counts = torch.cat([c for c, _ in seen])
    assert len(counts) == probe.stopped_steps * (1 + len(probe.table)) and bool((counts == 2).all())
    assert float(torch.cat([d for _, d in seen]).min()) > 1e-3  # another vehicle (normalised positions), never the ego (0)


def test_probe_with_one_vehicle_per_env_gives_the_global_critic_an_empty_masked_slot():
    alone = ScenarioConfig(scenario="intersection", num_agents=1, horizon=40, max_agent_steps=40)
    probe = probe_stopped(Brake(), ThrottleQ(), BrakeGlobalQ(), alone, [200000])
    assert probe.stopped_steps > 0
    # Q^G = -3 x the throttle + 0 others: at the policy's full brake exactly 3 (BrakeGlobalQ also checks masked slots are zero)
    assert probe.policy_q_global == 3.0 and probe.table.set_index("throttle").loc[1.0, "q_global"] == -3.0
