"""CoPO: LCFs on the env side, neighbour/global rewards, the three GAEs, the coordinated advantage, the meta-gradient."""

import copy
import json
import math

import numpy as np
import pytest
import torch
from fixtures import NO_BRAKES, tiny
from ray.rllib.core.rl_module.rl_module import RLModule

from coin_app.adapters.batched_runner import BatchedEnvRunner
from coin_app.adapters.lcf import LocalCoordination, decode, encode
from coin_app.adapters.rllib_env import CoinMultiAgentEnv
from coin_app.algorithms.common import coin_envs
from coin_app.algorithms.copo.advantages import (
    COORD_MEAN,
    COORD_STD,
    EGO_ADVANTAGES,
    GLOBAL_ADVANTAGES,
    GLOBAL_REWARDS,
    GLOBAL_TARGETS,
    LCF,
    NEI_ADVANTAGES,
    NEI_REWARDS,
    NEI_TARGETS,
    CoPOAdvantages,
)
from coin_app.algorithms.copo.coordination import (
    coordinated_advantage,
    gradient_dot,
    lcf_distribution,
    lcf_objective,
    lcf_parameters,
    neighbour_and_global_rewards,
)
from coin_app.algorithms.ppo_family.losses import surrogate_loss
from coin_app.cli import main
from coin_app.sim.road_map import load_map
from coin_app.training import build_config

RESPAWNING = {"num_agents": 5, "horizon": 60, "max_agent_steps": 60, "delay_done": 0, "dynamics": NO_BRAKES}
TINY = {**tiny("copo")[1], **RESPAWNING}  # CoPO's tiny scale on the respawning scenario


# ---------------------------------------------------------------- LCFs in the env


def test_lcf_draws_are_clipped_seeded_and_kept_per_agent():
    lcf = LocalCoordination(mean=0.9, std=5.0)
    lcf.reset(3)
    obs = {f"agent{i}": np.zeros(4, np.float32) for i in range(200)}
    out, infos = lcf.augment(obs, {a: {} for a in obs})
    values = np.array([infos[a]["lcf"] for a in obs])
    assert values.min() == -1.0 and values.max() == 1.0 and ((values > -1) & (values < 1)).any()
    np.testing.assert_allclose([out[a][-1] for a in obs], (values + 1) / 2, atol=1e-7)
    again, _ = lcf.augment({"agent7": np.ones(4, np.float32)}, {"agent7": {}})  # same life: same value
    assert again["agent7"][-1] == out["agent7"][-1] and np.array_equal(again["agent7"][:4], np.ones(4))
    other = LocalCoordination(mean=0.9, std=5.0)
    other.reset(3)
    assert other.augment(obs, {})[0]["agent5"][-1] == out["agent5"][-1]  # same seed, same draws
    other.reset(4)
    assert other.augment(obs, {})[0]["agent5"][-1] != out["agent5"][-1]
    lcf.set_distribution(-0.25, 0.0)
    new, infos = lcf.augment({"agent200": np.zeros(4, np.float32), "agent0": np.zeros(4, np.float32)}, {"agent200": {}})
    assert infos["agent200"]["lcf"] == -0.25 and new["agent0"][-1] == out["agent0"][-1]  # old agents keep theirs
    assert decode(encode(-0.25)) == pytest.approx(-0.25)


@pytest.mark.parametrize("bad", [{"mean": 1.5, "std": 0.1}, {"mean": 0.0, "std": -1.0}, {"mean": 0.0, "std": float("nan")}])
def test_bad_lcf_distribution_is_refused(bad):
    with pytest.raises(ValueError, match="bad LCF"):
        LocalCoordination(**bad)


