"""Same seed => same training run, in separate processes with different Python hash seeds.

RLlib keeps an episode's agent ids in a set, whose order follows the hash seed. CIG-TD3's
module acts in a canonical order; the PPO family's train batch is laid out from episodes
whose agents iterate in a fixed order (``coin_app/algorithms/ppo_family/agent_order.py``), with
either env runner. Runs must match bit for bit.
"""

import os
import pickle
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
from ray.rllib.env.multi_agent_episode import MultiAgentEpisode

from coin_app.adapters.episodes import OrderedMultiAgentEpisode, order_agents

PRELUDE = """
import ray, torch
torch.set_num_threads(1)
from coin_app.training import build_config
ray.init(address="local", num_cpus=1, include_dashboard=False, log_to_driver=False)
"""

SCRIPTS = {
    "cig_td3": """
S = {"num_agents": 3, "horizon": 60, "max_agent_steps": 60, "warmup_steps": 100, "train_batch_size_per_learner": 16,
     "hidden": 16, "latent_dim": 4, "node_width": 8, "policy_delay": 2, "eval_every": 0}
algo = build_config("cig_td3", "bottleneck", S, seed=5).reporting(min_sample_timesteps_per_iteration=100).build_algo()
for _ in range(3):
    algo.train()
m = algo.learner_group._learner.module["shared"].unwrapped()
print("RESULT", repr([float(p.detach().double().sum()) for p in m.actor.parameters()]), len(algo.replay))
""",
    "ippo": """
from coin_app.algorithms.registry import quick_settings
for runner in ("batched", "multi_agent"):
    S = {**quick_settings("ippo"), "train_batch_size_per_learner": 200, "minibatch_size": 100, "num_epochs": 2,
         "rollout_fragment_length": 100, "env_runner": runner}
    algo = build_config("ippo", "intersection", S, seed=5).build_algo()
    for _ in range(2):
        algo.train()
    m = algo.learner_group._learner.module["shared"].unwrapped()
    print("RESULT", runner, repr([float(p.detach().double().sum()) for p in m.parameters()]))
    algo.stop()
""",
}


EXPECTED_LINES = {"cig_td3": 1, "ippo": 2}


def run_both(algo: str, hash_seeds: tuple[int, int]) -> list[str]:
    """The RESULT lines of ``algo``'s script under each hash seed; the two processes run side by side (one thread each)."""
    procs, logs = [], []
    try:
        for hash_seed in hash_seeds:
            env = {**os.environ, "PYTHONHASHSEED": str(hash_seed), "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
            out, err = tempfile.TemporaryFile("w+"), tempfile.TemporaryFile("w+")  # files, not pipes: neither process blocks
            logs.append((out, err))
            procs.append(subprocess.Popen([sys.executable, "-c", PRELUDE + SCRIPTS[algo]], env=env, stdout=out, stderr=err, text=True))
        results = []
        for proc, (out, err) in zip(procs, logs, strict=True):
            proc.wait(timeout=300)
            out.seek(0), err.seek(0)
            lines = [line for line in out.read().splitlines() if line.startswith("RESULT")]
            assert proc.returncode == 0 and len(lines) == EXPECTED_LINES[algo], err.read()[-2000:]
            results.append("\n".join(lines))
        return results
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        for out, err in logs:
            out.close(), err.close()


@pytest.mark.parametrize("algo", sorted(SCRIPTS))
def test_same_seed_same_run_across_hash_seeds(algo):
    a, b = run_both(algo, (0, 1))
    assert a == b


def test_ordered_episode_iterates_agents_sorted_by_id_and_survives_pickling():
    obs = {"agent10": np.zeros(2), "agent2": np.ones(2), "agent1": np.full(2, 2.0)}
    ep = MultiAgentEpisode()
    ep.add_env_reset(observations=obs, infos={a: {} for a in obs})
    order_agents([ep])
    assert type(ep) is OrderedMultiAgentEpisode
    assert list(ep.agent_ids) == ["agent1", "agent2", "agent10"] == list(ep.get_agents_that_stepped())
    assert "agent2" in ep.agent_ids and set(ep.agent_ids) == set(obs)  # still set-like
    again = pickle.loads(pickle.dumps(ep))
    assert type(again) is OrderedMultiAgentEpisode and list(again.agent_ids) == ["agent1", "agent2", "agent10"]
    again._del_agent("agent2")  # RLlib's removal calls agent_ids.discard
    assert list(again.agent_ids) == ["agent1", "agent10"]
