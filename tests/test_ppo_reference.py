"""The PPO-family baselines as their authors ran them (CoPO's Ray 1.2 paper runs): the train batch, CoPO's evaluation LCF,
the adaptive-KL signal, per-agent time-outs, advantage standardization and normc initialization."""

import copy
import math
import zlib

import numpy as np
import pytest
import torch
from fixtures import NO_BRAKES, tiny
from ray.rllib.connectors.connector_v2 import ConnectorV2
from ray.rllib.core.columns import Columns
from ray.rllib.evaluation.postprocessing import Postprocessing

from coin_app.adapters.lcf import SampledLCFPolicy, encode, vehicle_lcf
from coin_app.algorithms.checkpoints import actor_policy, export_actor
from coin_app.algorithms.common import SHARED_MODULE_ID, coin_envs
from coin_app.algorithms.ppo_family.learner import EPOCH_KL_KEY, OLD_VALUES
from coin_app.algorithms.ppo_family.losses import last_epoch_mean
from coin_app.algorithms.ppo_family.settings import DEFAULT
from coin_app.evaluation.evaluate import evaluate_policy
from coin_app.evaluation.policies import with_lcf
from coin_app.inference import export_policy, load_policy
from coin_app.sim.rollout import AgentPolicy
from coin_app.sim.scenarios import config_from_dict
from coin_app.training import build_config, fresh_module
from tuning import get_experiment
from tuning.experiment import expand_grid, trial_overrides
from tuning.trainable import build_trial_config

PPO_FAMILY = ("ippo", "cppo", "mfpo", "copo")
TINY = {"num_agents": 3, "horizon": 40, "max_agent_steps": 40, "hidden": 16}


def trial(algo: str, scale: str) -> dict:
    """Seed 0's trial config of ``algo`` in the seeds experiment at ``scale``."""
    return next(t for t in expand_grid(get_experiment("seeds").param_space("intersection", scale, methods=(algo,))) if t["seed"] == 0)


# ---------------------------------------------------------------- 1. the train batch


@pytest.mark.parametrize("algo", PPO_FAMILY)
def test_paper_scale_batch_is_1600_env_steps_of_4_runners_x_200_step_chunks(algo):
    cfg = build_trial_config(trial(algo, "paper"))
    assert (cfg.total_train_batch_size, cfg.num_env_runners, cfg.get_rollout_fragment_length()) == (1600, 4, 200)
    assert cfg.count_steps_by == "env_steps"
    # the batched runner's automatic envs per runner: one sampling round of 4 runners x 2 envs x 200 env steps = 1600
    assert cfg.num_envs_per_env_runner == 2 and 4 * 2 * 200 == cfg.total_train_batch_size
    # RLlib's runner (one env each) samples until the batch is full: 2 rounds of 4 x 200, exactly 1600 as well
    base = trial(algo, "paper")
    reference = build_trial_config({**base, "overrides": {**base["overrides"], "env_runner": "multi_agent"}})
    assert reference.num_envs_per_env_runner == 1 and reference.total_train_batch_size == 1600
    # the algorithm's own defaults are the reference batch and chunk, sampled in the training process
    default = build_config(algo, "intersection", {}, 0)
    assert (default.total_train_batch_size, default.get_rollout_fragment_length(), default.num_env_runners) == (1600, 200, 0)
    # the smoke scale stays cheap
    smoke = build_trial_config(trial(algo, "smoke"))
    assert (smoke.total_train_batch_size, smoke.get_rollout_fragment_length(), smoke.num_env_runners) == (256, 128, 0)


def test_paper_scale_sampling_really_gives_4_chunks_of_200_and_an_update_on_1600_env_steps(ray_session):
    settings = trial_overrides(trial("ippo", "paper")) | TINY | {"minibatch_size": 400, "num_epochs": 1}
    cfg = build_config("ippo", "intersection", settings, 0).env_runners(num_cpus_per_env_runner=0)  # 4 runners on a 2-CPU test Ray
    algo = cfg.build_algo()
    try:
        result = algo.train()
        assert result["env_runners"]["num_env_steps_sampled"] == 1600
        chunks = algo.env_runner_group.foreach_env_runner(lambda r: sum(e.env_steps() for e in r.sample()), local_env_runner=False)
        assert chunks == [400, 400, 400, 400]  # 2 envs x 200-step chunks per runner
    finally:
        algo.stop()


# ---------------------------------------------------------------- 3. the adaptive-KL signal


