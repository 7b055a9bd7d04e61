"""CIG-TD3 on any device: no tensor created on a fixed device in updates and exploration, CUDA, one remote learner."""

import os
from pathlib import Path

import numpy as np
import pytest
import torch
from device_audit import CreationAudit
from ray.rllib.core.columns import Columns
from ray.rllib.core.learner.training_data import TrainingData
from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch

import coin_app.algorithms.cig_td3 as cig_td3_package
import coin_app.algorithms.td3 as td3_package
from coin_app.adapters.rllib_env import CoinMultiAgentEnv, register_envs
from coin_app.algorithms.cig_td3.cig_td3 import CigTd3, CigTd3Config
from coin_app.algorithms.registry import quick_settings
from coin_app.algorithms.td3 import columns as col
from coin_app.algorithms.td3.connector import JointRecordsCopy, inject_global_state
from coin_app.training import build_config

torch.set_num_threads(1)
register_envs()
ENV_CFG = {"num_agents": 4, "horizon": 50, "max_agent_steps": 50}
B = 16
# the TD3 family's base and CIG-TD3's code, and this file for the self-check
AUDITED = (Path(td3_package.__file__).parent, Path(cig_td3_package.__file__).parent, Path(__file__).parent)


def random_batch(cfg, seed=0):
    rng = np.random.default_rng(seed)
    o, n = cfg.scenario_config().obs_dim, cfg.max_others
    mask, next_mask = rng.random((B, n)) < 0.6, rng.random((B, n)) < 0.6
    f = np.float32
    return {
        "obs": rng.random((B, o), dtype=f),
        "state": rng.standard_normal((B, 10)).astype(f),
        "actions": rng.uniform(-1, 1, (B, 2)).astype(f),
        "rewards": rng.standard_normal(B).astype(f),
        "global_rewards": rng.standard_normal(B).astype(f),
        "terminateds": rng.random(B) < 0.2,
        "truncateds": rng.random(B) < 0.1,
        "new_obs": rng.random((B, o), dtype=f),
        "new_state": rng.standard_normal((B, 10)).astype(f),
        "others_state": rng.standard_normal((B, n, 10)).astype(f) * mask[..., None],
        "others_actions": rng.uniform(-1, 1, (B, n, 2)).astype(f) * mask[..., None],
        "others_mask": mask,
        "next_others_state": rng.standard_normal((B, n, 10)).astype(f) * next_mask[..., None],
        "next_others_obs": rng.random((B, n, o), dtype=f) * next_mask[..., None],
        "next_others_mask": next_mask,
    }


def build_learner(gpus=0, **training):
    base = {"train_batch_size_per_learner": B, "hidden": 32, "latent_dim": 4, "node_width": 16, "policy_delay": 1, "warmup_steps": 10}
    cfg = CigTd3Config().environment("coin-bottleneck-v0", env_config=ENV_CFG).debugging(seed=0).training(**{**base, **training})
    cfg = cfg.learners(num_gpus_per_learner=gpus)
    cfg.validate()
    return cfg, cfg.build_learner(env=CoinMultiAgentEnv({"scenario": "bottleneck", **ENV_CFG}))


def update_and_explore(learner, cfg):
    """One learner update (a policy step: targets, critics, actor) and exploration forwards in and after the warm-up."""
    module = learner.module["shared"].unwrapped()
    device = next(module.parameters()).device
    learner.update(
        batch=MultiAgentBatch({"shared": SampleBatch(random_batch(cfg))}, env_steps=B), timesteps={"num_env_steps_sampled_lifetime": 100}
    )
    obs = torch.as_tensor(random_batch(cfg, 1)["obs"], device=device)
    return [module.forward_exploration({Columns.OBS: obs}, t=t)[Columns.ACTIONS] for t in (0, 100)]


def test_the_audit_sees_a_tensor_created_without_a_device():
    torch.manual_seed(3)
    expected = torch.rand(3)
    torch.manual_seed(3)
    audit = CreationAudit(AUDITED)
    with audit:
        drawn = torch.rand(3)
        torch.zeros(2, device="cpu")
        torch.ones(2).new_zeros(3)  # from an input tensor: not a creation from scratch
    assert [(f, d.type) for _, f, d, _ in audit.created] == [("rand", "meta"), ("zeros", "cpu"), ("ones", "meta")]
    assert torch.equal(drawn, expected)  # the meta replay drew no random numbers


@pytest.mark.parametrize(
    "training",
    [
        {},  # CVAE + GAT + counterfactual baseline
        {"global_module": "graphsage", "graph": 40.0},
        {"local_module": "attention", "vae_weight": 0.0, "global_module": "gcn", "precision": "bf16"},
        {"local_module": "none", "vae_weight": 0.0, "global_module": "none"},
    ],
)
def test_update_and_exploration_create_tensors_on_the_module_device(training):
    cfg, learner = build_learner(**training)
    device = next(learner.module["shared"].unwrapped().parameters()).device
    audit = CreationAudit(AUDITED)
    with audit:
        actions = update_and_explore(learner, cfg)
    assert {"arange", "rand", "randn"} <= {f for _, f, _, _ in audit.created}  # canonical order, warm-up and exploration noise
    assert [c for c in audit.created if c[2] != device] == []
    assert all(a.device == device and a.abs().max() <= 1 for a in actions)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_one_update_and_exploration_on_cuda(precision, ray_session):  # a Ray driver, as in training: RLlib picks cuda:0
    cfg, learner = build_learner(gpus=1, precision=precision)
    module = learner.module["shared"].unwrapped()
    assert {p.device.type for p in module.parameters()} == {"cuda"}
    assert {p.device.type for t in (module.actor_target, module.local_q_target, module.central_target) for p in t.parameters()} == {"cuda"}
    before = [p.detach().clone() for p in module.actor.parameters()]
    audit = CreationAudit(AUDITED)
    with audit:
        actions = update_and_explore(learner, cfg)
    assert [c for c in audit.created if c[2].type != "cuda"] == []
    assert all(a.device.type == "cuda" for a in actions)
    assert not all(torch.equal(a, b) for a, b in zip(before, module.actor.parameters()))
    obs = torch.as_tensor(random_batch(cfg, 1)["obs"])  # evaluation and export read the actor on the CPU
    assert {p.device.type for p in module.deterministic_actor().parameters()} == {"cpu"}
    assert torch.allclose(module.inference_actions(obs), module.deterministic_actor()(obs), atol=1e-4)
    state = learner.get_state()["cig_td3"]  # a checkpoint readable without the GPU
    assert state["cuda_rng"] is not None
    assert all(v.device.type == "cpu" for v in state["targets"]["shared"]["central_target"].values())


