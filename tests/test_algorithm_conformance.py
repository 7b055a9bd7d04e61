"""Every algorithm of the registry, at its tiny scale: builds, updates in one training iteration, exports its actor (in
process and through ``coin-app export``), saves a checkpoint, is evaluated by code the episode cache's fingerprint
covers, and resumes from it where it stopped."""

import inspect
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from fixtures import tiny

from coin_app import training
from coin_app.algorithms.checkpoint_files import verify
from coin_app.algorithms.checkpoints import export_actor, scenario_of
from coin_app.algorithms.common import SHARED_MODULE_ID
from coin_app.algorithms.registry import ALGORITHMS
from coin_app.cli import main
from coin_app.evaluation.archive import actor_only_copy
from coin_app.evaluation.episode_cache import PACKAGE, episode_code
from coin_app.evaluation.evaluate import evaluate_policy
from coin_app.evaluation.policies import checkpoint_policy
from coin_app.inference import export_policy, load_policy
from coin_app.sim.config import ScenarioConfig

STEPS = ("env_runners", "num_env_steps_sampled_lifetime")


def build(name):
    """The algorithm ``name`` at its tiny scale (an off-policy one samples past its warm-up within one iteration)."""
    scenario, settings = tiny(name)
    cfg = training.build_config(name, scenario, settings, 0)
    if not ALGORITHMS[name].capabilities.on_policy:
        cfg = cfg.reporting(min_sample_timesteps_per_iteration=2 * settings["warmup_steps"])
    return scenario, settings, cfg.build_algo()


def files_run(action):
    """The coin_app files whose functions run (function bodies, not module or class bodies) while ``action()`` runs."""
    ran = set()

    def profile(frame, event, arg):
        code = frame.f_code
        if event == "call" and code.co_flags & inspect.CO_OPTIMIZED and code.co_filename.startswith(str(PACKAGE)):
            ran.add(Path(code.co_filename))

    sys.setprofile(profile)
    try:
        action()
    finally:
        sys.setprofile(None)
    return ran


def weights(algo):
    """Copies of the learner module's parameters and buffers."""
    return {k: v.detach().clone() for k, v in algo.learner_group._learner.module[SHARED_MODULE_ID].state_dict().items()}


@pytest.mark.parametrize("name", list(ALGORITHMS))
def test_builds_updates_exports_checkpoints_and_resumes(name, ray_session, tmp_path, capsys):
    scenario, settings, algo = build(name)
    try:
        before = weights(algo)
        algo.train()
        steps = int(algo.metrics.peek(STEPS))
        after = weights(algo)
        assert steps > 0 and any(not torch.equal(before[k], after[k]) for k in before), f"{name}: no update in one iteration"

        # the actor as export writes it gives the module's own actions
        network, reference, extra = export_actor(algo.learner_group._learner.module[SHARED_MODULE_ID])
        policy = load_policy(export_policy(network, tmp_path / "actor.npz", "numpy", meta={"algo": name, **extra}))
        obs = np.random.default_rng(0).uniform(-0.5, 1.5, (32, policy.obs_dim)).astype(np.float32)
        np.testing.assert_allclose(policy(obs), reference(obs), atol=1e-5, rtol=0, err_msg=name)

        ckpt = tmp_path / "checkpoint"
        training.save(algo, ckpt, training.checkpoint_meta(name, scenario, 0, settings, env_steps=steps))
        assert verify(ckpt)["algo"] == name
    finally:
        algo.stop()

    # loading and driving the checkpoint, whole or as an archived actor-only copy, runs only code the episode cache's
    # fingerprint covers (so its entries stay valid while learners change)
    covered, config = set(episode_code()), scenario_of(ckpt)
    driving = isinstance(config, ScenarioConfig)  # the arena's policies are evaluated by its own report, uncached
    for checkpoint in (ckpt, actor_only_copy(ckpt, tmp_path / "actor_only")):

        def drive(checkpoint=checkpoint):
            policy = checkpoint_policy(checkpoint)
            if driving:
                evaluate_policy(policy, config, [0], max_steps=5)

        ran = files_run(drive)
        assert not driving or PACKAGE / "sim" / "simulator.py" in ran, f"{name}: the trace saw no simulator step"
        assert ran <= covered, f"{name}: ran code the fingerprint leaves out: {sorted(str(f.relative_to(PACKAGE)) for f in ran - covered)}"

    # coin-app export of the checkpoint
    assert main(["export", str(ckpt), "--out", str(tmp_path / "cli.npz")]) == 0, capsys.readouterr().err
    exported = load_policy(tmp_path / "cli.npz")
    obs = np.random.default_rng(1).uniform(-0.5, 1.5, (8, exported.obs_dim)).astype(np.float32)
    assert exported(obs).shape == (8, 2)

    # resume: the saved weights and step count, and training goes on from there
    _, _, resumed = build(name)
    try:
        resumed.restore_from_path(str(ckpt.resolve()))
        restored = weights(resumed)
        assert all(torch.equal(after[k], restored[k]) for k in after), f"{name}: the checkpoint did not restore the weights"
        assert int(resumed.metrics.peek(STEPS)) == steps
        resumed.train()
        assert int(resumed.metrics.peek(STEPS)) > steps
    finally:
        resumed.stop()
