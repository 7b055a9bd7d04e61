"""The parking stage's training options: the start-spread curriculum, the initial action std and the warm start (issue 23)."""

import numpy as np
import pytest
import torch
from ray.rllib.core.columns import Columns

from coin_app.algorithms.checkpoints import actor_policy
from coin_app.algorithms.nav_ppo.config import curriculum_difficulty
from coin_app.algorithms.nav_ppo.warm_start import (
    ROUND_SEED_STRIDE,
    Demonstrations,
    TeacherLabels,
    bc_loss,
    bc_weight,
    clone,
    heuristic_demonstrations,
    intervention_weights,
    warm_start,
)
from coin_app.sim.arena.config import make_arena_config
from coin_app.sim.arena.env import ArenaEnv
from coin_app.sim.arena.generator import generate, training_rng
from coin_app.sim.arena.heuristic import DRIVERS, avoiding_actions, heuristic_actions, planning_actions
from coin_app.sim.arena.simulator import ArenaSimulator
from coin_app.sim.dynamics import wrap_angle
from coin_app.training import build_config, fresh_module, with_env_runner


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_start_difficulty_narrows_the_same_draws(seed):
    lo, hi = 1.0, 7.5
    near = 1.0 + 0.7 * (2 * 1.25 - 1.0)  # the near end moved 70 % of the way out to twice the success distance
    full = generate(training_rng(seed), make_arena_config(generator="short", num_vehicles=1, num_obstacles=0))
    narrow = generate(training_rng(seed), make_arena_config(generator="short", num_vehicles=1, num_obstacles=0, start_difficulty=0.3))
    np.testing.assert_allclose(narrow.targets, full.targets)  # the targets are drawn before the starts: unchanged
    d_full = np.linalg.norm(full.starts[:, :2] - full.targets[:, :2], axis=1)
    d_narrow = np.linalg.norm(narrow.starts[:, :2] - narrow.targets[:, :2], axis=1)
    u = (d_full - lo) / (hi - lo)  # the uniform draw behind the full spread's distance
    np.testing.assert_allclose(d_narrow, near + 0.3 * (hi - near) * u, atol=1e-9)  # U(near, near + d (hi - near)) from the same u
    e_full = wrap_angle(full.starts[:, 2] - full.targets[:, 2])
    np.testing.assert_allclose(wrap_angle(narrow.starts[:, 2] - narrow.targets[:, 2]), 0.3 * e_full, atol=1e-9)
    # the same direction from the target
    u_full = (full.starts[:, :2] - full.targets[:, :2]) / d_full[:, None]
    np.testing.assert_allclose((narrow.starts[:, :2] - narrow.targets[:, :2]) / d_narrow[:, None], u_full, atol=1e-9)


def _start_distances(difficulty: float, vehicles: int, layouts: int = 200) -> np.ndarray:
    cfg = make_arena_config(generator="short", num_vehicles=vehicles, num_obstacles=0, start_difficulty=difficulty)
    rng = training_rng(11)
    return np.concatenate(
        [np.linalg.norm((lay.starts - lay.targets)[:, :2], axis=1) for lay in (generate(rng, cfg) for _ in range(layouts))]
    )


def test_low_spreads_never_start_inside_the_success_region():
    # one vehicle (no spacing, no widening): U(a, b), a = 1 + 0.95 * 1.5 = 2.425 m, b = a + 0.05 * (7.5 - a) = 2.67875 m
    one = _start_distances(0.05, vehicles=1)
    assert one.min() >= 2.425 - 1e-9 and one.max() <= 2.67875 + 1e-9
    assert np.median(one) == pytest.approx((2.425 + 2.67875) / 2, abs=0.02)
    # four vehicles: a crowded draw may widen only the far end, so the near end still holds
    assert _start_distances(0.05, vehicles=4).min() >= 2.425 - 1e-9 > 1.25  # beyond the success distance
    # the full spread keeps the generator's near end of 1 m
    full = _start_distances(1.0, vehicles=1)
    assert full.min() >= 1.0 - 1e-9 and full.min() < 1.1 and full.max() <= 7.5 + 1e-9