def test_env_lcf_persists_over_each_agent_life_and_respawns_draw_anew():
    env = CoinMultiAgentEnv({"scenario": "intersection", **RESPAWNING, "lcf": {"mean": 0.2, "std": 0.4}})
    assert env.observation_spaces["agent0"].shape == (92,) and env.observation_spaces["agent0"].high[-1] == 1.0
    obs, infos = env.reset(seed=5)
    seen = {aid: o[-1] for aid, o in obs.items()}
    rng = np.random.default_rng(0)
    shifted = False
    while env.agents:
        if len(seen) > 7 and not shifted:
            env.set_lcf_distribution(-0.5, 0.0)  # agents spawned after this get exactly -0.5
            shifted, before = True, set(seen)
        obs, _, _, _, infos = env.step({a: rng.uniform(-1, 1, 2) for a in env.agents})
        for aid, o in obs.items():
            assert env.observation_spaces[aid].contains(o)
            assert seen.setdefault(aid, o[-1]) == o[-1], aid  # one value per life
            assert infos[aid]["lcf"] == pytest.approx(decode(o[-1]), abs=1e-6)
            if shifted and aid not in before:
                assert infos[aid]["lcf"] == -0.5
    assert shifted and len(seen) > len(before) and len(set(seen.values())) > 5
    plain = CoinMultiAgentEnv({"scenario": "intersection"})
    with pytest.raises(RuntimeError, match="no local coordination"):
        plain.set_lcf_distribution(0.0, 0.1)
    with pytest.raises(ValueError, match="bad env_config lcf"):
        CoinMultiAgentEnv({"scenario": "intersection", "lcf": {"mean": 0.0, "sd": 1.0}})


# ---------------------------------------------------------------- the math


def test_coordinated_advantage_by_hand():
    a_ego, a_nei = np.array([2.0, 2.0, 2.0, 2.0]), np.array([-1.0, -1.0, -1.0, -1.0])
    got = coordinated_advantage(a_ego, a_nei, np.array([0.0, 1.0, 0.5, -1.0]))
    # LCF 0: selfish; 1: only the neighbours; 0.5 (45 deg): both / sqrt(2); -1: against the neighbours
    np.testing.assert_allclose(got, [2.0, -1.0, 1.0 / math.sqrt(2), 1.0], atol=1e-12)
    t = coordinated_advantage(torch.tensor(a_ego), torch.tensor(a_nei), torch.tensor([0.0, 1.0, 0.5, -1.0]))
    np.testing.assert_allclose(t.numpy(), got, atol=1e-12)


def test_lcf_parameters_round_trip():
    mean, std = lcf_distribution(lcf_parameters(0.3, 0.2))
    assert float(mean) == pytest.approx(0.3) and float(std) == pytest.approx(0.2)
    assert float(lcf_distribution(torch.tensor([50.0, 9.0]))[1]) == pytest.approx(math.exp(2.0))  # log std clipped at 2
    with pytest.raises(ValueError, match="allowed"):
        lcf_parameters(1.0, 0.1)


@pytest.mark.parametrize("seed", range(4))
def test_neighbour_and_global_rewards_against_brute_force(seed):
    rng = np.random.default_rng(seed)
    n = 60
    pos, group, rew = rng.uniform(0, 80, (n, 2)), rng.integers(0, 5, n), rng.normal(size=n)
    nei, glob = neighbour_and_global_rewards(rew, pos, group, 40.0)
    for i in range(n):
        others = [j for j in range(n) if j != i and group[j] == group[i] and np.linalg.norm(pos[j] - pos[i]) < 40.0]
        assert nei[i] == pytest.approx(np.mean(rew[others]) if others else 0.0, abs=1e-5)
        assert glob[i] == pytest.approx(rew[group == group[i]].mean(), abs=1e-5)


def linear_gaussian_logp(theta, obs, actions, log_std=-0.5):
    """log N(a; theta o, exp(log_std)^2) of a 1-d linear Gaussian policy."""
    mean = obs @ theta
    return (-0.5 * ((actions - mean) / math.exp(log_std)) ** 2 - log_std - 0.5 * math.log(2 * math.pi)).squeeze(-1)


