"""Shared test fixtures (imported by test modules as ``from fixtures import ...``, as ``device_audit``)."""

# Fast cars without brakes or rolling resistance (the bicycle model): under random actions they crash and
# leave the road within a few steps, so short test episodes see respawns, time-outs and terminations.
NO_BRAKES = {
    "model": "bicycle",
    "brake_linear": 0.0,
    "brake_sat_intercept": 0.0,
    "brake_sat_slope": 0.0,
    "coast_decel": 0.0,
    "throttle_accel": 8.0,
}


# ----------------------------------------------------------------------------- TD3-family learner tests
def params(net):
    """Detached copies of a network's parameters."""
    return [p.detach().clone() for p in net.parameters()]


def same(a, b):
    """Whether two parameter lists are bit-identical."""
    import torch

    return all(torch.equal(x, y) for x, y in zip(a, b))


def module_of(learner):
    """The shared RLModule of a learner, unwrapped."""
    return learner.module["shared"].unwrapped()


def learner_update(learner, batch, env_steps=0):
    """One learner update on a dict of numpy columns (the shared module's batch); the results."""
    from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch

    n = len(next(iter(batch.values())))
    return learner.update(
        batch=MultiAgentBatch({"shared": SampleBatch(batch)}, env_steps=n), timesteps={"num_env_steps_sampled_lifetime": env_steps}
    )


def scalar(value):
    """A logged metric (a Stats object or a number) as a float."""
    return float(value.peek()) if hasattr(value, "peek") else float(value)


# ----------------------------------------------------------------------------- the tiny scale of every algorithm
def tiny(algo, scenario=None, **extra):
    """(scenario, settings) of ``algo`` at the smallest scale (``registry.tiny_settings``: the tiny scenario and the
    spec's ``tiny``) on ``scenario`` (default: the algorithm's first), with ``extra`` settings on top."""
    from coin_app.algorithms import registry

    scenario = scenario or registry.get(algo).scenarios[0]
    return scenario, {**registry.tiny_settings(algo, scenario), **extra}


def tiny_cli(algo, scenario=None, **extra):
    """The ``--scenario`` and ``--set`` arguments of ``coin-app train --algo algo`` at the tiny scale (see ``tiny``)."""
    scenario, settings = tiny(algo, scenario, **extra)
    return ["--scenario", scenario, "--set", *(f"{k}={v}" for k, v in settings.items())]


def acting_counts(config, actor, seed):
    """(episode step, vehicles acting) at every step of one ``DrivingEnv`` episode of ``config`` driven by the torch ``actor``."""
    import numpy as np
    import torch

    from coin_app.sim.driving_env import DrivingEnv

    env = DrivingEnv(config)
    obs, _ = env.reset(seed=seed)
    counts = []
    while not env.episode_over:
        counts.append((env.sim.episode_step, len(env.agents)))
        with torch.no_grad():
            act = actor(torch.as_tensor(np.stack([obs[a] for a in env.agents]))).numpy()
        obs.update(env.step(dict(zip(env.agents, act, strict=True)))[0])
    return counts
