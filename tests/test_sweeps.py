"""Tune sweeps: experiment grids, validation before any work, smoke sweeps end to end, resume after kill -9."""

import dataclasses
import importlib.util
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import ray

from coin_app import training
from coin_app.adapters.rllib_env import CoinMultiAgentEnv
from coin_app.algorithms import registry
from coin_app.algorithms.checkpoint_files import verify
from coin_app.algorithms.td3.learner import lr_schedule
from coin_app.cli import main
from coin_app.evaluation.sweep_results import load_trials, trial_name
from coin_app.sim.config import make_config
from coin_app.training import checkpoint_meta, iteration_metrics
from tuning import EXPERIMENTS, get_experiment
from tuning import sweep as sweep_module
from tuning.ablations import VARIANTS
from tuning.experiment import expand_grid, is_per_method, trial_layers, trial_overrides
from tuning.progress_csv import aligned_row, read_table, write_table
from tuning.sweep import check_address, check_local_gpus, validate_trials
from tuning.trainable import CoinTrial, build_trial_config, trial_gpus, trial_resources

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


def _seeds_trial(algo: str, overrides: dict, scale: str = "paper") -> dict:
    return expand_grid(get_experiment("seeds").param_space("intersection", scale, (algo,), (0,), overrides=overrides))[0]


def test_gpu_learner_settings_make_each_trial_reserve_a_gpu():
    def bundles(algo, overrides):
        return [{k: v for k, v in b.items() if v} for b in trial_resources(_seeds_trial(algo, overrides)).bundles]

    # CPU learners (the default): the trial's process only; the PPO family adds its 4 CPU env runners
    assert bundles("cig_td3", {}) == [{"CPU": 1}] and trial_gpus(_seeds_trial("cig_td3", {})) == 0
    assert bundles("ippo", {}) == [{"CPU": 1}] * 5
    # learner in the trial's process on a GPU: the trial's own bundle holds it
    assert bundles("cig_td3", {"num_gpus_per_learner": 1}) == [{"CPU": 1, "GPU": 1}]
    # one remote GPU learner: a bundle of its own; env runners stay CPU bundles
    assert bundles("cig_td3", {"num_learners": 1, "num_gpus_per_learner": 1}) == [{"CPU": 1}, {"GPU": 1}]
    assert bundles("ippo", {"num_learners": 1, "num_gpus_per_learner": 1}) == [{"CPU": 1}] * 5 + [{"GPU": 1}]
    assert bundles("copo", {"num_learners": 1, "num_gpus_per_learner": 1}) == [{"CPU": 1}] * 5 + [{"GPU": 1}]
    assert bundles("cig_td3", {"num_learners": 1}) == [{"CPU": 1}, {"CPU": 1}]  # a remote CPU learner
    t = _seeds_trial("cig_td3", {"num_learners": 1, "num_gpus_per_learner": 1})
    cfg = build_trial_config(t)
    assert (cfg.num_learners, cfg.num_gpus_per_learner) == (1, 1) and trial_gpus(t) == 1
    assert CoinTrial.default_resource_request(t).bundles == trial_resources(t).bundles  # what Tune asks the trainable
    assert CoinTrial.default_resource_request({"seed": 0}) is None  # partial configs: Tune's default
    # the learner keys stay out of a checkpoint's overrides (a CPU-only machine rebuilds the module from them)
    meta = checkpoint_meta("ippo", "intersection", 0, {"hidden": 32, "num_learners": 1, "num_gpus_per_learner": 0.5})
    assert meta["overrides"] == {"hidden": 32} and meta["learners"] == {"num_learners": 1, "num_gpus_per_learner": 0.5}
    for algo, overrides, message in [
        ("copo", {"num_learners": 2}, "bad value for 'num_learners': 2; allowed: 0 (the learner in the training process) or 1"),
        ("cig_td3", {"num_learners": 2}, "bad value for 'num_learners': 2; allowed: 0 (the learner in the training process) or 1"),
        ("ippo", {"num_learners": -1}, "bad value for 'num_learners': -1; allowed: 0 (the learner in the training process) or 1"),
        ("ippo", {"num_gpus_per_learner": "one"}, "bad value for 'num_gpus_per_learner': 'one'; allowed: a number >= 0"),
        ("ippo", {"num_gpus_per_learner": True}, "bad value for 'num_gpus_per_learner': True; allowed: a number >= 0"),
    ]:
        with pytest.raises(ValueError, match=re.escape(message)):
            validate_trials(get_experiment("seeds").param_space("intersection", methods=(algo,), overrides=overrides))


def test_gpu_sweep_on_a_local_ray_without_enough_gpus_is_refused(ray_session, tmp_path, capsys):
    more = int(ray.cluster_resources().get("GPU", 0)) + 1  # more GPUs than this machine has, whatever it has
    with pytest.raises(ValueError, match=f"each trial reserves {more} GPU"):
        check_local_gpus(float(more), started_here=False)
    storage = tmp_path / "sweeps"
    argv = [
        "sweep",
        "seeds",
        "--smoke",
        "--seeds",
        "0",
        "--storage",
        str(storage),
        "--set",
        "num_learners=1",
        f"num_gpus_per_learner={more}",
    ]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"each trial reserves {more} GPU(s) (num_gpus_per_learner), but the local Ray has {more - 1}" in err
    assert "--address of a cluster with GPU workers" in err
    assert not storage.exists() or not any(storage.iterdir())  # nothing was started
    assert ray.is_initialized()  # a Ray the sweep did not start stays up