def test_start_difficulty_one_is_the_unchanged_generator_and_bad_values_are_refused():
    a = generate(training_rng(7), make_arena_config(generator="short", num_vehicles=4, num_obstacles=3))
    b = generate(training_rng(7), make_arena_config(generator="short", num_vehicles=4, num_obstacles=3, start_difficulty=1.0))
    for x, y in ((a.starts, b.starts), (a.targets, b.targets), (a.obstacles, b.obstacles)):
        np.testing.assert_array_equal(x, y)
    env = ArenaEnv(make_arena_config(generator="short", num_vehicles=2))
    env.set_start_difficulty(0.5)
    assert env.config.start_difficulty == 0.5
    for bad in (0.0, 1.5, float("nan")):
        with pytest.raises(ValueError, match=r"bad arena value start_difficulty=.*; allowed: a number in \(0, 1\]"):
            env.set_start_difficulty(bad)


def test_curriculum_rises_linearly_and_stops_at_one():
    assert [curriculum_difficulty(s, 1000, 0.2) for s in (0, 250, 500, 1000, 5000)] == pytest.approx([0.2, 0.4, 0.6, 1.0, 1.0])
    assert curriculum_difficulty(10, 0, 0.2) == 1.0  # no curriculum: the full spread


def test_curriculum_settings_are_checked_before_any_work():
    cfg = build_config("nav_ppo", "arena", {"stage": "short", "curriculum_steps": 1000, "curriculum_start": 0.25}, 0)
    assert cfg.env_config["scenario_config"].start_difficulty == 0.25  # the first iteration samples at the start spread
    assert cfg.learner_config_dict["curriculum_steps"] == 1000
    with pytest.raises(ValueError, match="curriculum_steps=1000 narrows the short stage's starts; allowed with stage=short"):
        build_config("nav_ppo", "arena", {"stage": "long", "curriculum_steps": 1000}, 0)
    with pytest.raises(ValueError, match=r"bad value for 'curriculum_start': 0; allowed"):
        build_config("nav_ppo", "arena", {"stage": "short", "curriculum_steps": 1000, "curriculum_start": 0}, 0)
    with pytest.raises(ValueError, match=r"bad value for 'log_std_init': 9; allowed"):
        build_config("nav_ppo", "arena", {"log_std_init": 9}, 0)


def test_log_std_init_shifts_only_the_initial_log_std():
    obs = torch.as_tensor(np.random.default_rng(0).normal(size=(16, 13)), dtype=torch.float32)
    outs = {}
    for shift in (0.0, -1.5):
        torch.manual_seed(3)
        module = fresh_module("nav_ppo", "arena", {"hidden": 16, "log_std_init": shift}, seed=3)
        with torch.no_grad():
            outs[shift] = module.forward_inference({Columns.OBS: obs})[Columns.ACTION_DIST_INPUTS]
    np.testing.assert_allclose(outs[-1.5][:, :2], outs[0.0][:, :2], atol=1e-6)  # the means are untouched
    np.testing.assert_allclose(outs[-1.5][:, 2:] - outs[0.0][:, 2:], -1.5, atol=1e-5)  # std e^-1.5 ~ 0.22 times the default


