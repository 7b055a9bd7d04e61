"""Same seed => same training run, in separate processes with different Python hash seeds.

RLlib batches the acting agents in the order of a set of agent ids (hash-seed dependent);
the module acts in a canonical order, so runs must match bit for bit.
"""

import os
import subprocess
import sys
from pathlib import Path

SCRIPT = """
import ray, torch
torch.set_num_threads(1)
from coin_app.training import build_config
ray.init(address="local", num_cpus=1, include_dashboard=False, log_to_driver=False)
S = {"num_agents": 3, "horizon": 60, "max_agent_steps": 60, "warmup_steps": 100, "train_batch_size_per_learner": 16,
     "hidden": 16, "latent_dim": 4, "node_width": 8, "policy_delay": 2, "eval_every": 0}
algo = build_config("cig_td3", "bottleneck", S, seed=5).reporting(min_sample_timesteps_per_iteration=100).build_algo()
for _ in range(3):
    algo.train()
m = algo.learner_group._learner.module["shared"].unwrapped()
print("RESULT", repr([float(p.detach().double().sum()) for p in m.actor.parameters()]), len(algo.replay))
"""


def run(hash_seed):
    env = {**os.environ, "PYTHONHASHSEED": str(hash_seed), "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    out = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=300)
    lines = [line for line in out.stdout.splitlines() if line.startswith("RESULT")]
    assert lines, out.stderr[-2000:]
    return lines[0]


def test_same_seed_same_run_across_hash_seeds():
    a, b = run(0), run(1)
    assert a == b
