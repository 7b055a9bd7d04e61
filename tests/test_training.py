"""Training helpers: the per-iteration figures, their log text, the stand-still (TD3 freeze) detector and the resume check."""

import math

import pytest

from coin_app.training import FreezeDetector, iteration_metrics, outcome_text
from coin_app.training.checkpoints import check_resume, checkpoint_meta


def result(env_steps, speed_sum=0.0, agent_steps=0, finished=0, saturation=None, spread=None):
    """A minimal RLlib ``train()`` result with the env runner and learner keys coin_app reads."""
    learner = {} if saturation is None else {"actor_saturation": saturation}
    learner |= {} if spread is None else {"actor_action_std": spread}
    runners = {"agents_finished": finished, "agents_speed_sum": speed_sum, "agents_agent_steps": agent_steps}
    return {"num_env_steps_sampled_lifetime": env_steps, "env_runners": runners, "learners": {"shared": learner}}


def test_mean_speed_is_the_speed_sum_over_agent_steps():
    m = iteration_metrics(result(100, speed_sum=30.0, agent_steps=12))
    assert m["mean_speed"] == 2.5
    assert math.isnan(iteration_metrics(result(100))["mean_speed"])  # no driving agent stepped (the arena)
    assert "speed 2.5 m/s" in outcome_text(m) and "agents" not in outcome_text(m)


def test_detector_warns_after_a_scripted_stand_still_and_not_before():
    detector = FreezeDetector(warmup_steps=1000, patience=3, speed_threshold=0.5)
    speeds = [0.0, 0.0, 6.0, 0.1, 0.2, 0.0, 0.0, 7.0]  # iterations 1-2 are in the warm-up
    warnings = []
    for k, speed in enumerate(speeds):
        metrics = iteration_metrics(result(500 * (k + 1), speed_sum=speed * 10, agent_steps=10, saturation=0.97))
        warnings.append(detector.update(metrics))
    # warm-up iterations never count; stand-still runs 4-7 (speeds 0.1, 0.2, 0.0, 0.0) warn from the third on; moving resets
    assert [w is not None for w in warnings] == [False, False, False, False, False, True, True, False]
    assert "stood still" in warnings[5] and "97%" in warnings[5] and "for 3 iterations" in warnings[5]


def test_ray_noise_goes_to_the_log_file_not_the_console(tmp_path, capsys):
    import logging
    import warnings

    from coin_app.training import ray_noise_to

    log = tmp_path / "ray.log"
    before = logging.getLogger("ray").handlers[:]
    with ray_noise_to(log):
        logging.getLogger("ray.rllib.some_module").warning("rllib says hello")
        warnings.warn("a deprecated thing", DeprecationWarning, stacklevel=1)
    captured = capsys.readouterr()
    assert "rllib says hello" not in captured.err + captured.out and "deprecated thing" not in captured.err + captured.out
    text = log.read_text()
    assert "rllib says hello" in text and "a deprecated thing" in text
    assert logging.getLogger("ray").handlers == before  # restored afterwards


def test_detector_names_a_collapsed_actor_apart_from_the_saturation_freeze():
    def warning(saturation, spread):
        detector = FreezeDetector(warmup_steps=0, patience=1)
        return detector.update(iteration_metrics(result(500, speed_sum=1.0, agent_steps=10, saturation=saturation, spread=spread)))

    collapsed = warning(0.0, 0.004)  # TraCo's case: one braking action inside the guard, nothing saturated
    assert "one action whatever it observes" in collapsed and "0.004" in collapsed and "actor_preact_penalty" not in collapsed
    frozen = warning(0.97, 0.3)  # saturated at full brake, actions still vary: the freeze advice
    assert "frozen at full brake" in frozen and "actor_preact_penalty" in frozen
    assert "frozen at full brake" in warning(0.97, None)  # an algorithm without the statistic
    # the saturation freeze itself: every output at tanh(u) = -1, so the spread is ~0 too; the guard advice, not "collapsed"
    saturated = warning(1.0, 1e-6)
    assert "frozen at full brake" in saturated and "whatever it observes" not in saturated


def test_resume_check_ignores_keys_the_algorithm_no_longer_takes_but_not_a_changed_shape(tmp_path):
    """An ITD3 run from before algorithms/td3/ carries CIG-TD3's keys (unused by ITD3) in its metadata; its resume is allowed."""
    small = {"num_agents": 3, "horizon": 40, "max_agent_steps": 40, "hidden": 16}
    meta = checkpoint_meta("itd3", "bottleneck", 0, small) | {"overrides": small | {"latent_dim": 4, "node_width": 8}}
    check_resume(tmp_path, meta, "itd3", "bottleneck", small)  # no error: those keys shaped nothing of ITD3
    with pytest.raises(ValueError, match="another network shape"):  # a key ITD3 takes still counts
        check_resume(tmp_path, meta, "itd3", "bottleneck", small | {"hidden": 32})


def test_process_tree_cpu_counts_a_live_child_and_keeps_it_once_reaped():
    import subprocess
    import sys
    import time

    from coin_app.training.monitor import process_tree_cpu_seconds

    burn = "import sys, time\nwhile time.process_time() < 0.4: pass\nprint(time.process_time(), flush=True)\nsys.stdin.read()"
    before, own_before = process_tree_cpu_seconds(), time.process_time()
    child = subprocess.Popen([sys.executable, "-c", burn], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        child_cpu = float(child.stdout.readline())  # the child's own CPU seconds; it is still alive, waiting on stdin
        alive = process_tree_cpu_seconds() - before
    finally:
        child.communicate("")
    reaped = process_tree_cpu_seconds() - before
    own = time.process_time() - own_before
    assert own < 0.2 < 0.4 <= child_cpu  # this process did little: the figures below are the child's
    tick = 0.02  # /proc counts in clock ticks (10 ms)
    assert alive >= child_cpu - tick  # a live descendant counts
    assert reaped >= child_cpu - tick and reaped >= alive - tick  # an ended, reaped one still does (its parent's children times)
    assert reaped <= child_cpu + own + 0.3  # and once only (its startup after readline's figure and exit: well under 0.3 s)


def test_run_clock_adds_the_resumed_figures_to_this_segments_cpu_and_wall_time():
    import time

    from coin_app.training.loop import RunClock

    before = time.perf_counter()
    clock = RunClock({"cpu_s": 1000.0, "wall_s": 500.0})
    start, t0 = time.process_time(), time.perf_counter()
    while time.process_time() - start < 0.3:
        pass
    t1 = time.perf_counter()
    read = clock.read()
    spent, t2 = time.process_time() - start, time.perf_counter()
    assert 1000.0 + spent - 0.02 <= read["cpu_s"] <= 1000.0 + spent + 0.2
    # the clock started between `before` and t0 and was read between t1 and t2
    assert 500.0 + (t1 - t0) <= read["wall_s"] <= 500.0 + (t2 - before)
    fresh = RunClock().read()
    assert 0.0 <= fresh["cpu_s"] < 0.1 and 0.0 <= fresh["wall_s"] < 0.1
