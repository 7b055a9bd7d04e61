"""One CIG-TD3 learner update at the paper's density, this checkout against another one, side by side in one run.

Usage: python benchmarks/cig_td3_update_trees.py [--tree PATH] [--precision fp32 bf16] [--cycles 2] [--agents 30]

Each tree (this one and, with ``--tree``, e.g. a worktree of an older commit) gets a worker process
(``benchmarks/trees.py``) that builds CIG-TD3's learner on the intersection with ``--agents``
vehicles (B = 256, the paper's networks, every module on) from the same seed, so both start from
the same weights, and updates on the same synthetic batch, shaped as a replay batch of the
intersection: ``agents - 1`` other agents present at t and t+1, in the leading slots of
``max_others`` (what ``JointStepReplayBuffer`` samples there; the trailing slots are empty). The
lifetime env-step count given to the learner is past the warm-up, so every ``policy_delay``-th
update also steps the actor and the targets. Per precision the workers first report the losses of
their first update (the same weights, batch and seed: they must agree within the precision's
rounding), then run ``--cycles`` delay cycles each, in turn, and the script prints the mean time
per update of each tree and their ratio, in wall time and in the worker thread's CPU time (on a
loaded machine the latter leaves out the time spent waiting for a core).
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

import numpy as np
from trees import THIS_TREE, TreeWorker, serve, tree_path

LOSSES = ("local_critic_loss", "central_critic_loss", "actor_loss")
CLOCKS = ("wall", "cpu")  # elapsed time; the thread's CPU time (leaves out waiting for a core on a loaded machine)


# ---------------------------------------------------------------- worker side
def synthetic_batch(b: int, n: int, obs_dim: int, present: int, seed: int = 0) -> dict[str, np.ndarray]:
    """A replay-shaped batch: ``present`` of ``n`` other slots filled at t and at t+1 (the leading ones)."""
    rng = np.random.default_rng(seed)
    mask = np.zeros((b, n), bool)
    mask[:, :present] = True
    f, s, a = np.float32, 10, 2  # schema.STATE_DIM, schema.ACT_DIM
    return {
        "obs": rng.random((b, obs_dim), dtype=f),
        "state": rng.standard_normal((b, s)).astype(f),
        "actions": rng.uniform(-1, 1, (b, a)).astype(f),
        "rewards": rng.standard_normal(b).astype(f),
        "global_rewards": rng.standard_normal(b).astype(f),
        "terminateds": rng.random(b) < 0.05,
        "truncateds": np.zeros(b, bool),
        "new_obs": rng.random((b, obs_dim), dtype=f),
        "new_state": rng.standard_normal((b, s)).astype(f),
        "others_state": rng.standard_normal((b, n, s)).astype(f) * mask[..., None],
        "others_actions": rng.uniform(-1, 1, (b, n, a)).astype(f) * mask[..., None],
        "others_mask": mask,
        "next_others_state": rng.standard_normal((b, n, s)).astype(f) * mask[..., None],
        "next_others_obs": rng.random((b, n, obs_dim), dtype=f) * mask[..., None],
        "next_others_mask": mask.copy(),
    }


class Worker:
    """The learners of one tree, one per precision."""

    def __init__(self) -> None:
        self.learners: dict[str, Any] = {}

    def handle(self, req: dict[str, Any]) -> dict[str, Any]:
        """Answer one request: build (a learner per precision), first (one delay cycle's losses) or time (seconds of n updates)."""
        import torch  # noqa: I001  (imported by the worker only: its tree decides which coin_app these are)
        from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch

        from coin_app.adapters.rllib_env import CoinMultiAgentEnv
        from coin_app.training import build_config

        torch.set_num_threads(1)
        p = req["precision"]
        if req["op"] == "build":
            cfg = build_config("cig_td3", "intersection", {"num_agents": req["agents"], "precision": p}, 0)
            env = CoinMultiAgentEnv(cfg.env_config)
            present = req["agents"] - 1
            batch = synthetic_batch(cfg.train_batch_size_per_learner, cfg.max_others, env.config.obs_dim, present)
            ma = MultiAgentBatch({"shared": SampleBatch(batch)}, env_steps=cfg.train_batch_size_per_learner)
            ts = {"num_env_steps_sampled_lifetime": cfg.warmup_steps + cfg.actor_start_steps}
            torch.manual_seed(0)
            learner = cfg.build_learner(env=env)
            self.learners[p] = (learner, ma, ts, cfg.policy_delay)
            return {"batch": cfg.train_batch_size_per_learner, "slots": cfg.max_others, "present": present, "delay": cfg.policy_delay}
        learner, ma, ts, delay = self.learners[p]
        if req["op"] == "first":  # a whole delay cycle, so that the actor loss is among the results
            torch.manual_seed(1)
            losses: dict[str, float] = {}
            for _ in range(delay):
                res = learner.update(batch=ma, timesteps=ts)["shared"]
                for k in LOSSES:
                    if k in res:
                        v = res[k]
                        losses.setdefault(k, float(v.peek() if hasattr(v, "peek") else v))
            return {"losses": losses}
        wall0, cpu0 = time.perf_counter(), time.thread_time()
        for _ in range(req["updates"]):
            learner.update(batch=ma, timesteps=ts)
        return {"wall": time.perf_counter() - wall0, "cpu": time.thread_time() - cpu0}


# ---------------------------------------------------------------- parent side
def main() -> None:
    """Per precision: the trees' first losses, then their time per update, alternating delay cycles, and the ratio."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tree", help="another checkout to time beside this one (e.g. a worktree of an older commit)")
    ap.add_argument("--precision", nargs="+", choices=("fp32", "bf16"), default=["fp32", "bf16"])
    ap.add_argument("--cycles", type=int, default=2, help="timed delay cycles per tree and precision (default 2)")
    ap.add_argument("--agents", type=int, default=30, help="vehicles on the intersection (default 30, the paper's)")
    args = ap.parse_args()
    if args.cycles < 1:
        raise SystemExit(f"bad --cycles {args.cycles}; allowed: an integer >= 1")
    if args.agents < 2:
        raise SystemExit(f"bad --agents {args.agents}; allowed: an integer >= 2")
    trees = {"this": THIS_TREE}
    if args.tree:
        trees["other"] = tree_path(args.tree)
    workers = {name: TreeWorker(__file__, path, name) for name, path in trees.items()}
    try:
        rows = []
        for p in args.precision:
            shape = {name: w.call(op="build", precision=p, agents=args.agents) for name, w in workers.items()}["this"]
            print(
                f"{p}: B={shape['batch']}, intersection with {args.agents} vehicles ({shape['present']} of {shape['slots']} other slots "
                f"present), policy delay {shape['delay']}, one torch thread",
                flush=True,
            )
            for name, w in workers.items():
                losses = w.call(op="first", precision=p)["losses"]
                print(f"  first delay cycle's losses, {name} tree ({trees[name]}): " + ", ".join(f"{k} {v:.6g}" for k, v in losses.items()))
            spent = {(n, c): 0.0 for n in workers for c in CLOCKS}
            for cycle in range(args.cycles):
                for name, w in list(workers.items())[:: 1 if cycle % 2 == 0 else -1]:  # each tree first in every other cycle
                    took = w.call(op="time", precision=p, updates=shape["delay"])
                    for c in CLOCKS:
                        spent[name, c] += took[c]
                done = (cycle + 1) * shape["delay"]
                print(
                    f"  cycle {cycle + 1}/{args.cycles}: "
                    + ", ".join(
                        f"{n} {spent[n, 'wall'] / done * 1000:.0f} ms wall, {spent[n, 'cpu'] / done * 1000:.0f} ms cpu" for n in workers
                    ),
                    flush=True,
                )
            rows.append((p, {key: v / (args.cycles * shape["delay"]) for key, v in spent.items()}))
        cols = [(n, c) for n in workers for c in CLOCKS]
        print(f"\n{'ms/update':<10}" + "".join(f"{n + ' ' + c:>14}" for n, c in cols) + ("   this/other (cpu)" if len(workers) > 1 else ""))
        for p, per in rows:
            ratio = f"   {per['this', 'cpu'] / per['other', 'cpu']:.2f}" if len(workers) > 1 else ""
            print(f"{p:<10}" + "".join(f"{per[key] * 1000:>14.0f}" for key in cols) + ratio)
    finally:
        for w in workers.values():
            w.close()


if __name__ == "__main__":
    if sys.argv[1:] == ["--worker"]:
        serve(Worker().handle)
    else:
        main()