def test_meta_gradient_equals_autograd_through_one_policy_step():
    """Two agents in one state with one action, different advantages: the first-order formula is exact there.

    Reference: the policy takes one gradient step on the standardized coordinated advantage,
    theta' = theta + alpha * grad_theta mean(logp * (A_coord(p) - mu) / sigma); then
    d/dp of the global objective J(theta') = -L_clip(theta'; A_glob) by autograd through that step.
    CoPO's update direction -(g_new . g_old) grad_p L_lcf must equal dJ/dp / alpha.
    """
    torch.manual_seed(0)
    theta = torch.randn(3, 1, dtype=torch.float64)
    obs = torch.randn(1, 3, dtype=torch.float64).repeat(2, 1)
    actions = torch.randn(1, 1, dtype=torch.float64).repeat(2, 1)
    a_ego, a_nei = torch.tensor([1.5, -0.7], dtype=torch.float64), torch.tensor([0.2, 2.0], dtype=torch.float64)
    a_glob, noise = torch.tensor([0.9, 0.4], dtype=torch.float64), torch.tensor([0.3, -1.1], dtype=torch.float64)
    mu, sigma, alpha = 0.1, 1.3, 1e-3
    params = lcf_parameters(0.25, 0.3).double().requires_grad_(True)
    logp_behaviour = linear_gaussian_logp(theta, obs, actions).detach()

    def step(p):
        th = theta.clone().requires_grad_(True)
        lcf_mean, lcf_std = lcf_distribution(p)
        adv = (coordinated_advantage(a_ego, a_nei, lcf_mean + lcf_std * noise) - mu) / sigma
        g = torch.autograd.grad((linear_gaussian_logp(th, obs, actions) * adv).mean(), th, create_graph=True)[0]
        return theta + alpha * g

    # reference: autograd through the policy step
    new_theta = step(params)
    j = -surrogate_loss(linear_gaussian_logp(new_theta, obs, actions), logp_behaviour, a_glob, clip=0.3)
    reference = torch.autograd.grad(j, params)[0] / alpha

    # CoPO: g_new (clip loss at the updated policy), g_old (mean logp at the old policy), grad of L_lcf
    theta_new = new_theta.detach().requires_grad_(True)
    theta_old = theta.clone().requires_grad_(True)
    new_loss = surrogate_loss(linear_gaussian_logp(theta_new, obs, actions), logp_behaviour, a_glob, clip=0.3)
    scale = gradient_dot(new_loss, [theta_new], linear_gaussian_logp(theta_old, obs, actions).mean(), [theta_old])
    p = params.detach().clone().requires_grad_(True)
    (scale * lcf_objective(p, a_ego, a_nei, mu, sigma, noise)).backward()
    torch.testing.assert_close(-p.grad, reference, rtol=1e-9, atol=1e-12)
    assert reference.abs().min() > 1e-4  # a non-trivial gradient on both parameters


def test_gradient_dot_by_hand():
    x = torch.tensor([1.0, 2.0], requires_grad=True)
    y = torch.tensor([3.0], requires_grad=True)
    unused = torch.tensor([5.0], requires_grad=True)
    # d(x.x)/dx = 2x = (2, 4); d(3 x0 + x1)/dx = (3, 1): dot 10; y and unused add nothing
    got = gradient_dot((x * x).sum() + 0 * y.sum(), [x, y, unused], 3 * x[0] + x[1], [x, y, unused])
    assert float(got) == pytest.approx(10.0)
    with pytest.raises(ValueError, match="differ in length"):
        gradient_dot(x.sum(), [x], x.sum(), [x, y])


# ---------------------------------------------------------------- with RLlib


def gae(rewards, values, bootstrap, gamma, lam):
    """Plain GAE advantages of one trajectory (loop over time)."""
    values = list(values) + [bootstrap]
    adv, running = [], 0.0
    for t in reversed(range(len(rewards))):
        running = rewards[t] + gamma * values[t + 1] - values[t] + gamma * lam * running
        adv.append(running)
    return np.array(adv[::-1])