def test_log_std_min_floors_the_log_std_in_every_forward_pass_and_nothing_else():
    obs = torch.as_tensor(np.random.default_rng(1).normal(size=(32, 13)), dtype=torch.float32)
    outs = {}
    for floor in (None, -1.0):
        torch.manual_seed(4)
        module = fresh_module("nav_ppo", "arena", {"hidden": 16, "log_std_init": 0.0, "log_std_min": floor}, seed=4)
        with torch.no_grad():
            head = module.pi.net.mlp[-1]
            head.bias[2:] = torch.tensor([-3.0, 0.5])  # steering's log std far below the floor, the pedal's above it
            outs[floor] = {
                name: fwd({Columns.OBS: obs})[Columns.ACTION_DIST_INPUTS]
                for name, fwd in (("inference", module.forward_inference), ("exploration", module.forward_exploration))
            }
            outs[floor]["train"] = module.forward_train({Columns.OBS: obs})[Columns.ACTION_DIST_INPUTS]
    for name, raw in outs[None].items():
        floored = outs[-1.0][name]
        np.testing.assert_allclose(floored[:, :2], raw[:, :2], atol=1e-6)  # the means are untouched
        expected = np.maximum(raw[:, 2:].numpy(), -1.0)  # max(log std, floor), per entry
        np.testing.assert_allclose(floored[:, 2:], expected, atol=1e-6)
        assert (raw[:, 2] < -1.0).float().mean() > 0.5  # the floor really binds on steering for most rows
    with pytest.raises(ValueError, match=r"log_std_min=-0.5 is above log_std_init=-1.5; allowed: a floor at most log_std_init"):
        build_config("nav_ppo", "arena", {"log_std_init": -1.5, "log_std_min": -0.5}, 0)
    with pytest.raises(ValueError, match=r"bad value for 'log_std_min': nan; allowed"):
        build_config("nav_ppo", "arena", {"log_std_min": float("nan")}, 0)


def test_a_curriculum_run_moves_every_env_to_the_scheduled_spread(ray_session):
    overrides = {
        "stage": "short",
        "curriculum_steps": 800,
        "curriculum_start": 0.2,
        "train_batch_size_per_learner": 400,
        "minibatch_size": 200,
        "num_epochs": 1,
        "hidden": 16,
        "max_steps": 60,
    }
    cfg = build_config("nav_ppo", "arena", overrides, 0)
    cfg = with_env_runner(cfg, "batched", 2, True, cfg.env_config["scenario_config"])
    algo = cfg.build_algo()
    try:
        seen = []
        for _ in range(3):
            algo.train()
            seen.append([env.config.start_difficulty for env in algo.env_runner.vector_env.envs])
    finally:
        algo.stop()
    # set before each iteration from the env steps sampled so far: 0, 400, 800 of 800
    assert seen == [[0.2, 0.2], [pytest.approx(0.6), pytest.approx(0.6)], [1.0, 1.0]]


def test_demonstrations_label_each_driven_state_with_the_driver_and_its_discounted_return():
    cfg = make_arena_config(generator="short", num_vehicles=2, num_obstacles=1, max_steps=120)
    demos = heuristic_demonstrations(cfg, episodes=1, seed=5, noise=0.3, gamma=0.9)  # episode 0 is driven without noise
    # the same scenario, driven independently through the dict env
    env = ArenaEnv(cfg)
    env.reset(seed=5)
    layout = env.draw_layout()
    obs, _ = env.reset(options={"layout": layout})
    rewards = {a: [] for a in obs}
    first_obs = np.stack([obs[a] for a in sorted(obs)])
    while env.agents:
        obs, rew, _, _, _ = env.step({a: heuristic_actions(o[None])[0] for a, o in obs.items()})
        for a, r in rew.items():
            rewards[a].append(r)
    assert len(demos.obs) == sum(len(r) for r in rewards.values())  # one row per vehicle and step it drove
    np.testing.assert_allclose(demos.obs[:2], first_obs, atol=1e-6)
    np.testing.assert_allclose(demos.actions[:2], heuristic_actions(first_obs), atol=1e-6)
    for row, agent in enumerate(sorted(rewards)):  # rows of step 0: vehicle 0, then vehicle 1
        brute = sum(r * 0.9**t for t, r in enumerate(rewards[agent]))
        assert demos.returns[row] == pytest.approx(brute, rel=1e-5, abs=1e-4)
    assert demos.success_rate == np.mean([env.sim.succeeded[i] for i in range(2)])