def test_last_epoch_mean_by_hand():
    assert last_epoch_mean([0.05, 0.04, 0.003, 0.025], 2) == pytest.approx(0.014)  # epochs [0.05, 0.04] [0.003, 0.025]
    assert last_epoch_mean([1.0, 2.0, 3.0, 4.0, 5.0], 2) == pytest.approx(4.0)  # ceil(5 / 2) = 3 per epoch: [3, 4, 5]
    assert last_epoch_mean([7.0], 5) == 7.0
    with pytest.raises(ValueError, match="at least one value"):
        last_epoch_mean([], 1)


# (KLs of 4 minibatches = 2 epochs of 2) per update; target 0.01: x1.5 above 0.02, x0.5 below 0.005
SCRIPT = [[0.05, 0.04, 0.003, 0.025], [0.001, 0.002, 0.030, 0.012], [0.02, 0.02, 0.003, 0.006], [0.01, 0.01, 0.0, 0.001]]
# epoch means 0.014 (keep), 0.021 (x1.5), 0.0045 (x0.5), 0.0005 (x0.5); last minibatch 0.025 (x1.5), 0.012, 0.006, 0.001 (x0.5)
EXPECTED = {"epoch_mean": [0.2, 0.3, 0.15, 0.075], "last_minibatch": [0.3, 0.3, 0.3, 0.15]}


@pytest.mark.parametrize("signal", ["epoch_mean", "last_minibatch"])
def test_kl_coefficient_follows_the_hand_computed_sequence(signal):
    cfg = build_config("ippo", "intersection", {**TINY, "num_epochs": 2, "kl_signal": signal}, 0)
    module = fresh_module("ippo", overrides=TINY)
    learner = cfg.build_learner(spaces={SHARED_MODULE_ID: (module.observation_space, module.action_space)})
    assert learner.curr_kl_coeffs_per_module[SHARED_MODULE_ID].item() == pytest.approx(0.2)
    betas = []
    for kls in SCRIPT:
        learner.before_gradient_based_update(timesteps={})
        for kl in kls:
            learner.record_kl(SHARED_MODULE_ID, torch.tensor(kl))
        learner.after_gradient_based_update(timesteps={})
        betas.append(learner.curr_kl_coeffs_per_module[SHARED_MODULE_ID].item())
    assert betas == pytest.approx(EXPECTED[signal])


def test_a_training_update_adapts_the_kl_coefficient_to_its_last_epoch_mean(ray_session):
    _, settings = tiny("ippo", "intersection")
    algo = build_config("ippo", "intersection", settings, 0).build_algo()
    try:
        learner = algo.learner_group._learner
        before = learner.curr_kl_coeffs_per_module[SHARED_MODULE_ID].item()
        stats = algo.train()["learners"][SHARED_MODULE_ID]
        kl = float(stats[EPOCH_KL_KEY])
        factor = 1.5 if kl > 0.02 else 0.5 if kl < 0.005 else 1.0
        assert float(stats["curr_kl_coeff"]) == pytest.approx(before * factor)
    finally:
        algo.stop()


# ---------------------------------------------------------------- 4. per-agent time-outs, and advantage standardization


@pytest.fixture(scope="module")
def timeout_batches(ray_session):
    """Episodes of vehicles that time out after 20 own steps (random actions), and the learner batch of each setting.

    Cars without brakes leave the road early and respawn, so time-outs come at different env steps (vehicles that all end
    in one step end the episode, which RLlib records as terminated anyway).
    """
    settings = {"num_agents": 5, "horizon": 200, "max_agent_steps": 20, "delay_done": 0, "dynamics": NO_BRAKES, "hidden": 16}
    settings |= {"train_batch_size_per_learner": 100, "rollout_fragment_length": 50, "minibatch_size": 50}
    algo = build_config("ippo", "intersection", settings, 0).build_algo()
    try:
        for env in coin_envs(algo.env_runner):  # one action space object serves every agent: seeded, the sample is reproducible
            env.action_spaces[env.possible_agents[0]].seed(0)
        episodes = algo.env_runner.sample(num_timesteps=200, random_actions=True)  # 2 envs x 100 steps (seeded runner RNG)
        reference = algo.learner_group._learner
        bootstrap_cfg = build_config("ippo", "intersection", {**settings, "timeout_bootstrap": True}, 0)
        module = reference.module[SHARED_MODULE_ID].unwrapped()
        torch.manual_seed(0)
        with torch.no_grad():  # values far from 0, so a bootstrap with V(o_T) and one with 0 differ clearly
            for p in module.parameters():
                p.add_(0.3 * torch.randn_like(p))
        option = bootstrap_cfg.build_learner(spaces={SHARED_MODULE_ID: (module.observation_space, module.action_space)})
        option.module.set_state(reference.module.get_state())
        out = {}
        for name, learner in (("reference", reference), ("option", option)):
            batch = learner._learner_connector(rl_module=learner.module, batch={}, episodes=copy.deepcopy(episodes), shared_data={})
            out[name] = batch[SHARED_MODULE_ID]
        yield out, module, copy.deepcopy(episodes)
    finally:
        algo.stop()


