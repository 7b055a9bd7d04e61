"""Sampling (and adding) speed of the CIG-TD3 joint-step replay buffer on a synthetic respawning stream.

Usage: python benchmarks/replay_sampling.py [--transitions 200000] [--capacity N] [--batch 256] [--max-others 29 47] [--repeats 200]

Fills a buffer with ``--transitions`` transitions from a synthetic stream of ``--envs`` episodes in
parallel with ``--agents`` agents each (obs_dim 91, state_dim ``schema.STATE_DIM``): every step an agent ends with
probability 1/150 (2/3 terminated, 1/3 truncated; its terminal observation is at the next step) and
a replacement with a fresh id has its first observation one step later (so at most ``--agents``
observations per step); episodes last ``--horizon`` steps; chunks of ``--fragment`` env steps are
added at a time (as ``MultiAgentEnvRunner.sample()`` would return them). Then prints the median
time of ``sample(B)`` and of the learner connector's gather of every global column from it
(``connector.inject_global_state``), and what a remote learner gets per update (the sampled rows
with their lookups) against the same rows with every global column, per ``max_others``, and the time per ``add`` of
one-step chunks. The buffer's capacity is ``--capacity`` (default: the stream's length, so it is
full); its arrays grow with what is stored (module doc of ``coin_app/algorithms/td3/buffer.py``),
so each line also prints the bytes allocated, the bytes at full capacity and the size of the arrays
in a checkpoint (``get_state``); e.g. ``--capacity 10000000`` shows what the official capacity
costs a run that holds ``--transitions``. Pin one core with ``taskset -c 0``.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from coin_app.algorithms.td3 import columns as col  # noqa: E402
from coin_app.algorithms.td3.buffer import JointStepReplayBuffer  # noqa: E402
from coin_app.algorithms.td3.connector import inject_global_state  # noqa: E402
from coin_app.algorithms.td3.transitions import TransitionBatch  # noqa: E402
from coin_app.sim import schema  # noqa: E402


def synthetic_chunks(
    total: int,
    num_envs: int = 4,
    agents: int = 30,
    horizon: int = 1000,
    fragment: int = 50,
    obs_dim: int = 91,
    seed: int = 0,
    first_episode: int = 0,
) -> list[TransitionBatch]:
    """About ``total`` transitions of a respawning multi-agent stream, as one TransitionBatch per chunk boundary."""
    rng = np.random.default_rng(seed)
    slots = num_envs * agents
    env_of = np.repeat(np.arange(num_envs), agents)
    episode = np.arange(first_episode, first_episode + num_envs, dtype=np.int64)  # current episode key per env
    next_episode = first_episode + num_envs
    agent = np.tile(np.arange(agents, dtype=np.int64), num_envs)
    next_agent = np.full(num_envs, agents, np.int64)
    alive = np.ones(slots, bool)
    obs = rng.random((slots, obs_dim), dtype=np.float32)
    state = rng.random((slots, schema.STATE_DIM), dtype=np.float32)
    t = 0
    parts: list[dict[str, np.ndarray]] = []
    out: list[TransitionBatch] = []
    count = 0
    while count < total:
        idx = np.flatnonzero(alive)
        new_obs = obs + 0.01 * rng.standard_normal((slots, obs_dim), dtype=np.float32)
        new_state = state + 0.01 * rng.standard_normal((slots, schema.STATE_DIM), dtype=np.float32)
        end = rng.random(slots) < 1 / 150
        last = t == horizon - 1
        term = end & (rng.random(slots) < 2 / 3) & ~last
        trunc = (end & ~term) | last
        parts.append(
            {
                col.EPISODE: episode[env_of[idx]],
                col.AGENT: agent[idx],
                col.ENV_STEP: np.full(idx.shape[0], t, np.int64),
                col.OBS: obs[idx],
                col.STATE: state[idx],
                col.ACTIONS: rng.uniform(-1, 1, (idx.shape[0], schema.ACT_DIM)).astype(np.float32),
                col.REWARDS: rng.standard_normal(idx.shape[0]).astype(np.float32),
                col.GLOBAL_REWARDS: np.zeros(idx.shape[0], np.float32),
                col.TERMINATEDS: term[idx],
                col.TRUNCATEDS: trunc[idx],
                col.NEXT_OBS: new_obs[idx],
                col.NEXT_STATE: new_state[idx],
            }
        )
        count += idx.shape[0]
        obs, state = new_obs, new_state
        t += 1
        ended_eps = np.zeros(0, np.int64)
        if last:  # every env's episode ends together (same horizon); start fresh ones
            ended_eps = episode.copy()
            episode = np.arange(next_episode, next_episode + num_envs, dtype=np.int64)
            next_episode += num_envs
            agent = np.tile(np.arange(agents, dtype=np.int64), num_envs)
            next_agent[:] = agents
            alive[:] = True
            obs = rng.random((slots, obs_dim), dtype=np.float32)
            state = rng.random((slots, schema.STATE_DIM), dtype=np.float32)
            t = 0
        else:  # the slot's terminal obs is at t+1; its replacement (fresh id) has its first obs at t+2
            respawn = ~alive
            for s in np.flatnonzero(respawn).tolist():
                e = env_of[s]
                agent[s] = next_agent[e]
                next_agent[e] += 1
                obs[s] = rng.random(obs_dim, dtype=np.float32)
            alive = respawn | (alive & ~end)
        if last or t % fragment == 0 or count >= total:
            cat = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
            out.append(TransitionBatch(**cat, ended_episodes=ended_eps))
            parts = []
    return out


def main() -> None:
    """Fill buffers and print the median sampling time."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--transitions", type=int, default=200_000)
    ap.add_argument("--capacity", type=int, default=None, help="buffer capacity in transitions (default: the stream's length)")
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--max-others", type=int, nargs="+", default=[29, 47])
    ap.add_argument("--repeats", type=int, default=200)
    ap.add_argument("--envs", type=int, default=4)
    ap.add_argument("--agents", type=int, default=30)
    ap.add_argument("--horizon", type=int, default=1000)
    ap.add_argument("--fragment", type=int, default=50)
    args = ap.parse_args()
    chunks = synthetic_chunks(args.transitions, args.envs, args.agents, args.horizon, args.fragment)
    n = sum(len(c) for c in chunks)
    capacity = n if args.capacity is None else args.capacity
    print(
        f"synthetic stream: {n:,} transitions in {len(chunks)} chunks, {args.envs} envs x {args.agents} agents, obs_dim 91; "
        f"capacity {capacity:,}"
    )
    for max_others in args.max_others:
        buf = JointStepReplayBuffer(capacity, obs_dim=91, state_dim=schema.STATE_DIM, act_dim=schema.ACT_DIM, max_others=max_others, seed=0)
        t0 = time.perf_counter()
        for c in chunks:
            buf.add(c)
        add_s = time.perf_counter() - t0
        for _ in range(10):
            buf.sample(args.batch)
        times, gather = [], []
        records = buf.joint_columns()
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            rows = buf.sample(args.batch)
            t1 = time.perf_counter()
            sent = sum(v.nbytes for v in rows.values())
            out = inject_global_state(records, rows)
            gather.append(time.perf_counter() - t1)
            times.append(t1 - t0)
        times_ms, gather_ms = 1000 * np.array(times), 1000 * np.array(gather)
        full = sum(v.nbytes for v in out.values())
        others, next_others = out[col.OTHERS_MASK].sum(1).mean(), out[col.NEXT_OTHERS_MASK].sum(1).mean()
        held = min(n, capacity)
        state_bytes = sum(v.nbytes for v in buf.get_state().values() if isinstance(v, np.ndarray))
        print(
            f"max_others={max_others:>3}: sample(B={args.batch}) median {np.median(times_ms):.2f} ms "
            f"(p90 {np.percentile(times_ms, 90):.2f} ms), connector gather median {np.median(gather_ms):.2f} ms "
            f"(sum of medians {np.median(times_ms) + np.median(gather_ms):.2f} ms); "
            f"per update a remote learner gets {sent / 2**10:,.0f} KiB (rows and lookups) instead of {full / 2**10:,.0f} KiB; "
            f"add {n / add_s:,.0f} transitions/s; sampleable {len(buf):,}; "
            f"mean others at t {others:.1f}, at t+1 {next_others:.1f}; "
            f"buffer arrays {buf.nbytes / 2**20:,.0f} MiB allocated ({buf.nbytes / held:,.0f} B/transition held) "
            f"of {buf.capacity_nbytes / 2**20:,.0f} MiB at capacity; checkpoint arrays {state_bytes / 2**20:,.0f} MiB",
            flush=True,
        )
    small = synthetic_chunks(20 * args.envs * args.agents, args.envs, args.agents, args.horizon, fragment=1, seed=1, first_episode=10**6)
    buf = JointStepReplayBuffer(
        capacity, obs_dim=91, state_dim=schema.STATE_DIM, act_dim=schema.ACT_DIM, max_others=max(args.max_others), seed=0
    )
    for c in chunks:
        buf.add(c)
    t0 = time.perf_counter()
    for c in small:
        buf.add(c)
    ms = 1000 * (time.perf_counter() - t0) / len(small)
    print(f"add of a one-step chunk ({args.envs} envs x {args.agents} agents) into the filled buffer: {ms:.2f} ms")


if __name__ == "__main__":
    main()