def test_demonstrations_of_the_avoiding_driver_carry_its_labels():
    cfg = make_arena_config(generator="agnn", num_vehicles=4, num_obstacles=8, max_steps=100)  # starts far, obstacles between
    demos = heuristic_demonstrations(cfg, episodes=1, seed=2, noise=0.0, gamma=0.99, driver="avoiding")
    np.testing.assert_allclose(demos.actions, avoiding_actions(demos.obs), atol=1e-5)
    assert not np.allclose(demos.actions, heuristic_actions(demos.obs), atol=1e-3)  # it swerved somewhere


def test_warm_start_settings_are_checked_before_any_work():
    with pytest.raises(ValueError, match=r"bad value for 'warm_start': 'bc'; allowed: 'none', 'heuristic'"):
        build_config("nav_ppo", "arena", {"warm_start": "bc"}, 0)
    with pytest.raises(ValueError, match=r"bad value for 'warm_start_episodes': 0; allowed: an integer >= 1"):
        build_config("nav_ppo", "arena", {"warm_start": "heuristic", "warm_start_episodes": 0}, 0)
    with pytest.raises(ValueError, match=r"bad value for 'bc_coeff': -1; allowed: a finite number >= 0"):
        build_config("nav_ppo", "arena", {"bc_coeff": -1}, 0)


def _mean_action_error(module, obs: np.ndarray) -> float:
    with torch.no_grad():
        inputs = module.forward_inference({Columns.OBS: torch.as_tensor(obs, dtype=torch.float32)})[Columns.ACTION_DIST_INPUTS]
    return float(np.abs(inputs[:, :2].clamp(-1, 1).numpy() - heuristic_actions(obs)).mean())


def test_warm_start_clones_the_driver_into_the_learner_and_the_env_runners(ray_session):
    overrides = {
        "stage": "short",
        "warm_start": "heuristic",
        "warm_start_episodes": 30,
        "warm_start_epochs": 20,
        "log_std_init": -1.0,
        "bc_coeff": 0.5,
        "bc_steps": 800,
        "train_batch_size_per_learner": 400,
        "minibatch_size": 200,
        "num_epochs": 1,
        "hidden": 64,
        "max_steps": 150,
    }
    cfg = build_config("nav_ppo", "arena", overrides, 0)
    cfg = with_env_runner(cfg, "batched", 2, True, cfg.env_config["scenario_config"])
    algo = cfg.build_algo()
    try:
        held_out = heuristic_demonstrations(cfg.env_config["scenario_config"], episodes=6, seed=99, noise=0.3, gamma=0.99).obs
        learner_module = algo.learner_group._learner.module["shared"]
        before = _mean_action_error(learner_module, held_out)
        result = algo.train()  # the first iteration clones before it samples (then one small PPO update)
        runner_module = algo.env_runner.module["shared"]
        after = _mean_action_error(learner_module, held_out)
        assert after < 0.5 * before  # the untrained policy's means sit near 0, the driver's actions mostly near +-1
        for name, value in learner_module.state_dict().items():
            if name in runner_module.state_dict():
                np.testing.assert_allclose(runner_module.state_dict()[name].numpy(), value.numpy())
        with torch.no_grad():
            log_std = learner_module.forward_inference({Columns.OBS: torch.as_tensor(held_out)})[Columns.ACTION_DIST_INPUTS][:, 2:]
        assert float(log_std.mean()) == pytest.approx(-1.0, abs=0.3)
        assert 0 < result["warm_start/warm_start_demo_success"] <= 1
        assert result["bc_weight"] == 0.5 and result["learners"]["shared"]["bc_loss"] >= 0  # the weight at env step 0
        assert 0 <= result["warm_start/action_mse"] < before**2  # the untrained MSE is at least its mean error squared (Jensen)
    finally:
        algo.stop()


