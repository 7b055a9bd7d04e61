"""RLlib PPO and CIG-TD3 train on the MetaDrive backend; the CLI trains, exports and evaluates there."""

import json
import math

import numpy as np
import pytest

pytest.importorskip("metadrive", reason="the optional MetaDrive extra is not installed (pip install -r requirements-metadrive.txt)")

from ray.rllib.algorithms.ppo import PPOConfig  # noqa: E402
from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig  # noqa: E402

from coin_app.adapters.rllib_env import register_envs  # noqa: E402
from coin_app.algorithms.common import policy_mapping_fn, scenario_config_of  # noqa: E402
from coin_app.backends.metadrive import open_in_this_process  # noqa: E402
from coin_app.cli import main  # noqa: E402
from coin_app.training import build_config  # noqa: E402

SMALL = {"backend": "metadrive", "num_agents": 4, "horizon": 40, "max_agent_steps": 40}


@pytest.fixture(scope="module", autouse=True)
def envs(ray_session):
    register_envs()


def test_ppo_two_iterations_on_metadrive():
    config = (
        PPOConfig()
        .environment("coin-roundabout-v0", env_config=SMALL)
        .env_runners(num_env_runners=0, rollout_fragment_length=100)
        .training(train_batch_size_per_learner=200, minibatch_size=100, num_epochs=1)
        .multi_agent(policies={"shared"}, policy_mapping_fn=policy_mapping_fn)
        .rl_module(model_config=DefaultModelConfig(fcnet_hiddens=[32, 32]))
        .debugging(seed=0)
    )
    algo = config.build_algo()
    try:
        for _ in range(2):
            result = algo.train()
            assert math.isfinite(float(result["learners"]["shared"]["total_loss"]))
        assert result["env_runners"]["num_env_steps_sampled_lifetime"] >= 400
    finally:
        algo.stop()
    assert not open_in_this_process()  # stopping the algorithm shut the engine down


TINY_TD3 = {**SMALL, "warmup_steps": 40, "train_batch_size_per_learner": 16, "hidden": 16}  # ITD3's keys
TINY_CIG_TD3 = {**TINY_TD3, "latent_dim": 4, "node_width": 8}  # and the centralized critic's widths


def test_cig_td3_two_iterations_on_metadrive_with_evaluation():
    cfg = build_config("cig_td3", "intersection", {**TINY_CIG_TD3, "eval_every": 2, "eval_episodes": 1}, 0)
    algo = cfg.reporting(min_sample_timesteps_per_iteration=40).build_algo()
    try:
        results = [algo.train() for _ in range(2)]
        learner = results[-1]["learners"]["shared"]
        for key in ("local_critic_loss", "central_critic_loss", "actor_loss"):
            assert np.isfinite(float(learner[key])), key
        # the env runner holds this process's MetaDrive engine, so evaluation ran in a worker process
        ev = results[1]["coin_eval"]
        assert ev["num_vehicles"] >= 4 and 0.0 <= ev["success_rate"] <= 1.0
    finally:
        algo.stop()
    assert not open_in_this_process()


def test_metadrive_refuses_several_envs_per_runner():
    with pytest.raises(ValueError, match="num_envs_per_env_runner=2 with backend 'metadrive'"):
        build_config("itd3", "intersection", TINY_TD3, 0).env_runners(num_envs_per_env_runner=2).validate()


def test_cli_trains_on_metadrive_exports_and_evaluates_on_both_backends(tmp_path, capsys):
    out = tmp_path / "run"
    args = ["--scenario", "intersection", "--backend", "metadrive", "--num-agents", "3", "--steps", "80", "--out", str(out)]
    args += ["--set", "horizon=30", "max_agent_steps=30", "warmup_steps=40", "train_batch_size_per_learner=16", "hidden=16"]
    assert main(["train", "--algo", "itd3", *args, "eval_every=0"]) == 0
    ckpt = out / "checkpoint"
    assert json.loads((ckpt / "coin_app.json").read_text())["env_config"]["backend"] == "metadrive"
    assert main(["export", str(ckpt), "--out", str(tmp_path / "actor.npz")]) == 0
    assert "parity: max |action - RLModule.forward_inference|" in capsys.readouterr().out
    results = {}
    for name, source, backend in (("ckpt", ckpt, []), ("npz", tmp_path / "actor.npz", []), ("native", ckpt, ["--backend", "native"])):
        target = tmp_path / f"{name}.json"
        assert main(["evaluate", str(source), "--seeds", "7", "8", *backend, "--out", str(target)]) == 0
        results[name] = json.loads(target.read_text())["episodes"]
        assert f"backend {'native' if backend else 'metadrive'}" in capsys.readouterr().out
    # the exported file acts like the checkpoint (to float32 rounding), so MetaDrive gives the same episodes
    assert [e["episode_return"] for e in results["npz"]] == pytest.approx([e["episode_return"] for e in results["ckpt"]], abs=1e-3)
    assert [e["num_vehicles"] for e in results["npz"]] == [e["num_vehicles"] for e in results["ckpt"]]
    assert [e["num_vehicles"] for e in results["native"]] and results["native"] != results["ckpt"]


@pytest.mark.parametrize("algorithm", ["ippo", "cppo", "mfpo", "copo"])
def test_ppo_family_iteration_on_metadrive(algorithm):
    settings = {**SMALL, "train_batch_size_per_learner": 100, "rollout_fragment_length": 50, "minibatch_size": 50, "num_epochs": 1}
    settings |= {"hidden": 16}
    algo = build_config(algorithm, "bottleneck", settings, 0).build_algo()
    try:
        result = algo.train()
        assert math.isfinite(float(result["learners"]["shared"]["vf_loss"]))
        assert scenario_config_of(algo.config).backend == "metadrive"
    finally:
        algo.stop()
    assert not open_in_this_process()