def test_a_per_agent_time_out_bootstraps_with_zero_by_default_and_with_v_as_the_option(timeout_batches):
    out, module, episodes = timeout_batches
    gamma = DEFAULT.gamma
    agents = ConnectorV2.single_agent_episode_iterator(episodes, agents_that_stepped_only=False)  # the batch's order
    timed_out = cut = 0
    start = 0
    for sa in agents:
        n = len(sa)  # real rows of the episode chunk, then RLlib's one bootstrap row
        last = start + n - 1
        np.testing.assert_array_equal(out["reference"][Columns.OBS][last].numpy(), np.asarray(sa.get_observations(n - 1)))
        reward = float(sa.get_rewards(n - 1))
        with torch.no_grad():
            v_final = module.compute_values({Columns.OBS: torch.as_tensor(np.asarray(sa.get_observations(n))[None], dtype=torch.float32)})
        ref, opt = (float(out[k][Postprocessing.VALUE_TARGETS][last]) for k in ("reference", "option"))
        if sa.is_truncated and not sa.is_terminated:  # the vehicle's own step limit
            timed_out += 1
            assert ref == pytest.approx(reward, abs=1e-5)  # Ray 1.x: every done is terminal
            assert opt == pytest.approx(reward + gamma * float(v_final), abs=1e-5)  # RLlib: V(o_T)
            assert abs(opt - ref) > 1e-3
        elif not sa.is_done:  # cut by the sampling chunk: both bootstrap with V
            cut += 1
            assert ref == pytest.approx(reward + gamma * float(v_final), abs=1e-5)
            assert opt == pytest.approx(ref, abs=1e-6)
        start += n + 1
    assert start == len(out["reference"][Columns.OBS])
    assert timed_out >= 3 and cut >= 1


def test_advantages_are_standardized_over_the_real_rows_only(timeout_batches):
    out, module, _ = timeout_batches
    batch = out["reference"]
    real = batch[Columns.LOSS_MASK].numpy().astype(bool)
    with torch.no_grad():
        values = module.compute_values({Columns.OBS: batch[Columns.OBS]}).numpy()
    raw = batch[Postprocessing.VALUE_TARGETS].numpy() - values
    want = (raw - raw[real].mean()) / raw[real].std()
    np.testing.assert_allclose(batch[Postprocessing.ADVANTAGES].numpy()[real], want[real], atol=1e-4)
    adv = batch[Postprocessing.ADVANTAGES].numpy()[real]
    assert abs(adv.mean()) < 1e-5 and adv.std() == pytest.approx(1.0, abs=1e-4)
    np.testing.assert_allclose(batch[OLD_VALUES].numpy(), values, atol=1e-6)
    assert (~real).sum() >= 1  # RLlib's bootstrap rows are there, and left out of the statistics


# ---------------------------------------------------------------- 5. normc initialization


@pytest.mark.parametrize("algo", PPO_FAMILY)
def test_normc_gives_unit_hidden_rows_and_0_01_output_rows(algo):
    module = fresh_module(algo, overrides={"hidden": 32})
    outputs = {"pi.net.mlp.0.weight", "vf.net.mlp.0.weight", "central_vf.4.weight", "nei_vf.4.weight", "global_vf.4.weight"}
    seen = set()
    for name, p in module.named_parameters():
        if name.endswith(".bias"):
            assert torch.count_nonzero(p) == 0, name
            continue
        norms = p.detach().norm(dim=1)
        want = 0.01 if name in outputs else 1.0
        torch.testing.assert_close(norms, torch.full_like(norms, want), rtol=1e-5, atol=0, msg=name)
        seen.add(name)
    assert {"pi.net.mlp.0.weight", "vf.net.mlp.0.weight"} <= seen
    assert ("central_vf.4.weight" in seen) == (algo in ("cppo", "mfpo")) and ("global_vf.4.weight" in seen) == (algo == "copo")