@pytest.mark.parametrize("timeout_bootstrap", [False, True])
def test_three_advantages_match_a_reference_implementation(ray_session, timeout_bootstrap):
    algo = build_config("copo", "intersection", {**TINY, "timeout_bootstrap": timeout_bootstrap}, 0).build_algo()
    try:
        learner = algo.learner_group._learner
        pieces = [type(p).__name__ for p in learner._learner_connector.connectors]
        assert pieces[-1] == "CoPOAdvantages" and "GeneralAdvantageEstimation" not in pieces and "OldValuePredictions" not in pieces
        episodes = algo.env_runner.sample(num_timesteps=150, random_actions=True)
        assert any(len(ma.agent_episodes) > 5 for ma in episodes)  # respawns in the sample
        module = learner.module["shared"].unwrapped()
        batch = learner._learner_connector(rl_module=learner.module, batch={}, episodes=copy.deepcopy(episodes), shared_data={})["shared"]
    finally:
        algo.stop()
    scale, gamma, lam = load_map("intersection").scale, 0.99, 0.95
    # brute force: every agent's (env step) -> (position, reward) per episode chunk
    present: dict = {}
    for ma in episodes:
        for aid, sa in ma.agent_episodes.items():
            infos, rewards = sa.get_infos(), sa.get_rewards()
            for t in range(len(sa)):
                present.setdefault((ma.id_, infos[t]["env_step"]), []).append((aid, np.asarray(infos[t]["state"][:2]) * scale, rewards[t]))
    want = {k: [] for k in ("ego", "nei", "glob", "nei_r", "glob_r", "lcf")}
    order = CoPOAdvantages(gamma=gamma, lambda_=lam, radius=40.0, position_scale=scale).single_agent_episode_iterator(episodes, False)
    for sa in order:
        n, infos = len(sa), sa.get_infos()
        obs = torch.as_tensor(np.asarray(sa.get_observations()), dtype=torch.float32)  # n + 1 observations
        with torch.no_grad():
            v = [x.numpy().astype(float) for x in module.compute_all_values({"obs": obs})]
        nei_r, glob_r = [], []
        for t in range(n):
            me = np.asarray(infos[t]["state"][:2]) * scale
            rows = present[(sa.multi_agent_episode_id, infos[t]["env_step"])]
            near = [r for aid, p, r in rows if aid != sa.agent_id and np.linalg.norm(p - me) < 40.0]
            nei_r.append(np.mean(near) if near else 0.0)
            glob_r.append(np.mean([r for _, _, r in rows]))
        # Ray 1.x (default): every done, time-outs included, ends with 0; RLlib (option): a time-out bootstraps with V(o_T)
        ended = sa.is_terminated if timeout_bootstrap else sa.is_done
        boot = [0.0 if ended else x[n] for x in v]
        want["ego"] += list(gae(sa.get_rewards(), v[0][:n], boot[0], gamma, lam))
        want["nei"] += list(gae(nei_r, v[1][:n], boot[1], gamma, lam))
        want["glob"] += list(gae(glob_r, v[2][:n], boot[2], 1.0, lam))
        want["nei_r"] += nei_r
        want["glob_r"] += glob_r
        want["lcf"] += [infos[t]["lcf"]] * n
    real = batch["loss_mask"].numpy()
    got = {
        k: batch[c].numpy()[real]
        for k, c in (("nei_r", NEI_REWARDS), ("glob_r", GLOBAL_REWARDS), ("lcf", LCF), ("ego", EGO_ADVANTAGES), ("nei", NEI_ADVANTAGES))
    }
    assert len(got["ego"]) == len(want["ego"]) and np.ptp(want["lcf"]) > 0 and np.count_nonzero(want["nei_r"]) > 10
    for key in ("nei_r", "glob_r", "ego", "nei"):
        np.testing.assert_allclose(got[key], want[key], atol=2e-4, err_msg=key)
    np.testing.assert_allclose(got["lcf"], want["lcf"], atol=1e-6)
    glob_adv = np.array(want["glob"])
    np.testing.assert_allclose(batch[GLOBAL_TARGETS].numpy()[real] - batch["coin_old_global_values"].numpy()[real], glob_adv, atol=2e-4)
    np.testing.assert_allclose(batch[GLOBAL_ADVANTAGES].numpy()[real], (glob_adv - glob_adv.mean()) / glob_adv.std(), atol=2e-3)
    coord = coordinated_advantage(np.array(want["ego"]), np.array(want["nei"]), np.array(want["lcf"]))
    assert batch[COORD_MEAN].numpy()[0] == pytest.approx(coord.mean(), abs=1e-4)
    assert batch[COORD_STD].numpy()[0] == pytest.approx(coord.std(), rel=1e-3)
    np.testing.assert_allclose(batch["advantages"].numpy()[real], (coord - coord.mean()) / coord.std(), atol=2e-3)
    np.testing.assert_allclose(batch[NEI_TARGETS].numpy()[real] - batch["coin_old_nei_values"].numpy()[real], want["nei"], atol=2e-4)


