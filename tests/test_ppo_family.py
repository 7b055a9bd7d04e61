"""The PPO family: specs, the modules' deterministic actors, the PPO losses by hand, the clipped value loss wiring,
training, checkpoint, export, evaluation."""

import json
import math
import re

import numpy as np
import pytest
import torch
from fixtures import tiny
from ray.rllib.algorithms.ppo.torch.default_ppo_torch_rl_module import DefaultPPOTorchRLModule

from coin_app.algorithms.checkpoints import actor_module, load_module
from coin_app.algorithms.copo.settings import COPO
from coin_app.algorithms.nav_ppo.settings import NAV_PPO
from coin_app.algorithms.ppo_family.centralized import CRITIC_OBS
from coin_app.algorithms.ppo_family.learner import OLD_VALUES, OldValuePredictions
from coin_app.algorithms.ppo_family.losses import clipped_value_loss, surrogate_loss
from coin_app.algorithms.ppo_family.settings import CPPO, IPPO, MFPO, CppoSettings, PpoSettings
from coin_app.algorithms.spec import DRIVING_SCENARIOS, ActorModule
from coin_app.cli import main
from coin_app.training import build_config, fresh_module


def test_specs_declare_keys_capabilities_and_scenarios():
    specs = (IPPO, CPPO, MFPO, COPO, NAV_PPO)
    assert [s.name for s in specs] == ["ippo", "cppo", "mfpo", "copo", "nav_ppo"]
    ippo_keys = PpoSettings.keys()
    assert IPPO.keys() == ippo_keys and CPPO.keys() == MFPO.keys() == (*ippo_keys, "neighbour_radius", "num_neighbours")
    assert COPO.keys()[: len(ippo_keys)] == ippo_keys and "initial_lcf_mean" in COPO.keys()
    assert CPPO.hyperparameters["neighbour_radius"][0] == 40.0 and MFPO.hyperparameters["neighbour_radius"][0] == 10.0
    assert CppoSettings.lift(PpoSettings(hidden=7)) == CppoSettings(hidden=7)  # a family preset lifts into a child's class
    assert all(s.capabilities.on_policy and not s.capabilities.joint_replay for s in specs)
    assert [s.capabilities.centralized_critic for s in specs] == [False, True, True, True, False]
    assert all(s.scenarios == DRIVING_SCENARIOS for s in specs[:4]) and NAV_PPO.scenarios == ("arena",)
    assert all(s.quick == {"hidden": 64} for s in specs)
    assert NAV_PPO.scenario_defaults({})["generator"] == "agnn" and NAV_PPO.scenario_defaults({"stage": "short"})["generator"] == "short"


@pytest.mark.parametrize("name", ["ippo", "cppo", "mfpo", "copo", "nav_ppo"])
def test_deterministic_actor_is_the_clipped_mean_of_forward_inference(name):
    overrides = {"hidden": 16, "initial_lcf_mean": 0.4} if name == "copo" else {"hidden": 16}
    module = fresh_module(name, overrides=overrides)
    assert isinstance(module, ActorModule)
    torch.manual_seed(0)
    with torch.no_grad():  # RLlib initializes the policy head near zero; move every weight so actions differ and clip
        for p in module.parameters():
            p.add_(torch.randn_like(p))
    obs = torch.rand(64, 13 if name == "nav_ppo" else 91)  # CoPO: the plain observation, the learned mean LCF folded in
    with torch.no_grad():
        actions = module.deterministic_actor()(obs)
    assert actions.shape == (64, 2) and actions.abs().max() == 1.0 and (actions.abs() < 1).any()
    torch.testing.assert_close(actions, module.inference_actions(obs), atol=1e-5, rtol=0)  # the export parity bound


def test_a_ppo_module_saved_before_the_contract_still_gives_its_actor():
    new = fresh_module("ippo", overrides={"hidden": 16})
    old = DefaultPPOTorchRLModule(
        observation_space=new.observation_space, action_space=new.action_space, model_config=new.model_config, inference_only=False
    )
    old.load_state_dict(new.state_dict())
    assert not isinstance(old, ActorModule)  # RLlib's class, as a checkpoint of the previous layout stores it
    obs = torch.rand(32, new.observation_space.shape[0])
    with torch.no_grad():
        assert torch.equal(actor_module(old).deterministic_actor()(obs), new.deterministic_actor()(obs))


def test_surrogate_loss_by_hand():
    # ratio 1.5 with A = 2: min(3.0, 1.3 * 2 = 2.6) = 2.6; ratio 0.5 with A = -1: min(-0.5, -0.7) = -0.7
    logp_old = torch.tensor([0.0, 0.0])
    logp_new = torch.log(torch.tensor([1.5, 0.5]))
    loss = surrogate_loss(logp_new, logp_old, torch.tensor([2.0, -1.0]), clip=0.3)
    assert loss.item() == pytest.approx(-(2.6 - 0.7) / 2)