def test_normc_initial_action_scale_is_the_hand_computed_one():
    # normc output rows u have norm 0.01 and a uniform direction, so E[(u . h)^2] = 0.01^2 ||h||^2 / d: the action means'
    # RMS is 0.01 * RMS(h) over the hidden units h of the actor encoder; their log stds are as small, so the std is ~1
    obs = torch.as_tensor(np.random.default_rng(0).uniform(0.0, 1.0, (200, 91)), dtype=torch.float32)
    means, hidden, log_std = [], [], []
    for seed in range(12):
        torch.manual_seed(seed)
        module = fresh_module("ippo", seed=seed)
        with torch.no_grad():
            out = module.forward_inference({Columns.OBS: obs})[Columns.ACTION_DIST_INPUTS]
            hidden.append(module.encoder.actor_encoder.net.mlp(obs))
        means.append(out[:, :2])
        log_std.append(out[:, 2:])
    rms = torch.cat(means).pow(2).mean().sqrt().item()
    assert rms == pytest.approx(0.01 * torch.cat(hidden).pow(2).mean().sqrt().item(), rel=0.3)
    assert rms < 0.01 and torch.cat(log_std).abs().max() <= 0.01 * math.sqrt(256)
    torch.manual_seed(0)
    default = fresh_module("ippo", overrides={"weight_init": "torch"})
    with torch.no_grad():
        torch_rms = default.forward_inference({Columns.OBS: obs})[Columns.ACTION_DIST_INPUTS][:, :2].pow(2).mean().sqrt().item()
    assert torch_rms > 5 * rms  # PyTorch's default starts with clearly larger action means


def test_bad_reference_options_are_refused():
    for key, value in (("kl_signal", "median"), ("timeout_bootstrap", 1), ("weight_init", "xavier"), ("eval_lcf", "max")):
        with pytest.raises(ValueError, match=f"bad value for '{key}'"):
            build_config("copo", "intersection", {key: value}, 0)


# ---------------------------------------------------------------- 2. CoPO at evaluation


def test_vehicle_lcfs_are_seeded_per_vehicle_and_follow_the_distribution():
    draws = np.array([vehicle_lcf(0.3, 0.2, 0, 7, f"agent{i}") for i in range(4000)])
    assert draws.mean() == pytest.approx(0.3, abs=0.02) and draws.std() == pytest.approx(0.2, abs=0.02)
    assert vehicle_lcf(0.3, 0.2, 0, 7, "agent5") == draws[5]  # reproducible
    rng = np.random.default_rng([0, 7, zlib.crc32(b"agent5"), 0x4C434645])  # the documented key: (seed, episode, agent id)
    assert draws[5] == pytest.approx(float(np.clip(rng.normal(0.3, 0.2), -1, 1)))
    assert vehicle_lcf(0.3, 0.2, 0, 8, "agent5") != draws[5] and vehicle_lcf(0.3, 0.2, 1, 7, "agent5") != draws[5]
    wide = [vehicle_lcf(0.9, 5.0, 0, 1, f"agent{i}") for i in range(200)]
    assert min(wide) == -1.0 and max(wide) == 1.0


def test_sampled_lcf_policy_appends_each_vehicles_feature():
    policy = SampledLCFPolicy(lambda x: np.repeat(x[:, -1:], 2, axis=1), mean=-0.2, std=0.5, seed=3)
    assert isinstance(policy, AgentPolicy)
    agents = [(11, "agent0"), (11, "agent1"), (12, "agent0"), (11, "agent0")]
    got = policy.act(np.zeros((4, 5), np.float32), agents)
    want = encode(np.array([vehicle_lcf(-0.2, 0.5, 3, s, a) for s, a in agents]))
    np.testing.assert_allclose(got[:, 0], want, atol=1e-7)
    assert got[0, 0] == got[3, 0] and got[0, 0] != got[1, 0] and got[0, 0] != got[2, 0]
    with pytest.raises(ValueError, match="needs each row's vehicle"):
        policy(np.zeros((1, 5)))
    with pytest.raises(ValueError, match="one \\(episode seed, agent id\\) per observation row"):
        policy.act(np.zeros((2, 5)), agents)


class Recorder:
    """An agent-aware policy that records which vehicle (episode seed, agent id) got which observation; full throttle, steering."""

    def __init__(self):
        self.seen: dict[tuple[int, str], list[np.ndarray]] = {}

    def act(self, obs: np.ndarray, agents: list) -> np.ndarray:
        for o, key in zip(obs, agents):
            self.seen.setdefault(key, []).append(o.copy())
        return np.tile([0.6, 1.0], (len(obs), 1))


