"""CIG-TD3 (and TraCo, on the same machinery) end to end: trains, env runners hold only the actor, checkpoints keep the buffer."""

import numpy as np
import pytest
import torch
from fixtures import tiny
from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch

from coin_app.training import build_config

torch.set_num_threads(1)
pytestmark = pytest.mark.usefixtures("ray_session")
EVALUATING = {"eval_every": 2, "eval_episodes": 2}  # the tiny scale with a periodic evaluation every second iteration


def tiny_algo(seed=0, algo="cig_td3", **extra):
    _, settings = tiny(algo, "bottleneck", **{**EVALUATING, **extra})
    cfg = build_config(algo, "bottleneck", settings, seed).reporting(min_sample_timesteps_per_iteration=50)
    return cfg.build_algo()


def test_trains_evaluates_and_keeps_critics_off_the_env_runner():
    algo = tiny_algo()
    calls, updates = [], []
    algo.progress_callback = lambda phase, done, total: calls.append((phase, done, total))
    update = algo.learner_group.update
    algo.learner_group.update = lambda *a, **k: updates.append(1) or update(*a, **k)
    results = [algo.train() for _ in range(3)]
    # progress inside each iteration: every training step samples first, then counts each update up to its total
    starts = [i for i, c in enumerate(calls) if c[0] == "sampling"]
    assert starts[0] == 0 and len(starts) >= 3
    reported = 0
    for a, b in zip(starts, starts[1:] + [len(calls)]):
        steps = calls[a + 1 : b]
        if steps:
            n = steps[-1][2]
            assert steps == [("updates", i, n) for i in range(n)] + [("updates", n, n)]
            reported += n
    assert reported == len(updates) > 0
    learner = results[-1]["learners"]["shared"]
    for key in ("local_critic_loss", "central_critic_loss", "actor_loss", "global_q1_mean", "baseline_mean", "vae_recon"):
        assert np.isfinite(float(learner[key])), key
    assert "coin_eval" in results[1] and 0.0 <= results[1]["coin_eval"]["success_rate"] <= 1.0
    runner_module = algo.env_runner.module["shared"]
    assert runner_module.inference_only and runner_module.local_q is None and runner_module.central is None
    # the env runner's actor equals the learner's actor after the sync
    lm = algo.learner_group._learner.module["shared"].unwrapped()
    for a, b in zip(runner_module.actor.parameters(), lm.actor.parameters()):
        assert torch.equal(a, b) and a.data_ptr() != b.data_ptr()  # equal values in the runner's own tensors
    # the in-place copy gave the runner exactly what RLlib's own sync (state -> object store -> load) gives
    copied = [p.clone() for p in runner_module.parameters()]
    with torch.no_grad():
        for p in runner_module.parameters():
            p.add_(1.0)  # so that a sync that loads nothing would show
    algo.sync_actor_through_rllib()
    assert len(copied) == len(list(runner_module.parameters())) > 0
    for a, b in zip(runner_module.parameters(), copied):
        assert torch.equal(a, b)
    algo.stop()


def test_traco_trains_with_the_same_machinery_and_keeps_its_critics_off_the_env_runner():
    algo = tiny_algo(algo="traco", eval_every=0)
    results = [algo.train() for _ in range(3)]
    learner = results[-1]["learners"]["shared"]
    for key in ("domain_critic_loss", "baseline_loss", "actor_loss", "domain_q1_mean", "domain_reward_mean", "domain_size_mean"):
        assert np.isfinite(float(learner[key])), key
    assert float(learner["domain_size_mean"]) > 0  # three vehicles on the bottleneck: some are within 40 m of each other
    runner_module = algo.env_runner.module["shared"]
    assert runner_module.inference_only and runner_module.domain_q is None and runner_module.baseline is None
    lm = algo.learner_group._learner.module["shared"].unwrapped()
    for a, b in zip(runner_module.actor.parameters(), lm.actor.parameters()):
        assert torch.equal(a, b)
    algo.stop()


@pytest.mark.parametrize("algo_name", ["cig_td3", "traco"])
def test_checkpoint_keeps_the_buffer_and_resumes_the_same_updates(tmp_path, algo_name):
    algo = tiny_algo(seed=3, algo=algo_name)
    for _ in range(3):
        algo.train()
    algo.save_to_path(str(tmp_path / "ckpt"))
    restored = type(algo).from_checkpoint(str(tmp_path / "ckpt"))
    assert type(restored) is type(algo)
    assert len(restored.replay) == len(algo.replay) > 16
    assert restored.learner_updates() == algo.learner_updates() > 0

    def next_losses(a, n=3):
        out = []
        for _ in range(n):
            batch = a.replay.sample(16)
            res = a.learner_group.update(batch=MultiAgentBatch({"shared": SampleBatch(batch)}, env_steps=16), timesteps={})
            v = res[0]["shared"]["total_loss"] if isinstance(res, list) else res["shared"]["total_loss"]
            out.append(float(v.peek() if hasattr(v, "peek") else v))
        return out

    # both learners share this process's torch RNG (target noise, CVAE samples); in a real
    # resume the restored process starts from the checkpointed RNG state, so replay that
    rng = torch.get_rng_state()
    first = next_losses(algo)
    torch.set_rng_state(rng)
    assert first == next_losses(restored)
    algo.stop()
    restored.stop()


def test_no_uniform_random_action_after_warmup_steps():
    # one iteration of 50 env steps spans the warm-up boundary at 37; no updates (the batch never fills), no noise:
    # from env step 37 on, every stored action is the (fixed) actor's own action
    algo = tiny_algo(warmup_steps=37, exploration_noise=0.0, train_batch_size_per_learner=100_000, horizon=100, max_agent_steps=100)
    algo.train()
    assert algo.metrics.peek(("env_runners", "num_env_steps_sampled_lifetime")) >= 50
    sample = algo.replay.sample(len(algo.replay))
    actor = algo.get_module("shared").actor
    with torch.no_grad():
        policy = actor(torch.as_tensor(sample["obs"])).numpy()
    gap = np.abs(sample["actions"] - policy).max(axis=1)
    steps = sample["env_step"]
    assert set(steps[steps >= 37]) and set(steps[steps < 37])  # both sides of the boundary were sampled
    assert gap[steps >= 37].max() < 1e-5  # the policy's action, exactly from the boundary on
    assert np.median(gap[steps < 37]) > 0.1  # uniform random actions before it
    algo.stop()
