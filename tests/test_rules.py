"""The driving rules (coin_app/sim/rules.py): each rule by hand-computed values, and the simulator's recorded episodes bit for bit."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from coin_app.sim import rules
from coin_app.sim.config import make_config
from coin_app.sim.scenes import DRIVING_SCENARIOS

DATA = Path(__file__).parent / "data"


def _record_module():
    spec = importlib.util.spec_from_file_location("rules_record", DATA / "rules_record.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("scenario", DRIVING_SCENARIOS)
def test_long_seeded_episodes_give_the_recorded_rewards_terminations_and_infos(scenario):
    """Every event, id, flag and count equal to the record; rewards and other floats to float64 round-off (numpy's
    arctan2 and hypot round the last bit differently on CPUs where they take SIMD paths, AVX-512 among them)."""
    record_module = _record_module()
    with np.load(record_module.RECORD) as f:
        want = {k.split("/", 1)[1]: f[k] for k in f.files if k.startswith(f"{scenario}/")}
    got = record_module.episode(scenario)
    assert np.array_equal(got["first_pos"], want["first_pos"]), (
        "the first step's positions differ from the record: the dynamics (or this machine's floating point) changed, not "
        "only the rules; rewrite the record with tests/data/rules_record.py if the change is meant"
    )
    flags = want["flags"].sum(0)
    assert flags[0] > 0 and flags[2] > 0 and want["spawned"].sum() > 0  # the record holds arrivals, exits and respawns
    assert got.keys() == want.keys()
    for key in want:
        assert got[key].dtype == want[key].dtype and got[key].shape == want[key].shape, key
        if np.issubdtype(want[key].dtype, np.floating):
            np.testing.assert_allclose(got[key], want[key], rtol=1e-9, atol=1e-9, err_msg=key)
        else:
            assert np.array_equal(got[key], want[key]), key


# ----------------------------------------------------------------------------- each rule by hand
CFG = make_config("intersection", crash_penalty=7.0, out_of_road_penalty=3.0, horizon=100, max_agent_steps=40, force_stop_factor=2)
T, F = True, False


def test_progress_is_measured_on_the_localised_lane_only_on_the_reference_road():
    lane_road, first_lane = np.array([0, 0, 1, 1]), np.array([0, 2])  # road 0: lanes 0, 1; road 1: lanes 2, 3
    lane, on_ref = rules.reward_lane(np.array([1, 3, 1]), lane_road, np.array([0, 0, 1]), first_lane)
    assert lane.tolist() == [1, 0, 2] and on_ref.tolist() == [T, F, F]


def test_the_sign_flips_only_off_the_reference_lanes_of_a_negative_road_in_a_flipping_scene():
    on_ref, negative = np.array([T, F, F, F]), np.array([T, T, F, T])
    assert rules.progress_sign(on_ref, negative, True).tolist() == [1.0, -1.0, 1.0, -1.0]
    assert rules.progress_sign(on_ref, negative, False).tolist() == [1.0] * 4


def test_step_reward_is_progress_plus_a_tenth_of_the_speed_fraction():
    # 2 m of progress at 20 m/s = 72 km/h of 80: 1.0 * 2 + 0.1 * 0.9
    r = rules.step_reward(
        CFG, np.array([12.0, 12.0, 5.0]), np.array([10.0, 10.0, 5.0]), np.array([20.0, 20.0, 0.0]), np.array([1.0, -1.0, 1.0])
    )
    assert r == pytest.approx([2.09, -2.09, 0.0], abs=1e-12)


def test_arrival_is_within_5_m_of_the_final_lanes_end_across_the_roads_lanes():
    # final lane 60 m long, 3.5 m wide, on a 2-lane road: s in (55, 65), r in [-5.25, 1.75]
    s = np.array([55.1, 55.0, 64.9, 65.0, 60.0, 60.0, 60.0, 60.0])
    r = np.array([0.0, 0.0, 0.0, 0.0, -5.25, -5.26, 1.75, 1.76])
    got = rules.arrived(s, r, np.full(8, 60.0), np.full(8, 3.5), np.full(8, 2))
    assert got.tolist() == [T, F, T, F, T, F, T, F]


def test_off_road_is_any_of_no_lane_a_solid_line_a_sidewalk():
    on_lane, line, walk = np.array([T, F, T, T, F]), np.array([F, F, T, F, T]), np.array([F, F, F, T, T])
    assert rules.off_road(on_lane, line, walk).tolist() == [F, T, T, T, T]


def test_time_outs_at_the_vehicles_step_limit_and_the_force_stop():
    assert rules.step_limit_reached(np.array([39, 40, 41]), CFG).tolist() == [F, T, T]
    assert rules.force_stopped(np.array([199, 200]), CFG).tolist() == [F, T]


def test_a_terminal_reward_replaces_the_step_reward_arrival_first_then_off_road_then_crash():
    arrive, oor, crash = np.array([T, F, F, F, T]), np.array([T, T, F, F, F]), np.array([T, T, T, F, F])
    got = rules.reward(CFG, np.full(5, 0.5), arrive, oor, crash)
    assert got.tolist() == [10.0, -3.0, -7.0, 0.5, 10.0]


def test_an_outcome_terminates_and_a_time_out_truncates_only_what_no_outcome_ended():
    arrive, oor, crash = np.array([T, F, F, F, F]), np.array([F, T, F, F, F]), np.array([F, F, T, F, F])
    terminated, truncated = rules.done(arrive, oor, crash, np.array([T, F, T, T, F]), np.array([F, T, F, F, T]))
    assert terminated.tolist() == [T, T, T, F, F] and truncated.tolist() == [F, F, F, T, T]


def test_global_reward_is_the_mean_over_each_envs_acting_vehicles():
    got = rules.global_reward(np.array([1.0, 2.0, 3.0, 5.0]), np.array([0, 0, 2, 2]), 3)
    assert got.tolist() == [1.5, 0.0, 4.0]