def test_gpu_and_one_remote_learner_are_accepted_more_are_refused():
    cfg = CigTd3Config().environment("coin-bottleneck-v0", env_config=ENV_CFG)
    cfg.copy(copy_frozen=False).learners(num_gpus_per_learner=1).validate()
    cfg.copy(copy_frozen=False).learners(num_learners=1, num_gpus_per_learner=1).validate()
    with pytest.raises(ValueError, match=r"num_learners=2; allowed: 0 \(local learner\) or 1"):
        cfg.copy(copy_frozen=False).learners(num_learners=2).validate()


def _facts(algo):
    """The (remote) learner's process id, update count and actor weights."""

    def facts(learner):  # defined here: a closure travels to the learner actor by value
        actor = learner.module["shared"].unwrapped().actor
        return os.getpid(), learner.num_updates, {k: v.detach().cpu().clone() for k, v in actor.state_dict().items()}

    return next(iter(algo.learner_group.foreach_learner(facts))).get()


def assert_remote_connector_matches_the_replay(algo, n=64):
    """The remote learner's train batch of a replay sample (its connector on its copy of the joint records) is the one
    the connector gives on the replay's own records, bit for bit; its copy is current with every update sent so far."""
    sample = algo.replay.sample(n)
    written = algo._joint_written
    delta = algo.joint_delta()["joint_delta"]  # what the next update would carry: the rows added since the last one

    def remote(learner):  # defined here: a closure travels to the learner actor by value
        records = learner.joint_state.records
        before = records.written
        records.apply(delta)
        td = TrainingData(batch=MultiAgentBatch({"shared": SampleBatch(dict(sample))}, n))
        out = learner._make_batch_if_necessary(td).policy_batches["shared"]
        return type(records), before, {k: v.cpu().numpy() for k, v in out.items()}

    kind, before, got = next(iter(algo.learner_group.foreach_learner(remote))).get()
    assert kind is JointRecordsCopy and before == written is not None
    want = inject_global_state(algo.replay.joint_columns(), dict(sample))
    assert sorted(got) == sorted(want) == sorted(col.EGO + col.OTHERS + col.ORIGIN)
    for k in want:
        assert got[k].dtype == want[k].dtype and got[k].tobytes() == want[k].tobytes(), k
    assert want[col.NEXT_OTHERS_MASK].any() and want[col.OTHERS_MASK].any()  # the others are there to compare


def test_one_remote_learner_trains_syncs_evaluates_and_checkpoints(ray_session, tmp_path):
    settings = {**quick_settings("cig_td3"), "warmup_steps": 50, "train_batch_size_per_learner": 16, "eval_every": 3, "eval_episodes": 1}
    settings |= {"updates_per_env_step": 0.2}  # each update is a remote call: 10 per iteration keep the test short
    cfg = build_config("cig_td3", "bottleneck", settings, 0).reporting(min_sample_timesteps_per_iteration=50).learners(num_learners=1)
    algo = cfg.build_algo()
    assert not algo.learner_group.is_local
    pid, updates0, actor0 = _facts(algo)
    assert pid != os.getpid() and updates0 == 0
    results = [algo.train()]  # the warm-up: 50 env steps
    assert algo.metrics.peek(("env_runners", "num_env_steps_sampled_lifetime")) >= 50
    results += [algo.train() for _ in range(2)]  # 2 iterations of updates
    _, updates, actor = _facts(algo)
    assert updates == algo.learner_updates() >= 20
    assert np.isfinite(float(results[-1]["learners"]["shared"]["actor_loss"]))
    assert not all(torch.equal(actor0[k], actor[k]) for k in actor)  # the remote learner's actor learned ...
    runner = algo.env_runner.module["shared"].actor.state_dict()
    assert all(torch.equal(runner[k], actor[k]) for k in actor)  # ... and the env runner acts with it
    assert 0.0 <= results[-1]["coin_eval"]["success_rate"] <= 1.0  # the periodic evaluation reads the remote learner
    assert_remote_connector_matches_the_replay(algo)
    algo.save_to_path(str(tmp_path / "ckpt"))
    restored = CigTd3.from_checkpoint(str(tmp_path / "ckpt"))
    _, restored_updates, restored_actor = _facts(restored)
    assert restored_updates == updates and all(torch.equal(restored_actor[k], actor[k]) for k in actor)
    assert len(restored.replay) == len(algo.replay)
    restored.train()
    assert_remote_connector_matches_the_replay(restored)  # the restored replay's records reached the new remote learner in full
    algo.stop()
    restored.stop()