def test_the_rollout_names_every_row_by_its_episode_seed_and_agent_id():
    config = config_from_dict("intersection", {"num_agents": 4, "horizon": 100, "delay_done": 0})  # off-road at once: respawns
    both, alone = Recorder(), Recorder()
    metrics = evaluate_policy(both, config, [3, 4])
    assert evaluate_policy(alone, config, [4]) == metrics[1:]
    assert {k for k in both.seen if k[0] == 4} == set(alone.seen)  # the same vehicles, whatever runs alongside
    for key, rows in alone.seen.items():
        np.testing.assert_array_equal(np.stack(rows), np.stack(both.seen[key]))
    assert {s for s, _ in both.seen} == {3, 4} and len(alone.seen) > 10  # respawned vehicles get their own keys


@pytest.fixture(scope="module")
def copo_module():
    """A CoPO module with a wide LCF distribution and every weight moved (so the LCF feature changes the actions)."""
    module = fresh_module("copo", overrides={"hidden": 16, "initial_lcf_mean": 0.4, "initial_lcf_std": 0.5})
    torch.manual_seed(0)
    with torch.no_grad():
        for p in module.parameters():
            p.add_(0.5 * torch.randn_like(p))
    return module


def test_copo_evaluates_with_a_sampled_lcf_per_vehicle_by_default(copo_module):
    mean, std = copo_module.lcf_distribution()
    assert copo_module.evaluation_lcf() == "sampled" and std > 0.1
    policy = actor_policy(copo_module)
    assert isinstance(policy, SampledLCFPolicy) and (policy.mean, policy.std) == pytest.approx((mean, std))
    obs = np.random.default_rng(2).uniform(0.0, 1.0, (6, 91)).astype(np.float32)
    agents = [(200000, f"agent{i}") for i in range(6)]
    feature = encode(np.array([vehicle_lcf(mean, std, 0, s, a) for s, a in agents]))
    with torch.no_grad():
        want = copo_module.lcf_inference_actions(torch.as_tensor(np.concatenate([obs, feature[:, None]], 1))).numpy()
    np.testing.assert_allclose(policy.act(obs, agents), want, atol=1e-5)
    assert np.abs(policy.act(obs, agents) - actor_policy(copo_module, lcf="mean")(obs)).max() > 1e-3  # not the mean LCF
    np.testing.assert_allclose(actor_policy(copo_module, lcf="mean")(obs), copo_module.inference_actions(torch.as_tensor(obs)), atol=1e-5)


def test_the_mean_lcf_variant_is_selectable():
    module = fresh_module("copo", overrides={"hidden": 16, "eval_lcf": "mean", "initial_lcf_mean": 0.4})
    assert module.evaluation_lcf() == "mean"
    policy = actor_policy(module)
    assert not isinstance(policy, AgentPolicy)
    obs = np.random.default_rng(3).uniform(0.0, 1.0, (5, 91)).astype(np.float32)
    np.testing.assert_allclose(policy(obs), module.inference_actions(torch.as_tensor(obs)).numpy(), atol=1e-5)
    network, _, extra = export_actor(module)
    assert extra == {} and network[0].in_features == 91  # the export: the mean folded into the plain-observation actor


@pytest.mark.parametrize("fmt", ["numpy", "torchscript"])
def test_a_copo_export_reproduces_the_checkpoints_per_vehicle_draws(copo_module, fmt, tmp_path):
    network, reference, extra = export_actor(copo_module)
    mean, std = copo_module.lcf_distribution()
    assert network[0].in_features == 92 and extra == {"lcf": {"mean": mean, "std": std, "seed": 0}}
    path = export_policy(network, tmp_path / ("a.npz" if fmt == "numpy" else "a.pt"), fmt, meta={"algo": "copo", **extra})
    raw = load_policy(path)
    x = np.random.default_rng(4).uniform(0.0, 1.0, (64, 92)).astype(np.float32)
    np.testing.assert_allclose(raw(x), reference(x), atol=1e-5)  # the export's parity check
    exported, direct = with_lcf(raw), actor_policy(copo_module)
    obs, agents = x[:8, :91], [(200001, f"agent{i}") for i in range(8)]
    np.testing.assert_allclose(exported.act(obs, agents), direct.act(obs, agents), atol=1e-5)
    config = config_from_dict("intersection", {"num_agents": 4, "horizon": 40, "max_agent_steps": 40})
    (from_file,), (from_module,) = evaluate_policy(exported, config, [200002]), evaluate_policy(direct, config, [200002])
    assert from_file.keys() == from_module.keys()
    assert all(from_file[k] == pytest.approx(from_module[k], abs=1e-4, nan_ok=True) for k in from_file)