def test_bc_weight_falls_linearly_to_zero():
    assert [bc_weight(s, 0.5, 1000) for s in (0, 250, 1000, 4000)] == pytest.approx([0.5, 0.375, 0.0, 0.0])
    assert bc_weight(10**6, 0.5, 0) == 0.5  # no decay: constant


def test_bc_loss_is_the_squared_gap_to_the_drivers_actions_over_unmasked_rows():
    obs = np.random.default_rng(4).normal(size=(5, 13)).astype(np.float32)
    offsets = np.array([[0.1, -0.2], [0.3, 0.0], [0.0, 0.5], [-0.4, 0.4], [2.0, 2.0]], np.float32)
    means = heuristic_actions(obs) + offsets
    inputs = torch.as_tensor(np.concatenate([means, np.full((5, 2), -1.0)], 1), dtype=torch.float32)
    want = np.mean([np.mean(o**2) for o in offsets[:4]])  # the last row is masked out
    mask = torch.tensor([True, True, True, True, False])
    assert float(bc_loss(torch.as_tensor(obs), inputs, mask)) == pytest.approx(want, rel=1e-5)
    assert float(bc_loss(torch.as_tensor(obs), inputs)) == pytest.approx(np.mean(offsets**2), rel=1e-5)


def test_teacher_labels_are_the_drivers_own_and_each_row_is_computed_once_per_batch(monkeypatch):
    cfg = make_arena_config(observed_entities=3, num_vehicles=6, num_obstacles=4)
    sim = ArenaSimulator(cfg)
    obs = [sim.reset(generate(training_rng(s), cfg, 6, 4)) for s in range(8)]
    batch = np.concatenate(obs)  # 48 rows of real observations, 3 entities each
    computed = []

    def counting(rows):
        computed.append(len(rows))
        return planning_actions(rows)

    monkeypatch.setitem(DRIVERS, "planning", counting)
    labels = TeacherLabels("planning")
    # each row's label equals the driver's on that row alone: batching changes nothing
    first = labels(batch[:30])
    np.testing.assert_array_equal(first, np.concatenate([planning_actions(row[None]) for row in batch[:30]]))
    computed.clear()
    order = np.random.default_rng(0).permutation(48)
    np.testing.assert_array_equal(labels(batch[order])[np.argsort(order)][:30], first)  # a later epoch, reshuffled
    assert computed == [18]  # only the 18 rows not seen before
    labels.clear()
    computed.clear()
    labels(batch[:5])
    assert computed == [5]  # a new batch: everything again


def test_demonstrations_label_every_driving_row_with_the_drivers_own_action():
    cfg = make_arena_config(generator="short", num_vehicles=2, max_vehicles=6, max_obstacles=4, observed_entities=2)
    demos = heuristic_demonstrations(cfg, 4, 3, 0.3, 0.99, "planning")
    assert demos.obs.shape[1] == 6 + 7 * 2
    np.testing.assert_allclose(demos.actions, planning_actions(demos.obs), atol=1e-6)  # labels are noiseless, rows float32


def test_an_actor_drives_while_the_driver_labels_the_states_it_visits():
    cfg = make_arena_config(generator="short", num_vehicles=2, num_obstacles=1, max_steps=30)
    standing = heuristic_demonstrations(cfg, 1, 5, 0.0, 0.9, "heuristic", actor=lambda obs: np.zeros((len(obs), 2)))
    driven = heuristic_demonstrations(cfg, 1, 5, 0.0, 0.9, "heuristic")
    # a vehicle that never touches its pedals stays where it started: every row repeats its first observation
    assert len(standing.obs) == 2 * 30 and standing.success_rate == 0.0
    np.testing.assert_allclose(standing.obs[0::2], np.repeat(standing.obs[:1], 30, 0), atol=1e-6)
    np.testing.assert_allclose(standing.obs[:2], driven.obs[:2], atol=1e-6)  # the same scenario as the driver's own
    np.testing.assert_allclose(standing.actions, heuristic_actions(standing.obs), atol=1e-6)  # the driver's labels
    assert not np.allclose(standing.actions, 0.0)
    assert not np.allclose(standing.obs[2:4], driven.obs[2:4])  # the driver, driving, moved


