"""The TD3 family's chunked loop: K = ``rollout_fragment_length`` env steps per training step, then the updates K single steps earn.

``update_schedule`` is checked against hand-computed credits and against K single steps; a tiny CIG-TD3 then runs
chunks of 4 env steps across the warm-up boundary and must do exactly the hand-computed updates, each on the env-step
clock of the step that earned it, with its metrics reduced once per training step and none lost.
"""

import numpy as np
import pytest
import torch
from fixtures import tiny

from coin_app.algorithms.td3.td3 import update_schedule
from coin_app.training import build_config

torch.set_num_threads(1)


@pytest.mark.parametrize(
    "args,want",
    [
        # warm-up 10, one update per env step: steps 9..12, of which 10, 11, 12 are past the warm-up
        ((8, 4, 10, 1.0, 0.0), ([10, 11, 12], 0.0)),
        # half an update per step from step 10: 10 -> 0.5, 11 -> 1.0 (an update), 12 -> 0.5, 13 -> 1.0 (an update)
        ((9, 4, 10, 0.5, 0.0), ([11, 13], 0.0)),
        # 2.5 per step, 0.25 carried in: 21 -> 2.75 (2 updates, 0.75 left), 22 -> 3.25 (3 updates, 0.25 left)
        ((20, 2, 0, 2.5, 0.25), ([21, 21, 22, 22, 22], 0.25)),
        # the whole chunk inside the warm-up: nothing, the credit untouched
        ((0, 4, 5, 1.0, 0.5), ([], 0.5)),
        # one step (K = 1), the step that reaches the warm-up's count earns its update (as the loop always did)
        ((29, 1, 30, 1.0, 0.0), ([30], 0.0)),
    ],
)
def test_update_schedule_by_hand(args, want):
    schedule, credit = update_schedule(*args)
    assert (schedule, credit) == (want[0], pytest.approx(want[1], abs=1e-12))


@pytest.mark.parametrize("ratio", [0.1, 0.3, 1.0, 1.7, 4.0])
def test_a_chunk_earns_what_its_single_steps_earn(ratio):
    rng = np.random.default_rng(int(ratio * 10))
    chunks = rng.integers(1, 9, 40).tolist()
    lifetime, credit, chunked = 0, 0.0, []
    for k in chunks:
        got, credit = update_schedule(lifetime, k, 50, ratio, credit)
        chunked += got
        lifetime += k
    single_credit, single = 0.0, []
    for t in range(lifetime):
        got, single_credit = update_schedule(t, 1, 50, ratio, single_credit)
        single += got
    assert chunked == single and credit == single_credit
    assert len(single) == int((lifetime - 49) * ratio + 1e-9)  # ratio updates per step from step 50 on, up to the fraction


@pytest.mark.usefixtures("ray_session")
def test_a_training_step_samples_k_env_steps_then_their_updates():
    # 3 vehicles on the bottleneck fill the 16-transition batch long before the warm-up's 30 env steps
    _, settings = tiny(
        "cig_td3", "bottleneck", eval_every=0, warmup_steps=30, rollout_fragment_length=4, updates_per_env_step=0.5, policy_delay=2
    )
    algo = build_config("cig_td3", "bottleneck", settings, 0).build_algo()
    clocks: list[int] = []
    update = algo.learner_group.update
    algo.learner_group.update = lambda *a, **k: clocks.append(k["timesteps"]["num_env_steps_sampled_lifetime"]) or update(*a, **k)
    learner = algo.learner_group._learner
    per_step = []
    for _ in range(10):
        before = len(clocks)
        algo.training_step()
        per_step.append((algo.env_runner.num_env_steps_sampled_lifetime, clocks[before:]))
    # chunks end at 4, 8, ..., 40; steps 30..40 earn half an update each: 31, 33, 35, 37, 39 (hand-computed)
    assert per_step == [(4 * (i + 1), []) for i in range(7)] + [(32, [31]), (36, [33, 35]), (40, [37, 39])]
    assert learner.num_updates == 5 and algo._update_credit == 0.5
    # the learner's metrics were reduced once per training step and lost nothing: target updates at updates 2 and 4
    assert algo.metrics.peek(("learners", "shared", "num_target_updates")) == 2
    algo.stop()


@pytest.mark.usefixtures("ray_session")
def test_a_chunk_across_the_warmup_switches_to_the_policy_at_its_step():
    # chunks of 8 env steps: the one of stamps 32..39 holds the warm-up's end at 37; no updates (the batch never fills), no noise
    _, settings = tiny(
        "cig_td3",
        "bottleneck",
        eval_every=0,
        warmup_steps=37,
        exploration_noise=0.0,
        train_batch_size_per_learner=100_000,
        horizon=100,
        max_agent_steps=100,
        rollout_fragment_length=8,
    )
    algo = build_config("cig_td3", "bottleneck", settings, 0).build_algo()
    for _ in range(6):
        algo.training_step()
    assert algo.env_runner.num_env_steps_sampled_lifetime == 48
    sample = algo.replay.sample(len(algo.replay))
    with torch.no_grad():
        policy = algo.get_module("shared").actor(torch.as_tensor(sample["obs"])).numpy()
    gap, steps = np.abs(sample["actions"] - policy).max(axis=1), sample["env_step"]
    inside = (steps >= 32) & (steps < 40)  # the chunk across the boundary (0-based env steps 32..39)
    assert set(steps[inside & (steps >= 37)]) and set(steps[inside & (steps < 37)])
    assert gap[steps >= 37].max() < 1e-5  # the policy's action from the boundary (stamp 37) on, inside the chunk too
    assert np.median(gap[inside & (steps < 37)]) > 0.1  # uniform random before it
    algo.stop()
