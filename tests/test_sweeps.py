"""Tune sweeps: experiment grids, validation before any work, smoke sweeps end to end, resume after kill -9."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import ray

from coin_app import training
from coin_app.algorithms import registry
from coin_app.cli import main
from coin_app.evaluation.sweep_results import load_trials, trial_name
from tuning import EXPERIMENTS, get_experiment
from tuning.ablations import VARIANTS
from tuning.experiment import expand_grid, trial_overrides
from tuning.sweep import check_address, validate_trials

REPO = Path(__file__).resolve().parent.parent


def test_paper_scale_grids_match_the_paper():
    seeds = expand_grid(get_experiment("seeds").param_space("intersection", methods=("cig_td3", "itd3", "ippo", "copo")))
    assert len(seeds) == 4 * 8 and {t["seed"] for t in seeds} == set(range(8))
    assert {t["steps"] for t in seeds} == {1_000_000}
    abl = expand_grid(get_experiment("ablations").param_space("roundabout"))
    assert len(abl) == 8 * 8 and {t["variant"] for t in abl} == set(VARIANTS)
    gen = get_experiment("generalization").paper
    assert gen.counts["intersection"] == (6, 12, 18, 24, 30, 36) and gen.counts["roundabout"] == (8, 16, 24, 32, 40, 48)
    assert gen.test_seeds == 20
    # every trial config of every experiment at both scales is a valid coin_app config
    for exp in EXPERIMENTS.values():
        for scale in ("paper", "smoke"):
            assert validate_trials(exp.param_space("intersection", scale))
    baselines = tuple(n for n in registry.ALGORITHMS if "intersection" in registry.get(n).scenarios)
    assert len(validate_trials(get_experiment("seeds").param_space("roundabout", "smoke", methods=baselines))) == 2 * len(baselines)
    with pytest.raises(ValueError, match="nav_ppo does not train on scenario 'intersection'"):
        validate_trials(get_experiment("seeds").param_space("intersection", methods=("nav_ppo",)))


def test_ablation_variants_change_exactly_the_named_modules():
    space = get_experiment("ablations").param_space("intersection")
    by_variant = {t["variant"]: t for t in expand_grid(space) if t["seed"] == 0}
    assert trial_overrides(by_variant["full"]) == {}
    assert trial_overrides(by_variant["wo_both"]) == {"local_module": "none", "global_module": "none", "vae_weight": 0.0}
    cfg = training.build_config("cig_td3", "intersection", trial_overrides(by_variant["sparse_graph"]), 0)
    assert cfg.graph == 40.0 and cfg.local_module == "cvae" and cfg.global_module == "gat"
    cfg = training.build_config("cig_td3", "intersection", trial_overrides(by_variant["wo_gat"]), 0)
    assert cfg.global_module == "none" and cfg.local_module == "cvae"
    # smoke scale: quick scenario + smoke settings, then the variant, then the user's overrides
    smoke = expand_grid(get_experiment("ablations").param_space("intersection", "smoke", overrides={"horizon": 200}))
    t = next(t for t in smoke if t["variant"] == "wo_both")
    assert trial_overrides(t) == registry.quick_settings("cig_td3") | {
        "warmup_steps": 200,
        "updates_per_env_step": 0.1,
        "local_module": "none",
        "global_module": "none",
        "vae_weight": 0.0,
        "horizon": 200,
    }
    assert trial_name(t) == "cig_td3-wo_both-s0"


def test_bad_sweeps_are_refused_before_any_work(tmp_path, capsys):
    storage = tmp_path / "sweeps"
    cases = [
        (["sweep", "nonsense"], "unknown experiment 'nonsense'; allowed: seeds, ablations, generalization"),
        (["sweep", "seeds", "--scenario", "arena"], "runs on intersection, roundabout, bottleneck; got scenario 'arena'"),
        (["sweep", "seeds", "--algos", "dqn"], "unknown algorithm 'dqn'"),
        (["sweep", "seeds", "--seeds", "1", "1"], "bad seeds [1, 1]"),
        (["sweep", "seeds", "--set", "hiden=3"], "hiden"),
        (["sweep", "ablations", "--algos", "ippo"], "sweeps variants of cig_td3; got method 'ippo'"),
        (["sweep", "seeds", "--max-concurrent", "0"], "bad --max-concurrent 0"),
        (["sweep", "seeds", "--smoke", "--address", "127.0.0.1:1"], "cannot reach a Ray cluster at 127.0.0.1:1"),
        (["sweep", "seeds", "--smoke", "--address", "nohost"], "bad --address 'nohost'"),
        (["sweep", "seeds", "--smoke", "--resume"], "nothing to resume"),
    ]
    for argv, message in cases:
        assert main([*argv, "--storage", str(storage)]) == 2, argv
        assert message in capsys.readouterr().err, argv
    assert not storage.exists() or not any(storage.iterdir())  # nothing was started
    existing = storage / "seeds-intersection-smoke"
    existing.mkdir(parents=True)
    (existing / "keep.txt").write_text("old results")
    assert main(["sweep", "seeds", "--smoke", "--storage", str(storage)]) == 2
    assert "already exists; continue it with --resume" in capsys.readouterr().err
    assert [p.name for p in existing.iterdir()] == ["keep.txt"] and (existing / "keep.txt").read_text() == "old results"


def test_address_probe_accepts_a_listening_port():
    import socket

    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        check_address(f"127.0.0.1:{server.getsockname()[1]}")
        check_address(f"ray://127.0.0.1:{server.getsockname()[1]}")
    check_address(None)
    check_address("auto")


@pytest.fixture(scope="module")
def local_ray():
    """One local Ray for the in-process sweeps of this module (2 CPUs: two trials at once)."""
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False, ignore_reinit_error=True)
    yield
    ray.shutdown()


def test_trial_files_caught_mid_write_are_handled_and_corrupt_ones_named(tmp_path):
    exp = tmp_path / "sweep"
    (exp / "a").mkdir(parents=True)
    (exp / "b").mkdir()
    (exp / "coin_sweep.json").write_text(json.dumps({"experiment": "seeds"}))
    (exp / "a" / "params.json").write_text(json.dumps({"algo": "itd3", "variant": "default", "seed": 3, "steps": 100}))
    # two complete iterations, then a third line cut off while Tune was appending it
    (exp / "a" / "result.json").write_text('{"env_steps": 50}\n{"env_steps": 100}\n{"env_st')
    (exp / "b" / "params.json").write_text("")  # Tune has created the file but not written it yet
    (trial,) = load_trials(exp, live=True)
    assert trial.name == "itd3-s3" and [r["env_steps"] for r in trial.results] == [50, 100] and trial.finished
    with pytest.raises(ValueError, match=r"b/params\.json is not valid JSON"):
        load_trials(exp)
    (exp / "b" / "params.json").unlink()
    (exp / "a" / "result.json").write_text('{"env_steps": 50}\n{"env_st\n{"env_steps": 100}\n')
    with pytest.raises(ValueError, match=r"a/result\.json line 2 is not valid JSON"):
        load_trials(exp)


def test_ablations_smoke_sweep_end_to_end(local_ray, tmp_path, capsys):
    storage = tmp_path / "sweeps"
    assert main(["sweep", "ablations", "--smoke", "--storage", str(storage)]) == 0
    out = capsys.readouterr().out
    assert "sweep summary:" in out
    exp_dir = storage / "ablations-intersection-smoke"
    trials = load_trials(exp_dir)
    assert [t.name for t in trials] == ["cig_td3-full-s0", "cig_td3-sparse_graph-s0", "cig_td3-wo_both-s0"]
    for t in trials:
        assert t.finished and t.last["env_steps"] >= 1000
        steps = [r["env_steps"] for r in t.results]
        assert steps == sorted(steps) and len(set(steps)) == len(steps)  # one result per iteration, in order
        meta = json.loads((t.final_checkpoint / "coin_app.json").read_text())
        assert meta["experiment"] == "ablations" and meta["variant"] == t.config["variant"]
        assert {k: meta["overrides"][k] for k in VARIANTS[t.config["variant"]]} == VARIANTS[t.config["variant"]]
        assert t.name in out and str(t.final_checkpoint) in out
    # the checkpoints are plain coin_app checkpoints: evaluate takes them directly
    assert main(["evaluate", str(trials[0].final_checkpoint), "--episodes", "1"]) == 0


def _wait_for(condition, timeout: float, what: str) -> None:
    t0 = time.time()
    while not condition():
        if time.time() - t0 > timeout:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.5)


def test_sweep_killed_with_sigkill_resumes_without_rerunning_or_losing_anything(tmp_path, capsys):
    storage = tmp_path / "sweeps"
    argv = ["sweep", "seeds", "--smoke", "--seeds", "0", "1", "--max-concurrent", "1"]
    argv += ["--num-cpus", "1", "--storage", str(storage), "--name", "killed"]
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    log = open(tmp_path / "driver.log", "w")
    driver = subprocess.Popen([sys.executable, "-m", "coin_app", *argv], cwd=REPO, env=env, stdout=log, stderr=log, start_new_session=True)
    exp_dir = storage / "killed"

    def trials():
        return load_trials(exp_dir, live=True) if (exp_dir / "coin_sweep.json").exists() else []

    try:  # kill -9 once the first trial has finished and the second is mid-way (checkpointed, not finished)
        _wait_for(
            lambda: any(t.finished for t in trials()) and any(t.checkpoints and not t.finished for t in trials()), 400, "a mid-way sweep"
        )
    finally:
        driver.send_signal(signal.SIGKILL)
        driver.wait()
        time.sleep(1)
        try:
            os.killpg(driver.pid, signal.SIGKILL)  # the orphaned local Ray processes the driver started
        except ProcessLookupError:
            pass
        log.close()
    before = trials()
    done_before = [t for t in before if t.finished]
    assert len(done_before) == 1
    first = done_before[0]
    snapshot = {
        "results": (first.path / "result.json").read_bytes(),
        "checkpoints": {c.name: sorted(p.name for p in c.rglob("*")) for c in first.checkpoints},
    }
    interrupted = next(t for t in before if not t.finished)
    assert main([*argv, "--resume"]) == 0
    assert "resuming" in capsys.readouterr().out
    after = trials()
    assert sorted(t.name for t in after) == ["cig_td3-s0", "cig_td3-s1"]  # every trial, exactly once
    assert len(list(exp_dir.glob("*/params.json"))) == 2
    assert all(t.finished and t.last["env_steps"] >= 1000 for t in after)
    again = next(t for t in after if t.name == first.name)
    assert (again.path / "result.json").read_bytes() == snapshot["results"]  # the finished trial was not rerun
    assert {c.name: sorted(p.name for p in c.rglob("*")) for c in again.checkpoints} == snapshot["checkpoints"]
    resumed = next(t for t in after if t.name == interrupted.name)
    # it continued from its checkpoint: its env-step count never went back to the start
    steps = [r["env_steps"] for r in resumed.results]
    assert steps[0] == 500 and steps.count(500) == 1 and steps[-1] >= 1000