def test_bad_sweeps_are_refused_before_any_work(tmp_path, capsys):
    storage = tmp_path / "sweeps"
    cases = [
        (["sweep", "nonsense"], "unknown experiment 'nonsense'; allowed: seeds, ablations, generalization"),
        (["sweep", "seeds", "--scenario", "arena"], "invalid choice: 'arena'"),  # the parser's choices: the driving scenarios
        (["sweep", "seeds", "--algos", "dqn"], "unknown algorithm 'dqn'"),
        (["sweep", "seeds", "--seeds", "1", "1"], "bad seeds [1, 1]"),
        (["sweep", "seeds", "--set", "hiden=3"], "hiden"),
        (["sweep", "seeds", "--set", "num_learners=2"], "bad value for 'num_learners': 2"),
        (["sweep", "ablations", "--algos", "ippo"], "sweeps variants of cig_td3; got method 'ippo'"),
        (["sweep", "seeds", "--max-concurrent", "0"], "bad --max-concurrent 0"),
        (["sweep", "seeds", "--smoke", "--address", "127.0.0.1:1"], "cannot reach a Ray cluster at 127.0.0.1:1"),
        (["sweep", "seeds", "--smoke", "--address", "nohost"], "bad --address 'nohost'"),
        (["sweep", "seeds", "--smoke", "--resume"], "nothing to resume"),
        (["sweep", "seeds", "--smoke", "--restart", "ippo"], "--restart ippo without --resume"),
        (["sweep", "seeds", "--scale", "huge"], "unknown scale 'huge'; allowed: paper, dense, reduced, smoke"),
        (["sweep", "ablations", "--scale", "reduced"], "experiment 'ablations' has no reduced scale; allowed: paper, smoke"),
        (["sweep", "seeds", "--smoke", "--scale", "paper"], "--smoke with --scale paper; allowed: one of them"),
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


def test_reduced_scale_is_the_quick_scenario_with_each_familys_protocol_settings():
    space = get_experiment("seeds").param_space("intersection", "reduced", methods=("cig_td3", "itd3", "traco", "ippo", "copo"))
    trials = validate_trials(space)  # every trial of the protocol builds
    assert len(trials) == 5 * 5 and {t["seed"] for t in trials} == set(range(5)) and {t["steps"] for t in trials} == {40_000}
    by_algo = {t["algo"]: t for t in trials if t["seed"] == 0}
    # a TD3 trial checkpoints every 10 iterations of 500 env steps; all of them are kept for the validation-seed selection
    assert get_experiment("seeds").scale("reduced").keep >= 40_000 // (10 * 500)
    # the learning curves' settings (4 agents, small networks); the TD3 family in fp32 (faster than bf16 at these sizes),
    # its rates constant for 20k env steps, then falling to 10 % at 40k
    decay = {"lr_decay_start": 20_000, "lr_decay_steps": 20_000, "lr_final_fraction": 0.1}
    decay |= {"exploration_noise_decay_start": 20_000, "exploration_noise_decay_steps": 20_000}  # the exploration std with them
    guard = {"actor_preact_penalty": 0.01, "actor_preact_threshold": 1.0}  # 10x the quick settings' guard, from |u| = 1
    # twice the paper's exploration std (the lever adopted after the fourth sweep), decaying to 0.02 over the second half
    # (the lever adopted after the time-out lever)
    guard |= {"exploration_noise_initial": 0.1, "exploration_noise": 0.02}
    guard |= {"train_batch_size_per_learner": 256}  # the paper's minibatch, not the quick settings' 128 (after the fifth sweep)
    guard |= {"policy_delay": 1}  # the actor after every critic update (the quick settings' 2; the lever after batch 256)
    guard |= {"timeout_bootstrap": False}  # a time-out ends the TD target (the paper's d_i; the lever after policy delay 1)

    def resolved(trial):  # every setting the trial runs with (a preset value equal to the default is no override)
        return {s.key: s.value for s in registry.merged_settings(trial["algo"], trial["scenario"], trial_layers(trial))}

    for algo in ("cig_td3", "itd3"):
        assert (registry.quick_settings(algo) | {"precision": "fp32"} | guard | decay).items() <= resolved(by_algo[algo]).items()
    # TraCo also adds its optional individual critic (its domain critic alone froze the actor at one constant action)
    expected = registry.quick_settings("traco") | {"precision": "fp32"} | guard | decay | {"individual_critic": True}
    assert expected.items() <= resolved(by_algo["traco"]).items()
    assert build_trial_config(by_algo["traco"]).individual_critic is True
    assert "individual_critic" not in trial_overrides(by_algo["cig_td3"]) | trial_overrides(by_algo["ippo"])
    assert trial_overrides(by_algo["ippo"]) == registry.quick_settings("ippo")
    cfg = build_trial_config(by_algo["cig_td3"])
    assert (cfg.updates_per_env_step, cfg.train_batch_size_per_learner, cfg.env_config["scenario_config"].num_agents) == (1.0, 256, 4)
    assert registry.quick_settings("cig_td3")["train_batch_size_per_learner"] == 128
    assert cfg.precision == "fp32" and registry.get("cig_td3").hyperparameters["precision"][0] == "auto"
    assert (cfg.actor_preact_penalty, cfg.actor_preact_threshold) == (0.01, 1.0)  # the built config carries the stronger guard
    assert (cfg.exploration_noise_initial, cfg.exploration_noise) == (0.1, 0.02)
    assert registry.get("cig_td3").hyperparameters["exploration_noise"][0] == 0.05
    module = cfg.build_learner(env=CoinMultiAgentEnv(cfg.env_config)).module["shared"].unwrapped()
    # 0.1 from the warm-up's end through 20k env steps, then linear to 0.02 at 40k (hand-computed midpoint 0.06)
    assert [module.noise_std(t) for t in (600, 20_000, 30_000, 40_000)] == pytest.approx([0.1, 0.1, 0.06, 0.02])
    assert cfg.policy_delay == 1 and registry.quick_settings("cig_td3")["policy_delay"] == 2
    assert cfg.timeout_bootstrap is False and registry.get("cig_td3").hyperparameters["timeout_bootstrap"][0] is True
    assert build_trial_config(by_algo["traco"]).timeout_bootstrap is False
    assert lr_schedule(1e-3, cfg) == [[0, 1e-3], [20_000, 1e-3], [40_000, pytest.approx(1e-4)]]
    assert trial_name(by_algo["copo"]) == "copo-s0" and trial_resources(by_algo["copo"]).bundles == [{"CPU": 1}]
    # the user's --set still comes last
    tweaked = expand_grid(get_experiment("seeds").param_space("intersection", "reduced", ("itd3",), (0,), overrides={"hidden": 32}))
    assert (registry.quick_settings("itd3") | {"precision": "fp32", "hidden": 32} | guard | decay).items() <= resolved(tweaked[0]).items()
    # another budget moves the decay with it (an odd budget: the second half is the longer one)
    (short,) = expand_grid(get_experiment("seeds").param_space("intersection", "reduced", ("traco",), (0,), steps=601))
    moved = {"lr_decay_start": 300, "lr_decay_steps": 301, "lr_final_fraction": 0.1}
    assert {k: trial_overrides(short)[k] for k in decay} == moved | {
        "exploration_noise_decay_start": 300,
        "exploration_noise_decay_steps": 301,
    }


DENSE_METHODS = ("cig_td3", "itd3", "traco", "ippo", "cppo", "mfpo", "copo")


def test_dense_scale_is_the_default_intersection_with_each_familys_dense_preset_and_budget(tmp_path, capsys):
    seeds = get_experiment("seeds")
    dense = seeds.scale("dense", "intersection")
    space = seeds.param_space("intersection", "dense", methods=DENSE_METHODS)
    trials = expand_grid(space)
    assert len(trials) == 7 * 5 and {t["seed"] for t in trials} == set(range(5))
    # the PPO family at its reference budget, the TD3 family at its pilots' (one value: tuning/seeds.py)
    td3_family = {"cig_td3", "itd3", "traco"}
    budgets = {m: dense.steps_by_family["td3"] if m in td3_family else 1_000_000 for m in DENSE_METHODS}
    assert {t["algo"]: t["steps"] for t in trials} == budgets and dense.steps_by_family["td3"] < 1_000_000
    # Tune resolves the per-method budget as expand_grid does (the grid first, then each trial's method)
    from ray.tune.search.variant_generator import generate_variants

    tuned = [v for _, v in generate_variants(sweep_module.tune_space(space))]
    assert sorted((t["algo"], t["seed"], t["steps"]) for t in tuned) == sorted((t["algo"], t["seed"], t["steps"]) for t in trials)
    by_algo = {t["algo"]: t for t in trials if t["seed"] == 0}
    assert validate_trials(seeds.param_space("intersection", "dense", methods=DENSE_METHODS, seeds=(0,)))  # each method's builds
    scenario = make_config("intersection", preset="metadrive_compat")
    penalties = {"crash_penalty": 5.0, "out_of_road_penalty": 5.0}  # COIN's, for the TD3 family only
    for algo, trial in by_algo.items():
        preset = registry.get(algo).presets["dense"]
        own = penalties if algo in td3_family else {}
        # the preset and the scale's scenario alone: no quick scenario, no reduced decay
        assert trial_overrides(trial) == preset.changes() | {"preset": "metadrive_compat"} | own
        merged = {s.key: s for s in registry.merged_settings(algo, "intersection", trial_layers(trial))}
        # the scenario at its defaults: 30 vehicles, MetaDrive's horizon of 1000, respawning
        assert (merged["num_agents"].value, merged["horizon"].value, merged["allow_respawn"].value) == (30, 1000, True)
        for key in ("num_agents", "horizon", "max_agent_steps", "allow_respawn"):
            assert merged[key].value == getattr(scenario, key) and merged[key].origin.endswith("default"), (algo, key)
        # the authors' code's and CoPO's environment (issue 56's part 0): its lidar range for all, its penalties for the PPO
        # family, COIN's for the TD3 family (the pilots' P9)
        crash = 5.0 if algo in td3_family else 10.0
        assert (merged["preset"].value, merged["crash_penalty"].value, merged["lidar_range"].value) == ("metadrive_compat", crash, 40.0)
        assert merged["out_of_road_penalty"].value == crash and merged["lidar_range"].origin == "preset 'metadrive_compat'"
        family = "td3" if algo in td3_family else "ppo"
        want = f"dense scale's scenario for the {family} family (seeds experiment, tuning/)" if own else "preset 'metadrive_compat'"
        assert merged["crash_penalty"].origin == want, (algo, merged["crash_penalty"].origin)
    # the PPO family: the paper's settings, the defaults (sampled in the trial's process: one CPU a trial)
    for algo in ("ippo", "cppo", "mfpo", "copo"):
        assert registry.get(algo).presets["dense"].changes() == {}
    assert registry.get("ippo").presets["paper"].changes() == {"num_env_runners": 4}
    assert trial_resources(by_algo["ippo"]).bundles == [{"CPU": 1}]
    # the TD3 family: one choice (td3/settings.py), lifted into CIG-TD3 and TraCo with their critics' widths and rates;
    # TraCo keeps the reduced protocol's individual critic (the same freeze guard)
    family = registry.get("itd3").presets["dense"].changes()
    for algo in ("cig_td3", "traco"):
        assert family.items() <= registry.get(algo).presets["dense"].changes().items()
    assert registry.get("traco").presets["dense"].individual_critic is True
    cfg = build_trial_config(by_algo["cig_td3"])
    scenario_cfg = cfg.env_config["scenario_config"]
    assert (scenario_cfg.num_agents, scenario_cfg.horizon, scenario_cfg.allow_respawn) == (30, 1000, True)
    # every method observes with the lidar of the authors' code and CoPO's (40 m); the PPO family trains with their
    # penalties (10), the TD3 family with COIN's (5)
    for algo, trial in by_algo.items():
        env = build_trial_config(trial).env_config["scenario_config"]
        penalty = 5.0 if algo in td3_family else 10.0
        assert (env.crash_penalty, env.out_of_road_penalty, env.lidar_range) == (penalty, penalty, 40.0), algo
    cig = registry.get("cig_td3").presets["dense"]
    assert (cfg.updates_per_env_step, cfg.hidden, cfg.node_width, cfg.precision) == (
        cig.updates_per_env_step,
        cig.hidden,
        cig.node_width,
        cig.precision,
    )
    assert cig.exploration_noise_initial is None and cig.lr_decay_steps == 0  # constant exploration and rates
    # the TD3 family keeps its checkpoints best on their periodic validation: the key iteration_metrics gives that figure
    from coin_app.training import EVAL_RESULT_KEY

    assert dense.keep_best in iteration_metrics({"env_runners": {}, EVAL_RESULT_KEY: {"success_rate": 0.5}})
    assert registry.get("cig_td3").presets["dense"].eval_every == dense.checkpoint_every  # every checkpoint has its evaluation
    # --steps overrides every method's budget
    steered = seeds.param_space("intersection", "dense", methods=("cig_td3", "ippo"), seeds=(0,), steps=700)
    assert steered["steps"] == 700 and {t["steps"] for t in expand_grid(steered)} == {700}
    assert is_per_method(seeds.param_space("intersection", "dense", methods=("cig_td3", "ippo"))["steps"])
    # config prints the trial the sweep runs, with the layer of each setting
    assert main(["config", "--algo", "cig_td3", "--scale", "dense"]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0].endswith(f"one cig_td3 trial on intersection, {dense.steps_by_family['td3']:,} env steps")
    rows = {line.split()[0]: line.split(maxsplit=2)[2] for line in out.splitlines() if line.startswith("  ")}
    assert rows["num_agents"] == "intersection's default" and rows["horizon"] == "ScenarioConfig default"
    assert rows["updates_per_env_step"] == "preset 'dense' (coin_app.algorithms.cig_td3.settings)"
    assert rows["preset"].startswith("dense scale's scenario") and rows["lidar_range"] == "preset 'metadrive_compat'"
    # the reduced scale, made for the intersection, refuses another scene in one line before any work, naming the
    # scales made for every scene (the dense one among them)
    argv = ["sweep", "seeds", "--scenario", "roundabout", "--scale", "reduced", "--algos", "cig_td3", "--seeds", "0"]
    assert main([*argv, "--storage", str(tmp_path / "sweeps")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "the reduced scale was made for the intersection" in err
    assert "not the roundabout; allowed: --scenario intersection, or a scale for every scene: paper, dense, smoke" in err


@pytest.mark.parametrize(("scene", "vehicles"), [("roundabout", 40), ("bottleneck", 20)])
def test_dense_scale_runs_the_other_scenes_at_their_density_the_bottleneck_as_the_authors_did(scene, vehicles):
    seeds = get_experiment("seeds")
    space = seeds.param_space(scene, "dense", methods=DENSE_METHODS, seeds=(0,))
    trials = validate_trials(space)  # each method's config builds on the scene
    assert len(trials) == 7
    authors = scene == "bottleneck"  # their patched MetaDrive's solid neck centre line, MetaDrive's 96 numbers
    for trial in trials:
        env = build_trial_config(trial).env_config["scenario_config"]
        assert (env.num_agents, env.horizon, env.allow_respawn, env.lidar_range) == (vehicles, 1000, True, 40.0)
        assert (env.solid_center_line, env.obs_dim) == ((True, 96) if authors else (False, 91)), trial["algo"]
        penalty = 5.0 if registry.get(trial["algo"]).family == "td3" else 10.0
        assert env.crash_penalty == penalty, trial["algo"]


def test_a_scales_scenario_by_family_reaches_only_that_familys_trials(monkeypatch, capsys):
    import dataclasses

    from tuning.experiment import per_method

    seeds = get_experiment("seeds")
    dense = dataclasses.replace(seeds.dense, scenario={"lidar_range": 40.0}, scenario_by_family={"ppo": {"crash_penalty": 10.0}})
    exp = dataclasses.replace(seeds, dense=dense)
    space = exp.param_space("intersection", "dense", methods=("cig_td3", "ippo", "itd3"), seeds=(0,))
    assert is_per_method(space["scale_scenario"])
    by_algo = {t["algo"]: trial_overrides(t) for t in expand_grid(space)}
    assert {a: (o["lidar_range"], o.get("crash_penalty")) for a, o in by_algo.items()} == {
        "cig_td3": (40.0, None),
        "itd3": (40.0, None),
        "ippo": (40.0, 10.0),
    }
    # one family only: every trial's settings are the same, a plain value rather than a per-method one
    alone = exp.param_space("intersection", "dense", methods=("cig_td3", "itd3"), seeds=(0,))
    assert alone["scale_scenario"] == {"lidar_range": 40.0}
    assert per_method({"a": {"x": 1}, "b": {"x": 1}}) == {"x": 1} and is_per_method(per_method({"a": {"x": 1}, "b": {}}))
    # what Tune resolves (tune.sample_from per method) is what expand_grid gives
    from ray.tune.search.variant_generator import generate_variants

    from tuning.sweep import tune_space

    tuned = {v["algo"]: v["scale_scenario"] for _, v in generate_variants(tune_space(space))}
    assert tuned == {"cig_td3": {"lidar_range": 40.0}, "itd3": {"lidar_range": 40.0}, "ippo": {"lidar_range": 40.0, "crash_penalty": 10.0}}
    # config --scale prints the family's layer, as the sweep's trial takes it
    import tuning

    monkeypatch.setitem(tuning.EXPERIMENTS, "seeds", exp)
    assert main(["config", "--algo", "ippo", "--scale", "dense"]) == 0
    rows = {line.split()[0]: line.split(maxsplit=2)[2] for line in capsys.readouterr().out.splitlines() if line.startswith("  ")}
    assert rows["crash_penalty"] == "dense scale's scenario for the ppo family (seeds experiment, tuning/)"
    assert rows["lidar_range"] == rows["crash_penalty"]
    # a family no algorithm has is refused where the scale is written
    with pytest.raises(ValueError, match=r"unknown algorithm families \['PPO'\]; allowed: ppo, td3"):
        dataclasses.replace(seeds.dense, scenario_by_family={"PPO": {}})


def test_address_probe_accepts_a_listening_port():
    import socket

    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        check_address(f"127.0.0.1:{server.getsockname()[1]}")
        check_address(f"ray://127.0.0.1:{server.getsockname()[1]}")
    check_address(None)
    check_address("auto")


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


def test_reduced_protocol_runs_end_to_end_at_a_tiny_budget(ray_session, tmp_path, capsys, monkeypatch):
    storage = tmp_path / "sweeps"
    argv = ["sweep", "seeds", "--scale", "reduced", "--algos", "cig_td3", "copo", "--seeds", "3", "--steps", "600"]
    assert main([*argv, "--storage", str(storage)]) == 0
    assert "seeds on intersection (reduced scale): 2 trials" in capsys.readouterr().out
    exp_dir = storage / "seeds-intersection-reduced"
    assert json.loads((exp_dir / "coin_sweep.json").read_text())["scale"] == "reduced"
    for t in load_trials(exp_dir):
        assert t.finished and t.last["env_steps"] >= 600 and t.config["seed"] == 3
        meta = json.loads((t.final_checkpoint / "coin_app.json").read_text())
        assert meta["overrides"] == trial_overrides(t.config) and meta["seed"] == 3
        assert meta["overrides"]["num_agents"] == 4 and (t.config["algo"] != "cig_td3" or meta["overrides"]["precision"] == "fp32")
    # --restart copo: CoPO's trial runs again from scratch (a new directory; the old one kept aside), CIG-TD3's stays as it is
    before = {t.config["algo"]: t for t in load_trials(exp_dir)}
    kept = (before["cig_td3"].path / "result.json").read_bytes()
    assert main([*argv, "--storage", str(storage), "--resume", "--restart", "copo"]) == 2  # just written: may be running
    assert "so its sweep may still be running" in capsys.readouterr().err
    monkeypatch.setattr(sweep_module, "LIVE_STATE_S", 0.0)
    assert main([*argv, "--storage", str(storage), "--resume", "--restart", "ippo"]) == 2
    assert "--restart ippo: not a method of" in capsys.readouterr().err
    assert main([*argv, "--storage", str(storage), "--resume", "--restart", "copo"]) == 0
    assert "restarting 1 trial(s) of copo" in capsys.readouterr().out
    trials = load_trials(exp_dir)
    assert sorted(t.name for t in trials) == ["cig_td3-s3", "copo-s3"]  # the old trial directory is not left behind
    after = {t.config["algo"]: t for t in trials}
    assert after["cig_td3"].path == before["cig_td3"].path and (after["cig_td3"].path / "result.json").read_bytes() == kept
    old, new = before["copo"], after["copo"]
    assert new.path != old.path and new.finished and new.last["env_steps"] >= 600
    assert list((exp_dir / "replaced").glob(f"*/{old.path.name}/result.json"))  # nothing lost
    # the rerun, in another worker process (another string hash seed), reproduces the first run
    keys = ("env_steps", "episode_return_mean", "learner/policy_loss", "learner/vf_loss", "learner/lcf_mean")
    assert json.dumps([[r[k] for k in keys] for r in new.results]) == json.dumps([[r[k] for k in keys] for r in old.results])


def test_dense_protocol_runs_end_to_end_at_a_tiny_budget(ray_session, tmp_path, capsys):
    """30 vehicles, horizon 1000: CIG-TD3 two iterations of 500 env steps (the warm-up, then 125 updates), IPPO one of 1,600.

    Measured at a load average of 11 on 2 cores: 58 s (CIG-TD3's iterations 6.7 and 22.6 s, IPPO's 12.8 s, the rest
    building the two algorithms); ``--steps 1`` (one warm-up iteration, no update) took 29 s at a load of 5.
    """
    storage = tmp_path / "sweeps"
    argv = ["sweep", "seeds", "--scale", "dense", "--algos", "cig_td3", "ippo", "--seeds", "0", "--steps", "501"]
    assert main([*argv, "--storage", str(storage)]) == 0
    assert "seeds on intersection (dense scale): 2 trials" in capsys.readouterr().out
    exp_dir = storage / "seeds-intersection-dense"
    settings = json.loads((exp_dir / "coin_sweep.json").read_text())
    assert (settings["scale"], settings["steps"]) == ("dense", 501)  # --steps: one budget for both families
    trials = {t.config["algo"]: t for t in load_trials(exp_dir)}
    assert sorted(t.name for t in trials.values()) == ["cig_td3-s0", "ippo-s0"]
    assert [r["env_steps"] for r in trials["cig_td3"].results] == [500, 1000]
    assert "learner/global_q_loss" in trials["cig_td3"].results[-1]  # past the warm-up: the 30-vehicle update ran
    # the last iteration is evaluated on validation seeds, so the final checkpoint has its score (the scale's keep_best)
    assert "eval/success_rate" not in trials["cig_td3"].results[0] and "eval/success_rate" in trials["cig_td3"].results[-1]
    assert not any("eval/success_rate" in r for r in trials["ippo"].results)
    assert [r["env_steps"] for r in trials["ippo"].results] == [registry.get("ippo").presets["dense"].train_batch_size_per_learner]
    for algo, t in trials.items():
        assert t.finished and t.config["steps"] == 501
        meta = json.loads((t.final_checkpoint / "coin_app.json").read_text())
        # the dense preset alone, on the scenario's defaults (30 vehicles, horizon 1000) in the metadrive_compat environment,
        # the TD3 family with COIN's penalties
        own = {"crash_penalty": 5.0, "out_of_road_penalty": 5.0} if algo == "cig_td3" else {}
        assert meta["overrides"] == registry.get(algo).presets["dense"].changes() | {"preset": "metadrive_compat"} | own
        assert meta["env_config"] == {"preset": "metadrive_compat"} | own
        # every iteration carries the trial's clocks, and its checkpoint the clocks at its save
        cpu, wall = [r["cpu_s"] for r in t.results], [r["wall_s"] for r in t.results]
        assert cpu == sorted(cpu) and wall == sorted(wall) and 0 < cpu[0] and 0 < wall[0]
        assert meta["cpu_s"] >= cpu[-1] and meta["wall_s"] >= wall[-1]


def test_ablations_smoke_sweep_end_to_end(ray_session, tmp_path, capsys):
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


@pytest.mark.skipif(
    any(importlib.util.find_spec(p) is None for p in ("wandb", "mlflow")), reason="optional trackers: pip install wandb mlflow-skinny"
)
def test_sweep_logs_every_trial_to_wandb_offline_and_an_mlflow_store(ray_session, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("WANDB_MODE", "offline")  # no network: W&B writes its run files locally
    monkeypatch.setenv("WANDB_SILENT", "true")
    monkeypatch.setenv("MLFLOW_ALLOW_FILE_STORE", "true")  # MLflow 3 wants a database; a directory store is enough here
    store = tmp_path / "mlruns"
    argv = ["sweep", "seeds", "--smoke", "--storage", str(tmp_path / "s"), "--name", "tracked"]
    assert main([*argv, "--wandb", "coin-test", "--mlflow", store.as_uri()]) == 0
    capsys.readouterr()
    trials = load_trials(tmp_path / "s" / "tracked")
    assert len(trials) == 2 and all(t.finished for t in trials)
    for t in trials:  # one offline W&B run per trial, in the trial's directory, with its history file
        runs = list((t.path / "wandb").glob("offline-run-*"))
        assert len(runs) == 1 and any(runs[0].glob("*.wandb"))
    import mlflow

    client = mlflow.tracking.MlflowClient(tracking_uri=store.as_uri())
    found = client.search_runs([client.get_experiment_by_name("tracked").experiment_id])
    assert len(found) == 2
    for run in found:  # each trial's env-step curve is in MLflow as Tune reported it
        history = [m.value for m in client.get_metric_history(run.info.run_id, "env_steps")]
        assert history == sorted(history) and history[-1] >= 1000


@pytest.fixture
def ray_tmp():
    """A fresh RAY_TMPDIR, short (Ray's socket paths must fit in 107 characters), removed afterwards."""
    path = tempfile.mkdtemp(prefix="cr", dir="/tmp")
    yield path
    shutil.rmtree(path, ignore_errors=True)


def _wait_for(condition, timeout: float, what: str) -> None:
    t0 = time.time()
    while not condition():
        if time.time() - t0 > timeout:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.5)


def test_sweep_killed_with_sigkill_leaves_no_ray_process_and_resumes_without_rerunning_or_losing_anything(tmp_path, capsys, ray_tmp):
    storage = tmp_path / "sweeps"
    argv = ["sweep", "seeds", "--smoke", "--seeds", "0", "1", "--max-concurrent", "1"]
    argv += ["--num-cpus", "1", "--storage", str(storage), "--name", "killed"]
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1", "RAY_TMPDIR": ray_tmp}
    log = open(tmp_path / "driver.log", "w")
    driver = subprocess.Popen([sys.executable, "-m", "coin_app", *argv], cwd=REPO, env=env, stdout=log, stderr=log, start_new_session=True)
    exp_dir = storage / "killed"

    def trials():
        return load_trials(exp_dir, live=True) if (exp_dir / "coin_sweep.json").exists() else []

    try:  # kill -9 once the first trial has finished and the second is mid-way (checkpointed, not finished)
        _wait_for(
            lambda: any(t.finished for t in trials()) and any(t.checkpoints and not t.finished for t in trials()), 400, "a mid-way sweep"
        )
        assert _ray_processes(ray_tmp), f"the sweep's Ray should be running: {_processes_with_env(ray_tmp)}"
    finally:
        driver.send_signal(signal.SIGKILL)
        driver.wait()
        log.close()
    try:  # Ray's agents outlived a kill -9 of the driver before tuning/reaper.py; now nothing of this sweep's Ray is left
        _wait_for(lambda: not _processes_with_env(ray_tmp), 90, f"the sweep's Ray processes to exit: {_processes_with_env(ray_tmp)}")
    finally:
        try:
            os.killpg(driver.pid, signal.SIGKILL)  # whatever the reaper missed, so that a failure leaves nothing running
        except ProcessLookupError:
            pass
    before = trials()
    done_before = [t for t in before if t.finished]
    assert len(done_before) == 1
    first = done_before[0]
    snapshot = {
        "results": (first.path / "result.json").read_bytes(),
        "checkpoints": {c.name: sorted(p.name for p in c.rglob("*")) for c in first.checkpoints},
    }
    interrupted = next(t for t in before if not t.finished)
    resumed_from = json.loads((interrupted.checkpoints[-1] / "coin_app.json").read_text())
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
    # its clocks continued from the checkpoint's: the first row after the restore is the checkpoint's time plus its own
    # iteration's (Tune's time_this_iter_s), not that iteration's alone
    first_after = [r for r in resumed.results if r["env_steps"] == resumed_from["env_steps"] + 500][-1]
    assert first_after["wall_s"] >= resumed_from["wall_s"] + first_after["time_this_iter_s"] - 0.05
    assert first_after["cpu_s"] > resumed_from["cpu_s"]
    # progress.csv: every row of the resumed trial under the right header (one column order across the restore)
    _check_progress_aligned(resumed)


def _check_progress_aligned(trial) -> None:
    """Every row of a trial's progress.csv under the right header."""
    header, rows = read_table(trial.path / "progress.csv")
    assert len(header) == len(set(header)) and rows
    for row in rows:
        assert None not in row and float(row["env_steps"]).is_integer() and float(row["training_iteration"]).is_integer()
        assert row["done"] in ("True", "False") and row["trial_id"] == rows[0]["trial_id"]


FAULT_KILLS = int(os.environ.get("COIN_FAULT_KILLS", "0"))


@pytest.mark.skipif(FAULT_KILLS < 1, reason="fault injection run: COIN_FAULT_KILLS=N kills the sweep driver at N random points")
def test_sweep_killed_at_random_points_loses_nothing(tmp_path, capsys):
    """SIGKILL a sweep driver at seeded random moments (inside saves or not), resume after each, then check the whole."""

    rng = random.Random(int(os.environ.get("COIN_FAULT_SEED", "0")))
    storage = tmp_path / "sweeps"
    argv = ["sweep", "seeds", "--smoke", "--seeds", "0", "1", "2", "--steps", "3000", "--max-concurrent", "1"]
    argv += ["--num-cpus", "1", "--storage", str(storage), "--name", "faults"]
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    exp_dir = storage / "faults"

    def trials():
        return load_trials(exp_dir, live=True) if (exp_dir / "coin_sweep.json").exists() else []

    finished: dict[str, bytes] = {}  # trial -> its result.json when first seen finished
    for k in range(FAULT_KILLS):
        if len(finished) == 3:
            break
        run = [*argv, "--resume"] if (exp_dir / "coin_sweep.json").exists() else argv
        with open(tmp_path / f"driver{k}.log", "w") as log:
            driver = subprocess.Popen(
                [sys.executable, "-m", "coin_app", *run], cwd=REPO, env=env, stdout=log, stderr=log, start_new_session=True
            )
            delay = rng.uniform(4.0, 30.0)
            time.sleep(delay)
            driver.send_signal(signal.SIGKILL)
            driver.wait()
        time.sleep(1)
        try:
            os.killpg(driver.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        for t in trials():
            if t.finished:
                finished.setdefault(t.name, (t.path / "result.json").read_bytes())
        with capsys.disabled():
            saved = sum(len(t.checkpoints) for t in trials())
            print(f"kill {k + 1} after {delay:.1f} s: {len(finished)} trial(s) finished, {saved} checkpoint(s) on disk", flush=True)
    assert main([*argv, "--resume"] if (exp_dir / "coin_sweep.json").exists() else argv) == 0
    capsys.readouterr()
    after = trials()
    assert sorted(t.name for t in after) == ["cig_td3-s0", "cig_td3-s1", "cig_td3-s2"]  # every trial, exactly once
    assert len(list(exp_dir.glob("*/params.json"))) == 3
    assert all(t.finished and t.last["env_steps"] >= 3000 for t in after)
    for t in after:
        if t.name in finished:  # finished before a kill: not rerun
            assert (t.path / "result.json").read_bytes() == finished[t.name]
        steps = [r["env_steps"] for r in t.results]
        assert steps[0] == 500 and steps[-1] >= 3000 and steps == sorted(steps)  # never went back past a checkpoint
        _check_progress_aligned(t)
        for c in t.checkpoints:  # a torn leftover would have failed its trial's restore above; count them for the record
            try:
                verify(c)
            except ValueError as e:
                with capsys.disabled():
                    print(f"torn leftover (never restored): {e}", flush=True)


def test_progress_rows_follow_the_existing_header_and_new_keys_extend_it(tmp_path):
    path = tmp_path / "progress.csv"
    write_table(path, ["env_steps", "learner/lr", "done"], [{"env_steps": 500, "learner/lr": 0.1, "done": False}])
    header, rows = read_table(path)
    # a restored process reports the same keys in another order, plus a new one
    columns, row = aligned_row(header, {"done": True, "eval/success": 0.5, "learner/lr": 0.2, "env_steps": 1000})
    assert columns == ["env_steps", "learner/lr", "done", "eval/success"]
    assert list(row) == columns and row == {"env_steps": 1000, "learner/lr": 0.2, "done": True, "eval/success": 0.5}
    write_table(path, columns, [*rows, row])
    header, rows = read_table(path)
    assert header == columns and rows[0]["eval/success"] == "" and rows[1]["learner/lr"] == "0.2" and rows[1]["env_steps"] == "1000"


def _ray_processes(text: str) -> list[str]:
    """Those of :func:`_processes_with_env` that are Ray's own (its raylet or GCS), not the driver or the reaper."""
    return [c for c in _processes_with_env(text) if "raylet" in c or "gcs_server" in c]


def _processes_with_env(text: str) -> list[str]:
    """Command lines of live processes whose environment contains ``text`` (Linux /proc; Ray retitles its processes)."""
    found = []
    for environ in Path("/proc").glob("[0-9]*/environ"):
        try:
            if text.encode() in environ.read_bytes():
                found.append((environ.parent / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")[:160])
        except OSError:
            continue
    return found


def test_sweep_driver_stopped_with_sigterm_leaves_no_ray_process_and_no_traceback(tmp_path, ray_tmp):
    """SIGTERM (kill -9 is the killed-sweep test above, which also resumes)."""
    sig = signal.SIGTERM
    storage = tmp_path / "sweeps"
    argv = ["sweep", "seeds", "--smoke", "--seeds", "0", "--num-cpus", "1", "--storage", str(storage), "--name", "stop"]
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1", "RAY_TMPDIR": ray_tmp}
    with open(tmp_path / "driver.log", "w") as log:
        driver = subprocess.Popen([sys.executable, "-m", "coin_app", *argv], cwd=REPO, env=env, stdout=log, stderr=log)
        try:
            _wait_for(lambda: any(storage.glob("stop/*/result.json")), 300, "a running trial")
            assert _ray_processes(ray_tmp), f"the sweep's Ray should be running: {_processes_with_env(ray_tmp)}"
            driver.send_signal(sig)
            driver.wait(timeout=120)
        finally:
            if driver.poll() is None:
                driver.kill()
    _wait_for(lambda: not _processes_with_env(ray_tmp), 90, f"the sweep's Ray processes to exit: {_processes_with_env(ray_tmp)}")
    assert "Traceback" not in (tmp_path / "driver.log").read_text()


def _crafted_sweep(root: Path) -> Path:
    """A sweep directory with Tune's experiment state for three trials (a finished, an errored, a finished), no Ray."""
    path = root / "crafted"
    path.mkdir(parents=True)
    (path / "coin_sweep.json").write_text(json.dumps({"experiment": "seeds", "methods": ["a", "b"]}))
    trials = [("a-s0_1", "a", "TERMINATED"), ("b-s0_2", "b", "ERROR"), ("a-s1_3", "a", "TERMINATED")]
    data = [[json.dumps({"status": st, "config": {"algo": algo}, "relative_logdir": name}), "{}"] for name, algo, st in trials]
    for name, _, _ in trials:
        (path / name).mkdir()
        (path / name / "result.json").write_text("{}\n")
    state = path / "experiment_state-2026-01-01_00-00-00.json"
    state.write_text(json.dumps({"trial_data": data, "runner_data": {}, "stats": {}}))
    os.utime(state, (time.time() - 3600, time.time() - 3600))
    return path


def test_restart_marks_the_methods_trials_moves_their_directories_and_guards_a_plain_resume(tmp_path, capsys):
    path = _crafted_sweep(tmp_path)
    settings = json.loads((path / "coin_sweep.json").read_text())
    with pytest.raises(ValueError, match=r"errored trials of other methods \(b-s0_2\); allowed: resume them first"):
        sweep_module.check_restart(path, ("a",), settings, True)
    with pytest.raises(ValueError, match="--restart c: not a method of"):
        sweep_module.check_restart(path, ("b", "c"), settings, True)
    with pytest.raises(ValueError, match="allowed: a sweep in a local directory"):
        sweep_module.check_restart(path, ("a",), settings, False)
    names, dest = sweep_module.restart_trials(path, ("a", "b"), "the command")
    assert names == ["a-s0_1", "b-s0_2", "a-s1_3"]
    assert sorted(p.name for p in dest.iterdir()) == sorted(names) and not any((path / n).exists() for n in names)
    state = json.loads(next(path.glob("experiment_state-*.json")).read_text())
    assert [json.loads(t)["status"] for t, _ in state["trial_data"]] == ["ERROR"] * 3  # Tune restarts errored trials
    after = json.loads((path / "coin_sweep.json").read_text())
    assert after["restart_pending"] == ["a", "b"] and after["restarts"][0]["command"] == "the command"
    # a crash before the rerun: a plain --resume is refused before any work, the same --restart is the way on
    assert main(["sweep", "seeds", "--storage", str(tmp_path), "--name", "crafted", "--resume"]) == 2
    assert "has an unfinished --restart of a b; allowed: --resume --restart a b" in capsys.readouterr().err


def test_a_scale_fits_its_scenes_or_refuses_the_others_in_one_line():
    seeds = get_experiment("seeds")
    # the reduced protocol was chosen on the intersection: other scenes are refused before any work
    for scenario in ("roundabout", "bottleneck"):
        with pytest.raises(ValueError) as err:
            seeds.param_space(scenario, "reduced", methods=("cig_td3",))
        assert "\n" not in str(err.value) and f"not the {scenario}; allowed: --scenario intersection" in str(err.value)
    assert main(["sweep", "seeds", "--scale", "reduced", "--scenario", "roundabout", "--algos", "cig_td3", "--seeds", "0"]) == 2
    # the quick scenario (smoke scale, --quick) fits each scene's longest route as 300 steps fit the intersection's 150.5 m
    road = {s: registry.longest_route(s) for s in ("intersection", "roundabout", "bottleneck")}
    assert road["intersection"] == pytest.approx(150.5) and road["bottleneck"] == pytest.approx(170.0)
    for scenario, metres in road.items():
        quick = registry.quick_scenario(scenario)
        assert quick["horizon"] == quick["max_agent_steps"] and quick["horizon"] % 10 == 0
        assert abs(quick["horizon"] - 300 * metres / road["intersection"]) <= 5  # to the nearest 10 steps
    smoke = {t["seed"]: t for t in validate_trials(seeds.param_space("roundabout", "smoke", methods=("ippo",)))}
    assert trial_overrides(smoke[0])["horizon"] == registry.quick_scenario("roundabout")["horizon"] > 600


def _real_crafted_sweep(root: Path) -> Path:
    """A smoke seeds sweep of itd3 (seeds 0 and 1) as its driver leaves it, without running it: settings and Tune's state."""

    space = get_experiment("seeds").param_space("intersection", "smoke", ("itd3",), (0, 1), 300, {})
    trials = expand_grid(space)
    path = root / "seeds-intersection-smoke"
    path.mkdir(parents=True)
    settings = {"experiment": "seeds", "scenario": "intersection", "scale": "smoke", "methods": ["itd3"], "code_version": "v-then"}
    sweep_module.write_settings(path, settings | {sweep_module.RESOLVED: sweep_module.resolved_settings(trials)})
    data = [[json.dumps({"status": "PENDING", "config": t, "relative_logdir": trial_name(t)}), "{}"] for t in trials]
    (path / "experiment_state-2026-01-01_00-00-00.json").write_text(json.dumps({"trial_data": data, "runner_data": {}, "stats": {}}))
    assert registry.get("itd3").presets["smoke"].warmup_steps == 200
    return path


def test_resume_refuses_settings_the_code_now_resolves_differently_and_accept_changes_records_them(tmp_path, monkeypatch, capsys):

    path = _real_crafted_sweep(tmp_path)
    argv = ["sweep", "seeds", "--smoke", "--algos", "itd3", "--storage", str(tmp_path), "--resume"]
    settings = json.loads((path / "coin_sweep.json").read_text())
    assert sweep_module.check_protocol(path, settings, (), False, "cmd", print) == settings  # the same code: nothing changed
    itd3 = registry.get("itd3")
    monkeypatch.setitem(itd3.presets, "smoke", dataclasses.replace(itd3.presets["smoke"], warmup_steps=300))  # the scale edited since
    monkeypatch.setattr(itd3.settings.__dataclass_fields__["tau"], "default", 0.01)  # and a declared default
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "this code resolves other settings than the sweep ran with (" in err
    assert "warmup_steps: 200 -> 300 (2 trial(s))" in err and "tau: 0.005 -> 0.01 (2 trial(s))" in err
    assert "allowed: --accept-changes to continue with them (recorded), --restart METHOD" in err and "(v-then)" in err
    assert json.loads((path / "coin_sweep.json").read_text()) == settings  # refused: nothing written
    # --accept-changes: continues, and the sweep's record says what changed, when and by which command
    after = sweep_module.check_protocol(path, settings, (), True, "the accepting command", print)
    assert "--accept-changes: the trials continue with 2 changed setting(s): tau, warmup_steps" in capsys.readouterr().out
    (entry,) = after[sweep_module.ACCEPTED]
    assert entry["command"] == "the accepting command" and entry["changes"]["warmup_steps"] == "200 -> 300 (2 trial(s))"
    assert all(t["warmup_steps"] == 300 and t["tau"] == 0.01 for t in after[sweep_module.RESOLVED].values())
    assert json.loads((path / "coin_sweep.json").read_text()) == after
    assert sweep_module.check_protocol(path, after, (), False, "cmd", print) == after  # accepted: the next --resume goes on
    # a restarted method's trials run this code's settings afresh: not a change to refuse
    assert (
        sweep_module.check_protocol(path, settings, ("itd3",), False, "cmd", print)[sweep_module.RESOLVED] == after[sweep_module.RESOLVED]
    )


def test_a_trial_restore_refuses_a_checkpoint_of_another_network_than_this_code_builds(tmp_path):
    """What ``CoinTrial.load_checkpoint`` checks before RLlib's restore (which printed 180 lines of size mismatch)."""
    from types import SimpleNamespace

    import torch

    from coin_app.algorithms.checkpoint_files import SHAPES_KEY
    from coin_app.training import check_restorable

    def algo(module):
        return SimpleNamespace(learner_group=SimpleNamespace(_learner=SimpleNamespace(module={"shared": module})))

    meta = {SHAPES_KEY: {"weight": [16, 91], "bias": [16], "actor_target.weight": [16, 91]}}
    check_restorable(algo(torch.nn.Linear(91, 16)), tmp_path, meta, "x")  # the same network (targets are the learner's own)
    hint = "sweep --resume --restart itd3 (reruns its trials with this code)"
    with pytest.raises(ValueError, match=r"holds another network than this code builds \(bias: \(16,\) in the checkpoint, \(32,\) in this"):
        check_restorable(algo(torch.nn.Linear(91, 32)), tmp_path, meta, hint)
    check_restorable(algo(torch.nn.Linear(91, 32)), tmp_path, {}, hint)  # a checkpoint without recorded shapes: not checked
