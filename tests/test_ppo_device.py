"""The PPO family on any device: no tensor created on a fixed device in an update, CUDA, one remote learner."""

import os
from pathlib import Path

import pytest
import torch
from device_audit import CreationAudit
from fixtures import tiny
from ray.rllib.utils.metrics import NUM_ENV_STEPS_SAMPLED_LIFETIME

import coin_app.algorithms.copo as copo_package
import coin_app.algorithms.nav_ppo as nav_ppo_package
import coin_app.algorithms.ppo_family as ppo_family_package
from coin_app.algorithms.common import SHARED_MODULE_ID
from coin_app.training import build_config

torch.set_num_threads(1)
# the PPO family's learners, connector pieces, losses and modules, and this file for the self-check
AUDITED = tuple(Path(p.__file__).parent for p in (ppo_family_package, copo_package, nav_ppo_package)) + (Path(__file__).parent,)
DRIVING = {**tiny("ippo")[1], "num_epochs": 1}  # the tiny scale, one epoch
_, ARENA = tiny("nav_ppo")
SETTINGS = {"ippo": DRIVING, "cppo": DRIVING, "copo": DRIVING, "nav_ppo": ARENA}
# what each update creates from no input tensor (the audit's own check that it looked): the KL of a run without the KL
# term, the critic inputs and CoPO's columns (numpy -> the batch's device), CoPO's gradient dot product
EXPECTED = {
    "ippo": set(),
    "ippo_no_kl": {"zeros"},
    "cppo": {"as_tensor"},
    "copo": {"as_tensor", "zeros"},
    "nav_ppo": set(),
}
SEEDED_DRAWS = {("learner.py", "randperm"), ("learner.py", "randn")}  # CoPO's meta-gradient shuffles and LCF noise


def config(name, **learners):
    """The tiny config of ``name`` (``ippo_no_kl``: IPPO without the KL term), with ``learners`` settings."""
    algo = "ippo" if name == "ippo_no_kl" else name
    cfg = build_config(algo, "arena" if algo == "nav_ppo" else "intersection", SETTINGS[algo], 0)
    if name == "ippo_no_kl":
        cfg = cfg.training(use_kl_loss=False)
    return cfg.learners(**learners) if learners else cfg


def learner_and_episodes(name, gpus=0):
    """A learner of ``name``'s tiny config (``gpus`` per learner) and one train batch of episodes from its env runner."""
    cfg = config(name, num_gpus_per_learner=gpus)
    runner = cfg.env_runner_cls(config=cfg)
    try:
        episodes = runner.sample(num_timesteps=cfg.train_batch_size_per_learner)
        spaces = {SHARED_MODULE_ID: runner.get_spaces()[SHARED_MODULE_ID]}
    finally:
        runner.stop()
    return cfg, cfg.build_learner(spaces=spaces), episodes


def update(cfg, learner, episodes):
    """One PPO update of ``learner`` on ``episodes``, as PPO's training step runs it."""
    steps = sum(len(e) for e in episodes)
    return learner.update(
        episodes=episodes, timesteps={NUM_ENV_STEPS_SAMPLED_LIFETIME: steps}, num_epochs=cfg.num_epochs, minibatch_size=cfg.minibatch_size
    )


def policy_state(state):
    """The policy's weights (what env runners act with) of a module or its state dict, as CPU copies."""
    state = state.state_dict() if isinstance(state, torch.nn.Module) else state
    return {k: v.detach().cpu().clone() for k, v in state.items() if k.startswith(("encoder.actor_encoder.", "pi.net."))}


def changed(before, after):
    """Whether any tensor of ``after`` differs from ``before``."""
    return not all(torch.equal(before[k], after[k]) for k in before)


def test_the_audit_sees_a_tensor_created_without_a_device():
    torch.manual_seed(3)
    expected, expected_on_cpu = torch.rand(3), torch.rand(2)
    torch.manual_seed(3)
    reference = torch.Generator().manual_seed(0)
    expected_seeded = torch.randn(2, generator=reference)
    generator = torch.Generator().manual_seed(0)
    audit = CreationAudit(AUDITED)
    with audit:
        drawn = torch.rand(3)
        torch.zeros(2, device="cpu")
        drawn_on_cpu = torch.rand(2, device="cpu")  # replayed on the CPU: from a forked generator
        torch.ones(2).new_zeros(3)  # from an input tensor: not a creation from scratch
        seeded = torch.randn(2, generator=generator, device="cpu")
    assert [(f, d.type, s) for _, f, d, s in audit.created] == [
        ("rand", "meta", False),
        ("zeros", "cpu", False),
        ("rand", "cpu", False),
        ("ones", "meta", False),
        ("randn", "cpu", True),
    ]
    assert torch.equal(drawn, expected) and torch.equal(drawn_on_cpu, expected_on_cpu)  # the replays drew nothing, globally ...
    assert torch.equal(seeded, expected_seeded) and torch.equal(generator.get_state(), reference.get_state())  # ... nor from a generator


