"""CIG-TD3 learns: after a short training run the deterministic actor clearly beats its own untrained self and a random policy.

Budget: about two minutes on the 2-core CI machine (3,000 env steps of the bottleneck with four
agents, small networks). In that budget no vehicle reaches its destination yet (success rate
0 for both the trained and the random policy; see benchmarks/learning_curves.py for success
over longer runs), so the test compares the mean per-vehicle episode return (progress along
the route, speed and the terminal penalties). Early TD3 training oscillates, so the actor is
selected by its return on validation seeds every 500 env steps (as a user selects a checkpoint)
and then compared on the test seeds with a random policy and with the untrained actor, which
already drives forward (seed 0, 2026-11-27: random 3.1, untrained 10.8, trained 50.5 at 3,000 env
steps and 25.5 at 2,000; 2026-12-01 on an AVX-512/AMX CPU: 33.5 in fp32, the quick preset's precision, and 16.7
when the preset left `auto` to choose bf16 there).
"""

import copy

import numpy as np
import torch

from coin_app.algorithms.registry import QUICK_SETTINGS
from coin_app.evaluation.evaluate import evaluate_policy
from coin_app.evaluation.metrics import aggregate
from coin_app.sim.seeds import eval_test_seeds, validation_seeds
from coin_app.training import build_config, evaluate_algorithm


def test_cig_td3_beats_random_policy(ray_session):
    cfg = build_config("cig_td3", "bottleneck", QUICK_SETTINGS, seed=0).reporting(min_sample_timesteps_per_iteration=500)
    algo = cfg.build_algo()
    try:
        actor = algo.learner_group._learner.module["shared"].unwrapped().actor
        untrained = copy.deepcopy(actor)
        best, best_state = -np.inf, None
        while algo.metrics.peek(("env_runners", "num_env_steps_sampled_lifetime"), default=0) < 3000:
            algo.train()
            # checkpoint selection on validation seeds (never on the test seeds)
            score = evaluate_algorithm(algo, validation_seeds(6))["episode_return"]
            if score > best:
                best, best_state = score, copy.deepcopy(actor.state_dict())
    finally:
        algo.stop()
    actor.load_state_dict(best_state)

    def deterministic(net):
        def policy(obs):
            with torch.no_grad():
                return net(torch.as_tensor(obs, dtype=torch.float32)).numpy()

        return policy

    scenario, seeds = cfg.scenario_config(), eval_test_seeds(6)
    got = aggregate(evaluate_policy(deterministic(actor), scenario, seeds))["episode_return"]["mean"]
    before = aggregate(evaluate_policy(deterministic(untrained), scenario, seeds))["episode_return"]["mean"]
    rng = np.random.default_rng(0)
    base = aggregate(evaluate_policy(lambda o: rng.uniform(-1, 1, (len(o), 2)), scenario, seeds))["episode_return"]["mean"]
    print(f"best validation return {best:.2f}; test return: trained {got:.2f}, untrained {before:.2f}, random {base:.2f}")
    assert got > 2 * base and got > base + 5, (got, base)
    assert got > 2 * before and got > before + 10, (got, before)  # learned, not the initial actor's forward drive