def test_clipped_value_loss_by_hand():
    v, v_old, r = torch.tensor([5.0, 0.0, 2.0]), torch.tensor([1.0, 3.0, 2.0]), torch.tensor([4.0, 0.0, 7.0])
    # clip 2: [max((5-4)^2, (1+2-4)^2) = 1, max(0^2, (3-2-0)^2) = 1, 5^2 = 25]
    assert clipped_value_loss(v, v_old, r, clip=2.0).item() == pytest.approx((1 + 1 + 25) / 3)
    # clip 1: [max(1, (1+1-4)^2) = 4, max(0, (3-1)^2) = 4, 25]: the clipped error wins where V moved far
    assert clipped_value_loss(v, v_old, r, clip=1.0).item() == pytest.approx((4 + 4 + 25) / 3)
    # a large clip is the plain squared error
    assert clipped_value_loss(v, v_old, r, clip=100.0).item() == pytest.approx((1 + 0 + 25) / 3)


_, TINY = tiny("ippo")  # the PPO family's tiny scale (IPPO, CPPO, MFPO and CoPO share it)


def test_ippo_trains_with_the_paper_hyperparameters(ray_session):
    cfg = build_config("ippo", "bottleneck", TINY, 0)
    assert (cfg.lr, cfg.clip_param, cfg.vf_clip_param, cfg.kl_coeff, cfg.entropy_coeff, cfg.lambda_) == (3e-4, 0.3, 10.0, 0.2, 0.0, 0.95)
    assert cfg.model_config["fcnet_activation"] == "tanh" and not cfg.model_config["vf_share_layers"]
    algo = cfg.build_algo()
    try:
        learner = algo.learner_group._learner
        pieces = [type(p).__name__ for p in learner._learner_connector.connectors]
        # old values after GAE, then the advantages standardized over the real rows; time-outs terminal before the extra row
        assert pieces[-3:] == ["GeneralAdvantageEstimation", "OldValuePredictions", "RealRowAdvantages"]
        assert pieces.index("TimeoutsAsTerminal") + 1 == pieces.index("AddOneTsToEpisodesAndTruncate")
        for _ in range(2):
            result = algo.train()
            stats = result["learners"]["shared"]
            for key in ("policy_loss", "vf_loss", "entropy", "mean_kl_loss"):
                assert math.isfinite(float(stats[key])), key
        # the connector piece stores exactly the module's current values
        module = learner.module["shared"].unwrapped()
        obs = torch.rand(7, 91)
        batch = OldValuePredictions()(rl_module=learner.module, batch={"shared": {"obs": obs}}, episodes=[])
        assert torch.allclose(batch["shared"][OLD_VALUES], module.compute_values({"obs": obs}))
    finally:
        algo.stop()


def test_ippo_cli_train_export_evaluate(ray_session, tmp_path, capsys):
    out = tmp_path / "run"
    sets = [f"{k}={v}" for k, v in TINY.items() if k != "num_agents"]
    assert (
        main(
            [
                "train",
                "--algo",
                "ippo",
                "--scenario",
                "bottleneck",
                "--num-agents",
                "3",
                "--steps",
                "200",
                "--out",
                str(out),
                "--set",
                *sets,
            ]
        )
        == 0
    )
    ckpt = out / "checkpoint"
    capsys.readouterr()
    # the deterministic actor is the clipped mean of the Gaussian the module outputs
    module = load_module(ckpt)
    obs = torch.rand(20, 91)
    with torch.no_grad():
        mean = module.forward_inference({"obs": obs})["action_dist_inputs"][:, :2]
        np.testing.assert_allclose(module.deterministic_actor()(obs).numpy(), mean.clamp(-1, 1).numpy(), atol=1e-6)
    assert main(["export", str(ckpt), "--out", str(tmp_path / "ippo.npz")]) == 0
    gap = float(re.search(r"forward_inference\| on 256 random obs = ([0-9.e+-]+)", capsys.readouterr().out).group(1))
    assert gap < 1e-5
    for source in (ckpt, tmp_path / "ippo.npz"):
        assert main(["evaluate", str(source), "--seeds", "3", "--out", str(tmp_path / "e.json")]) == 0
        episodes = json.loads((tmp_path / "e.json").read_text())["episodes"]
        assert episodes[0]["num_vehicles"] >= 3


@pytest.mark.parametrize("variant", ["cppo", "mfpo"])
def test_centralized_variants_train(ray_session, variant):
    algo = build_config(variant, "bottleneck", TINY, 0).build_algo()
    try:
        learner = algo.learner_group._learner
        pieces = [type(p).__name__ for p in learner._learner_connector.connectors]
        assert pieces[-4:] == ["CriticInputs", "GeneralAdvantageEstimation", "OldValuePredictions", "RealRowAdvantages"]
        module = learner.module["shared"].unwrapped()
        dim = 91 + 4 * 93 if variant == "cppo" else 2 * 91 + 2
        assert module.central_vf[0].in_features == dim
        assert not hasattr(algo.env_runner.module["shared"], "central_vf")  # env runners: policy only
        for _ in range(2):
            stats = algo.train()["learners"]["shared"]
            assert math.isfinite(float(stats["vf_loss"])) and math.isfinite(float(stats["policy_loss"]))
        assert module.compute_values({CRITIC_OBS: torch.zeros(3, dim)}).shape == (3,)
    finally:
        algo.stop()