@pytest.mark.parametrize("name", ["ippo", "ippo_no_kl", "cppo", "copo", "nav_ppo"])
def test_an_update_creates_tensors_on_the_module_device(name):
    cfg, learner, episodes = learner_and_episodes(name)
    module = learner.module[SHARED_MODULE_ID].unwrapped()
    device = next(module.parameters()).device
    before = policy_state(module)
    audit = CreationAudit(AUDITED)
    with audit:
        results = update(cfg, learner, episodes)
    assert results and changed(before, policy_state(module))
    assert EXPECTED[name] <= {f for _, f, _, seeded in audit.created if not seeded}
    assert [c for c in audit.created if not c[3] and c[2] != device] == []
    seeded = {(where.split(":")[0], f) for where, f, d, s in audit.created if s and d.type == "cpu"}
    assert seeded == (SEEDED_DRAWS if name == "copo" else set())
    assert [c for c in audit.created if c[3] and c[2].type != "cpu"] == []


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("name", ["ippo_no_kl", "cppo", "copo"])
def test_one_update_on_cuda(name, ray_session):  # a Ray driver, as in training: RLlib picks cuda:0
    cfg, learner, episodes = learner_and_episodes(name, gpus=1)
    module = learner.module[SHARED_MODULE_ID].unwrapped()
    assert {p.device.type for p in module.parameters()} == {"cuda"}
    before = policy_state(module)
    audit = CreationAudit(AUDITED)
    with audit:
        update(cfg, learner, episodes)
    assert [c for c in audit.created if not c[3] and c[2].type != "cuda"] == []  # seeded CPU draws are moved to the data
    assert changed(before, policy_state(module))
    if name == "copo":
        param = learner._lcf_params[SHARED_MODULE_ID]
        assert module.lcf_params.device.type == param.device.type == "cuda"
        state = learner._lcf_optimizers[SHARED_MODULE_ID].state[param]
        assert {v.device.type for v in state.values() if v.dim() > 0} == {"cuda"}
        assert torch.equal(module.lcf_params, param.detach())
    obs = torch.rand(8, module.observation_space.shape[0])  # evaluation and export read the actor on the CPU
    actor = module.lcf_actor() if name == "copo" else module.deterministic_actor()
    assert {p.device.type for p in actor.parameters()} == {"cpu"}
    reference = module.lcf_inference_actions(obs) if name == "copo" else module.inference_actions(obs)
    assert reference.device.type == "cpu" and torch.allclose(actor(obs), reference, atol=1e-4)


def _facts(algo):
    """The (remote) learner's process id and policy weights."""

    def facts(learner):  # defined here: a closure travels to the learner actor by value
        module = learner.module[SHARED_MODULE_ID].unwrapped()
        return os.getpid(), {k: v.detach().cpu().clone() for k, v in module.state_dict().items()}

    return next(iter(algo.learner_group.foreach_learner(facts))).get()


@pytest.mark.parametrize("name", ["ippo", "cppo", "copo", "nav_ppo"])
def test_one_remote_learner_trains_and_syncs_the_env_runner(name, ray_session):
    algo = config(name, num_learners=1).build_algo()
    try:
        assert not algo.learner_group.is_local
        pid, learner0 = _facts(algo)
        assert pid != os.getpid()
        result = algo.train()  # the episodes travel to the learner actor
        assert result["learners"][SHARED_MODULE_ID]["num_module_steps_trained"] > 0
        _, learner1 = _facts(algo)
        runner = algo.env_runner.module[SHARED_MODULE_ID].state_dict()
        assert changed(policy_state(learner0), policy_state(learner1))  # the remote learner learned ...
        assert set(runner) <= set(learner1) and all(
            torch.equal(runner[k].cpu(), learner1[k]) for k in runner
        )  # ... the runner acts with it
        if name == "copo":  # the meta-gradient moved the LCF distribution, and the runner's envs draw from it
            assert not torch.equal(learner0["lcf_params"], learner1["lcf_params"])
            mean, std = algo.lcf_distribution()
            assert (algo.env_runner.vector_env.lcf.mean, algo.env_runner.vector_env.lcf.std) == pytest.approx((mean, std))
    finally:
        algo.stop()