def test_copo_trains_moves_the_lcf_and_pushes_it_to_every_env_runner(ray_session, tmp_path):
    settings = {**TINY, "num_env_runners": 1, "lcf_lr": 0.05, "initial_lcf_std": 0.3}
    algo = build_config("copo", "intersection", settings, 0).build_algo()
    try:
        module = algo.learner_group._learner.module["shared"].unwrapped()
        assert module.lcf_distribution() == pytest.approx((0.0, 0.3))
        for _ in range(2):
            result = algo.train()
            stats = result["learners"]["shared"]
            for key in ("policy_loss", "vf_loss", "vf_loss_ego", "vf_loss_nei", "vf_loss_global", "lcf_meta_scale"):
                assert math.isfinite(float(stats[key])), key
        mean, std = module.lcf_distribution()
        assert (mean, std) != pytest.approx((0.0, 0.3), abs=1e-3)  # the meta-gradient moved it
        assert (float(stats["lcf_mean"]), float(stats["lcf_std"])) == pytest.approx((mean, std))

        def runner_lcfs(runner):  # each env's LCF distribution (the batched runner's vector env, or RLlib's sub-envs)
            envs = [runner.vector_env] if isinstance(runner, BatchedEnvRunner) else coin_envs(runner)
            return [(e.lcf.mean, e.lcf.std) for e in envs]

        remote = algo.env_runner_group.foreach_env_runner(runner_lcfs, local_env_runner=False)
        assert remote == [[pytest.approx((mean, std))]]
        # the env runners' policy copies carry the same LCF parameters (weights sync after the update)
        runner_params = algo.env_runner_group.foreach_env_runner(lambda r: r.module["shared"].lcf_params.tolist(), local_env_runner=False)
        np.testing.assert_allclose(runner_params[0], module.lcf_params.tolist(), atol=1e-7)
        # sampled observations hold one LCF per agent life
        episodes = algo.env_runner_group.foreach_env_runner(lambda r: r.sample(num_timesteps=80), local_env_runner=False)[0]
        for ma in episodes:
            for sa in ma.agent_episodes.values():
                assert np.ptp(np.asarray(sa.get_observations())[:, -1]) == 0.0
        algo.save_to_path(str(tmp_path / "ckpt"))
    finally:
        algo.stop()
    # the checkpoint carries the LCF; the exported actor acts with the learned mean LCF folded in
    restored = RLModule.from_checkpoint(str(tmp_path / "ckpt/learner_group/learner/rl_module/shared"))
    assert restored.lcf_distribution() == pytest.approx((mean, std))
    obs = torch.rand(16, 91)
    with_lcf = torch.cat([obs, torch.full((16, 1), float(encode(mean)))], 1)
    with torch.no_grad():
        want = restored.forward_inference({"obs": with_lcf})["action_dist_inputs"][:, :2].clamp(-1, 1)
        np.testing.assert_allclose(restored.deterministic_actor()(obs).numpy(), want.numpy(), atol=1e-6)


def test_bad_copo_settings_are_refused():
    for key, value in (
        ("initial_lcf_mean", 1.0),
        ("initial_lcf_std", 0.0),
        ("lcf_lr", -1.0),
        ("lcf_num_iters", 1.5),
        ("neighbour_radius", 0),
    ):
        with pytest.raises(ValueError, match=f"bad value for '{key}'"):
            build_config("copo", "intersection", {key: value}, 0)


def test_copo_cli_train_export_evaluate(ray_session, tmp_path, capsys):
    out = tmp_path / "run"
    sets = ["horizon=40", "max_agent_steps=40", "train_batch_size_per_learner=100", "rollout_fragment_length=50", "minibatch_size=50"]
    sets += ["hidden=16"]
    assert (
        main(
            [
                "train",
                "--algo",
                "copo",
                "--scenario",
                "roundabout",
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
    capsys.readouterr()
    assert main(["export", str(out / "checkpoint"), "--out", str(tmp_path / "copo.npz")]) == 0
    assert "parity: max |action - RLModule.forward_inference|" in capsys.readouterr().out
    results = []
    for source in (out / "checkpoint", tmp_path / "copo.npz"):  # each vehicle's own LCF, the same draws from both
        assert main(["evaluate", str(source), "--seeds", "3", "--out", str(tmp_path / "e.json")]) == 0
        results.append(json.loads((tmp_path / "e.json").read_text())["episodes"])
    assert results[0][0]["num_vehicles"] >= 3
    assert [e["episode_return"] for e in results[1]] == pytest.approx([e["episode_return"] for e in results[0]], abs=1e-3)