def test_dagger_rounds_add_the_clones_own_states_labelled_by_the_driver():
    cfg = make_arena_config(generator="short", num_vehicles=2, num_obstacles=1, max_steps=40)
    torch.manual_seed(0)  # the modules' initial weights
    module = fresh_module("nav_ppo", "arena", {"stage": "short", "hidden": 32}, seed=0)
    losses, rounds = warm_start(module, cfg, "heuristic", 4, 0.3, 3, -1.0, 7, 0.99, rounds=3)
    assert len(rounds) == 3 and set(losses) == {"action_mse", "log_std_mse", "value_mse"}
    first = heuristic_demonstrations(cfg, 4, 7, 0.3, 0.99, "heuristic")
    np.testing.assert_array_equal(rounds[0].obs, first.obs)  # round 0: the driver's own demonstrations
    for r in rounds[1:]:
        np.testing.assert_allclose(r.actions, heuristic_actions(r.obs), atol=1e-6)  # labels: always the driver's
    # round 2 was driven by the clone as round 1 left it: replay it with a module refitted the same way
    torch.manual_seed(0)
    again = fresh_module("nav_ppo", "arena", {"stage": "short", "hidden": 32}, seed=0)
    warm_start(again, cfg, "heuristic", 4, 0.3, 3, -1.0, 7, 0.99, rounds=2)
    replay = heuristic_demonstrations(cfg, 4, 7 + 2 * ROUND_SEED_STRIDE, 0.3, 0.99, "heuristic", actor_policy(again))
    np.testing.assert_array_equal(replay.obs, rounds[2].obs)
    assert not np.array_equal(rounds[2].obs[: len(rounds[0].obs)], rounds[0].obs[: len(rounds[2].obs)])
    with pytest.raises(ValueError, match=r"bad value for 'warm_start_rounds': 0; allowed: an integer >= 1"):
        warm_start(module, cfg, "heuristic", 4, 0.3, 3, -1.0, 7, 0.99, rounds=0)
    with pytest.raises(ValueError, match=r"bad value for 'warm_start_rounds': 0"):
        build_config("nav_ppo", "arena", {"warm_start": "heuristic", "warm_start_rounds": 0}, 0)


def test_lone_fraction_mixes_in_single_vehicle_episodes_and_leaves_the_default_stream_unchanged():
    short = {"generator": "short", "num_vehicles": 1, "max_vehicles": 8, "num_obstacles": 0, "max_obstacles": 8}
    env = ArenaEnv(make_arena_config(**short))
    env.reset(seed=5)
    rng = training_rng(5)  # the default draws: the counts, then the layout, from one stream
    n, m = int(rng.integers(1, 9)), int(rng.integers(0, 9))
    expected = generate(rng, env.config, n, m)
    np.testing.assert_array_equal(env.sim.layout.starts, expected.starts)
    np.testing.assert_array_equal(env.sim.layout.obstacles, expected.obstacles)
    always = ArenaEnv(make_arena_config(**short, lone_fraction=1.0))
    always.reset(seed=3)
    assert all((len(lay.starts), len(lay.obstacles)) == (1, 0) for lay in (always.draw_layout() for _ in range(20)))
    mixed = ArenaEnv(make_arena_config(**short, lone_fraction=0.3))
    mixed.reset(seed=4)
    lone = np.mean([(len(lay.starts), len(lay.obstacles)) == (1, 0) for lay in (mixed.draw_layout() for _ in range(600))])
    p = 0.3 + 0.7 / 72  # the lone draws plus the mix's own 1 x 0
    assert abs(lone - p) < 4 * np.sqrt(p * (1 - p) / 600)
    for bad in (-0.1, 1.5, float("nan"), True):
        with pytest.raises(ValueError, match=r"bad arena value lone_fraction=.*; allowed: a number in \[0, 1\]"):
            make_arena_config(lone_fraction=bad)


def test_intervention_weights_mark_exactly_the_rows_the_filter_changed():
    cfg = make_arena_config(num_vehicles=4, num_obstacles=3, observed_entities=2, max_steps=60)
    demos = heuristic_demonstrations(cfg, 2, 3, 0.0, 0.99, "planning")
    changed = np.abs(heuristic_actions(demos.obs) - demos.actions).max(axis=1) > 1e-6  # the plain driver: the filter's nominal
    assert 0 < changed.sum() < len(changed)  # some rows filtered, most not
    weights = intervention_weights(demos, 4.0)
    np.testing.assert_array_equal(weights, np.where(changed, 4.0, 1.0))
    plain = heuristic_demonstrations(cfg, 2, 3, 0.0, 0.99, "heuristic")
    np.testing.assert_array_equal(intervention_weights(plain, 4.0), np.ones(len(plain.obs)))  # the plain driver never intervenes


def test_weighted_clone_loss_is_the_weighted_mean_of_the_row_errors():
    cfg = make_arena_config(generator="short", num_vehicles=2, num_obstacles=1, max_steps=30)
    demos = heuristic_demonstrations(cfg, 2, 5, 0.3, 0.99, "heuristic")
    assert len(demos.obs) < 512  # one minibatch: the reported loss is that batch's
    module = fresh_module("nav_ppo", "arena", {"stage": "short", "hidden": 16}, seed=0)
    with torch.no_grad():
        inputs = module.forward_train({Columns.OBS: torch.as_tensor(demos.obs)})[Columns.ACTION_DIST_INPUTS]
    errors = ((inputs[:, :2].numpy() - demos.actions) ** 2).mean(axis=1)
    weights = np.where(errors > np.median(errors), 5.0, 1.0).astype(np.float32)  # the worse half counts 5x: a larger mean
    losses = clone(module, demos, 1, -1.0, 0, lr=0.0, weights=weights)  # lr 0: the weights stay, the loss is the initial one
    assert losses["action_mse"] == pytest.approx(float((weights * errors).sum() / weights.sum()), rel=1e-5)
    assert losses["action_mse"] > float(errors.mean()) * 1.01
    assert clone(module, demos, 1, -1.0, 0, lr=0.0)["action_mse"] == pytest.approx(float(errors.mean()), rel=1e-5)
    with pytest.raises(ValueError, match=r"bad value for 'warm_start_weight': 0"):
        build_config("nav_ppo", "arena", {"warm_start": "planning", "warm_start_weight": 0}, 0)
    with pytest.raises(ValueError, match=r"bad value for 'warm_start_weight': 0.0; allowed: a number > 0"):
        warm_start(module, cfg, "heuristic", 1, 0.3, 1, -1.0, 0, 0.99, weight=0.0)


def test_intervention_weights_on_hand_built_rows():
    obs = heuristic_demonstrations(make_arena_config(num_vehicles=2, num_obstacles=1, max_steps=20), 1, 1, 0.0, 0.99, "heuristic").obs[:6]
    actions = heuristic_actions(obs).astype(np.float32)
    actions[1, 0] += 0.5  # a swerve
    actions[4, 1] = -1.0 if actions[4, 1] > -0.5 else 1.0  # a brake (or a push)
    demos = Demonstrations(obs, actions, np.zeros(len(obs), np.float32), 1.0)
    np.testing.assert_array_equal(intervention_weights(demos, 3.0), [1.0, 3.0, 1.0, 1.0, 3.0, 1.0])
