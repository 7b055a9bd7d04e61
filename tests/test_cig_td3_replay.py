"""Joint-step replay buffer of CIG-TD3: exact cross-agent alignment, completeness, eviction, seeding, checkpointing.

Expectations come from an independent record of what was played: a scripted stream (built into
RLlib ``MultiAgentEpisode`` chunks exactly like ``MultiAgentEnvRunner`` does: ``add_env_step``,
``cut(len_lookback_buffer=1)``, ``to_numpy``) whose observations / states / actions / rewards
encode (episode, agent, env step), and a logging subclass of the real env sampled by a real
``MultiAgentEnvRunner``.
"""

from __future__ import annotations

import pickle
from collections import defaultdict
from dataclasses import fields

import numpy as np
import pytest
from fixtures import NO_BRAKES
from ray.rllib.core.columns import Columns
from ray.rllib.env.multi_agent_episode import MultiAgentEpisode

from coin_app.algorithms.td3 import buffer as buffer_module
from coin_app.algorithms.td3 import columns as col
from coin_app.algorithms.td3.buffer import JointStepReplayBuffer
from coin_app.algorithms.td3.connector import inject_global_state
from coin_app.algorithms.td3.transitions import TransitionBatch, agent_key, episode_key, episodes_to_transitions

OBS_DIM, STATE_DIM, ACT_DIM = 6, 10, 2
MAX_OTHERS = 12  # >= the most other agents with an observation at one step of the scripted stream (6 acting + 6 spawns)


# ----------------------------------------------------------------------------- scripted stream
def obs_of(q: int, a: int, t: int, terminal: bool = False) -> np.ndarray:
    return np.array([t, a, q, float(terminal), 0.5, q + 0.01 * a], np.float32)


def state_of(q: int, a: int, t: int, terminal: bool = False) -> np.ndarray:
    s = np.zeros(STATE_DIM, np.float32)
    s[:5] = [t, a, q, float(terminal), 7.0]
    return s


def action_of(q: int, a: int, t: int) -> np.ndarray:
    return np.array([a + 100 * q, t + 0.5], np.float32)


def reward_of(a: int, t: int) -> float:
    return 0.25 * a + t


def global_reward_of(q: int, t: int) -> float:  # the global reward in the info of env step t
    return 1000.0 * q + t


class Truth:
    """What was played, recorded independently of the buffer."""

    def __init__(self):
        self.acting = defaultdict(set)  # (q, t) -> agents that act at t
        self.present = defaultdict(dict)  # (q, t) -> {agent: terminal obs?}
        self.kind = {}  # (q, a, t) -> None | "term" | "trunc"
        self.env_t = {}  # q -> env steps played so far
        self.finished = set()
        self.key_of = {}  # q -> episode key
        self.batches = []  # per add: list of (q, a, t) transitions of that batch

    def sampleable(self) -> set[tuple[int, int, int]]:
        """The completeness rule, stated on the record: all of a finished episode, else t + 2 <= env steps played."""
        out = set()
        for q, a, t in self.kind:
            if q in self.finished or t + 2 <= self.env_t[q]:
                out.add((q, a, t))
        return out


class ScriptedEnv:
    """One env of a fake runner: plays episode scripts one after another into MultiAgentEpisodes and the Truth.

    A script is ``(q, initial_agents, horizon, events)``; ``events(t, acting, rng)`` returns
    ``(terminated, truncated, n_spawn)`` for env step t (spawns get their first obs at t+1). At
    ``t = horizon - 1`` every remaining agent is truncated. When every acting agent is done in a
    step, the episode is over and that step's spawns are dropped (the env adapter's rule).
    """

    def __init__(self, scripts, truth: Truth, rng: np.random.Generator):
        self.scripts = list(scripts)
        self.truth = truth
        self.rng = rng
        self.ep = None

    def _reset(self) -> bool:
        if not self.scripts:
            return False
        self.q, n0, self.horizon, self.events = self.scripts.pop(0)
        self.t = 0
        self.alive = set(range(n0))
        self.next_id = n0
        self.ep = MultiAgentEpisode()
        self.truth.key_of[self.q] = episode_key(self.ep.id_)
        self.truth.env_t[self.q] = 0
        obs = {f"agent{a}": obs_of(self.q, a, 0) for a in self.alive}
        infos = {
            f"agent{a}": {"env_step": 0, "state": state_of(self.q, a, 0), "global_reward": global_reward_of(self.q, 0)} for a in self.alive
        }
        for a in self.alive:
            self.truth.present[(self.q, 0)][a] = False
        self.ep.add_env_reset(observations=obs, infos=infos)
        return True

    def step(self, finished: list) -> None:
        if self.ep is None and not self._reset():
            return
        q, t = self.q, self.t
        acting = sorted(self.alive)
        term, trunc, n_spawn = self.events(t, acting, self.rng)
        term, trunc = set(term), set(trunc) - set(term)
        if t == self.horizon - 1:
            trunc = set(acting) - term
        ended = term | trunc
        over = ended == set(acting)
        spawned = [] if over else list(range(self.next_id, self.next_id + n_spawn))
        self.next_id += len(spawned)
        obs, infos = {}, {}
        for a in acting + spawned:
            terminal = a in ended
            obs[f"agent{a}"] = obs_of(q, a, t + 1, terminal)
            infos[f"agent{a}"] = {"env_step": t + 1, "state": state_of(q, a, t + 1, terminal), "global_reward": global_reward_of(q, t + 1)}
            self.truth.present[(q, t + 1)][a] = terminal
        for a in acting:
            self.truth.acting[(q, t)].add(a)
            self.truth.kind[(q, a, t)] = "term" if a in term else "trunc" if a in trunc else None
        terms = {f"agent{a}": a in term for a in acting}
        truncs = {f"agent{a}": a in trunc for a in acting}
        terms["__all__"] = over
        truncs["__all__"] = over and not term
        self.ep.add_env_step(
            observations=obs,
            actions={f"agent{a}": action_of(q, a, t) for a in acting},
            rewards={f"agent{a}": reward_of(a, t) for a in acting},
            infos=infos,
            terminateds=terms,
            truncateds=truncs,
        )
        self.alive = (self.alive - ended) | set(spawned)
        self.t += 1
        self.truth.env_t[q] = self.t
        if over:
            assert self.ep.is_done
            self.truth.finished.add(q)
            finished.append(self.ep)
            self.ep = None

    def cut(self) -> MultiAgentEpisode | None:
        if self.ep is None:
            return None
        chunk, self.ep = self.ep, self.ep.cut(len_lookback_buffer=1)
        return chunk


def run_fake_runner(envs: list[ScriptedEnv], steps_per_call: list[int], truth: Truth, to_numpy: bool = True):
    """Yield one list of chunks per sample() call, like MultiAgentEnvRunner (done episodes + cut ongoing ones)."""
    for n in steps_per_call:
        finished: list[MultiAgentEpisode] = []
        for _ in range(n):
            for env in envs:
                env.step(finished)
        chunks = finished + [c for c in (env.cut() for env in envs) if c is not None]
        if to_numpy:
            for c in chunks:
                c.to_numpy()
        yield chunks[::-1]  # order of episodes inside a call must not matter


def edge_case_script(q: int):
    """Hand-written: crash with disappearance, spawn / terminal obs exactly on chunk boundaries (every 4 steps), ..."""
    plan = {
        1: ([1], [], 1),  # agent1 crashes at 1 (terminal obs at 2, then gone); agent3 spawns at 2
        3: ([0], [], 1),  # agent0 crashes at 3: terminal obs at 4 = chunk boundary; agent4 spawns at 4 (boundary)
        4: ([4], [], 1),  # agent4 crashes on its first step; agent5 spawns at 5
        6: ([], [2], 2),  # agent2 times out; agents 6 and 7 spawn at 7
        7: ([], [], 1),  # agent8 spawns at 8 (boundary) while nobody ends
        11: ([3, 5], [], 0),
    }
    return (q, 3, 14, lambda t, acting, rng: plan.get(t, ([], [], 0)))


def random_script(q: int, horizon: int, n0: int = 3, cap: int = 6):
    def events(t, acting, rng):
        u = rng.random(len(acting))
        term = [a for a, x in zip(acting, u) if x < 0.12]
        trunc = [a for a, x in zip(acting, u) if 0.12 <= x < 0.17]
        if len(term) + len(trunc) == len(acting):  # the episode only ends at its horizon (see all_die_script)
            term, trunc = term[1:], trunc[1:] if not term else trunc
        left = len(acting) - len(term) - len(trunc)
        n_spawn = len(term) + len(trunc) + int(rng.random() < 0.15) - int(rng.random() < 0.3)  # mostly replacements
        return term, trunc, int(np.clip(n_spawn, 2 - left, cap - left))

    return (q, n0, horizon, events)


def all_die_script(q: int):
    """Two agents; both crash at step 5 while a spawn is requested: the episode ends and the spawn is dropped."""
    return (q, 2, 50, lambda t, acting, rng: (acting, [], 2) if t == 5 else ([], [], 0))


def make_stream(seed: int = 0):
    truth = Truth()
    rng = np.random.default_rng(seed)
    env0 = ScriptedEnv([edge_case_script(0), random_script(2, 23), random_script(4, 30), random_script(6, 200)], truth, rng)
    env1 = ScriptedEnv([random_script(1, 19), all_die_script(3), random_script(5, 200)], truth, rng)
    return truth, [env0, env1]


def fill(buf: JointStepReplayBuffer, calls: list[int], seed: int = 0, to_numpy: bool = True, after_add=None) -> Truth:
    truth, envs = make_stream(seed)
    for chunks in run_fake_runner(envs, calls, truth, to_numpy):
        batch = episodes_to_transitions(chunks)
        truth.batches.append(
            [(q, int(a), int(t)) for e, a, t in zip(batch.episode, batch.agent, batch.env_step) for q in [_q_of(truth, int(e))]]
        )
        buf.add(batch)
        if after_add is not None:
            after_add(buf, truth)
    return truth


def _q_of(truth: Truth, key: int) -> int:
    return next(q for q, k in truth.key_of.items() if k == key)


def check_rows(out: dict[str, np.ndarray], truth: Truth, buf: JointStepReplayBuffer, subset: bool = False) -> None:
    """Every column of every sampled row against the record (``subset``: others may be masked out by eviction)."""
    B, N = out["obs"].shape[0], buf.max_others
    assert out["others_state"].shape == (B, N, STATE_DIM) and out["others_actions"].shape == (B, N, ACT_DIM)
    assert out["next_others_obs"].shape == (B, N, OBS_DIM) and out["next_others_state"].shape == (B, N, STATE_DIM)
    for name in (
        "obs",
        "state",
        "actions",
        "rewards",
        "global_rewards",
        "new_obs",
        "new_state",
        "others_state",
        "others_actions",
        "others_rewards",
    ):
        assert out[name].dtype == np.float32, name
    for name in ("terminateds", "truncateds", "others_mask", "next_others_mask"):
        assert out[name].dtype == bool, name
    assert out["env_step"].dtype == np.int64 and out["episode"].dtype == np.int64
    for i in range(B):
        t, a, q = (int(v) for v in out["obs"][i, :3])
        assert out["obs"][i, 3] == 0.0  # o_t is never a terminal observation
        np.testing.assert_array_equal(out["obs"][i], obs_of(q, a, t))
        np.testing.assert_array_equal(out["state"][i], state_of(q, a, t))
        assert out["env_step"][i] == t and out["episode"][i] == truth.key_of[q] and out["agent"][i] == a
        kind = truth.kind[(q, a, t)]
        np.testing.assert_array_equal(out["actions"][i], action_of(q, a, t))
        assert out["rewards"][i] == np.float32(reward_of(a, t))
        assert out["global_rewards"][i] == np.float32(global_reward_of(q, t + 1))
        assert out["terminateds"][i] == (kind == "term") and out["truncateds"][i] == (kind == "trunc")
        np.testing.assert_array_equal(out["new_obs"][i], obs_of(q, a, t + 1, kind is not None))
        np.testing.assert_array_equal(out["new_state"][i], state_of(q, a, t + 1, kind is not None))
        # others that acted at t (ego excluded)
        m = out["others_mask"][i]
        got = {}
        for s, act, rew in zip(out["others_state"][i][m], out["others_actions"][i][m], out["others_rewards"][i][m]):
            oa = int(s[1])
            np.testing.assert_array_equal(s, state_of(q, oa, t))
            np.testing.assert_array_equal(act, action_of(q, oa, t))
            assert rew == np.float32(reward_of(oa, t))
            assert oa not in got
            got[oa] = s
        want = truth.acting[(q, t)] - {a}
        assert a not in got
        assert (set(got) <= want) if subset else (set(got) == want), (q, a, t, sorted(got), sorted(want))
        assert not out["others_state"][i][~m].any() and not out["others_actions"][i][~m].any()  # padding is zero
        assert not out["others_rewards"][i][~m].any()
        # every other agent with an observation at t+1 (continuing, terminated at t, spawned at t+1)
        m1 = out["next_others_mask"][i]
        got1 = set()
        for s, o in zip(out["next_others_state"][i][m1], out["next_others_obs"][i][m1]):
            oa = int(s[1])
            terminal = truth.present[(q, t + 1)].get(oa)
            assert terminal is not None, (q, a, t, oa)
            np.testing.assert_array_equal(s, state_of(q, oa, t + 1, terminal))
            np.testing.assert_array_equal(o, obs_of(q, oa, t + 1, terminal))
            assert oa not in got1
            got1.add(oa)
        want1 = set(truth.present[(q, t + 1)]) - {a}
        assert a not in got1
        assert (got1 <= want1) if subset else (got1 == want1), (q, a, t, sorted(got1), sorted(want1))
        assert not out["next_others_obs"][i][~m1].any()


def sample_full(buf: JointStepReplayBuffer, n: int) -> dict[str, np.ndarray]:
    """``n`` sampled rows with their global columns, gathered as the learner connector gathers them."""
    return inject_global_state(buf.joint_columns(), buf.sample(n))


def sample_many(buf: JointStepReplayBuffer, total: int) -> dict[str, np.ndarray]:
    """``total`` draws in calls of at most len(buf) (sample() refuses more than the sampleable count)."""
    parts = []
    while total > 0:
        parts.append(sample_full(buf, min(total, len(buf))))
        total -= parts[-1]["obs"].shape[0]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def unique_rows(out: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The first draw of every distinct transition."""
    keys = np.stack([out["episode"], out["agent"], out["env_step"]], axis=1)
    _, first = np.unique(keys, axis=0, return_index=True)
    return {k: v[np.sort(first)] for k, v in out.items()}


CALLS = [4] * 12 + [3, 5, 2, 7, 1, 1, 6] + [4] * 6  # boundaries every 4 env steps first, then irregular


# ----------------------------------------------------------------------------- tests
def test_scripted_stream_every_column_matches_the_record():
    buf = JointStepReplayBuffer(10_000, OBS_DIM, STATE_DIM, ACT_DIM, max_others=MAX_OTHERS, seed=0)

    def after_add(buf, truth):
        assert len(buf) == len(truth.sampleable())  # completeness rule, call by call

    truth = fill(buf, CALLS, after_add=after_add)
    assert {0, 1, 2, 3, 4} <= truth.finished and not {5, 6} & truth.finished  # finished and ongoing episodes
    expected = truth.sampleable()
    assert buf.num_added == len(truth.kind)  # the converter produced every played transition once
    # every observation is stored once, also across chunk boundaries: o_t and o_{t+1} of all transitions, deduplicated
    assert buf.num_obs_added == len({(q, a, s) for (q, a, t) in truth.kind for s in (t, t + 1)})
    assert buf.num_pending == len(truth.kind) - len(expected)
    out = sample_many(buf, 20 * len(expected))
    check_rows(unique_rows(out), truth, buf)
    keys = {(_q_of(truth, int(e)), int(a), int(t)) for e, a, t in zip(out["episode"], out["agent"], out["env_step"])}
    assert keys == expected  # uniform draws cover every sampleable transition and nothing else
    # the edge cases really are in the stream
    assert truth.present[(0, 4)] == {0: True, 2: False, 3: False, 4: False}  # terminal obs and a spawn on a boundary
    assert truth.kind[(0, 4, 4)] == "term" and (0, 4, 5) not in truth.kind  # crash on the first step, then gone
    assert truth.kind[(3, 0, 5)] == "term" and truth.present[(3, 6)] == {0: True, 1: True}  # spawns dropped at the end
    assert max(len(v) for v in truth.present.values()) > 5


def test_column_names_are_rllib_columns_and_the_sample_keys():
    assert (col.OBS, col.ACTIONS, col.REWARDS, col.TERMINATEDS, col.TRUNCATEDS, col.NEXT_OBS) == (
        Columns.OBS,
        Columns.ACTIONS,
        Columns.REWARDS,
        Columns.TERMINATEDS,
        Columns.TRUNCATEDS,
        Columns.NEXT_OBS,
    )
    assert {f.name for f in fields(TransitionBatch)} == set(col.EGO + col.ORIGIN) | {"ended_episodes"}
    buf = JointStepReplayBuffer(1000, OBS_DIM, STATE_DIM, ACT_DIM, max_others=MAX_OTHERS, seed=0)
    fill(buf, CALLS[:6])
    assert set(buf.sample(4)) == set(col.SAMPLED)
    assert set(sample_full(buf, 4)) == set(col.EGO + col.OTHERS + col.ORIGIN)


def test_transition_is_held_back_until_late_spawns_arrive():
    truth, envs = make_stream()
    buf = JointStepReplayBuffer(1000, OBS_DIM, STATE_DIM, ACT_DIM, max_others=MAX_OTHERS, seed=0)
    calls = run_fake_runner(envs, [4, 4], truth)
    buf.add(episodes_to_transitions(next(calls)))  # env steps 0..4 of episodes 0 and 1
    # agent4 of episode 0 spawns at step 4 = the cut: its first obs comes with the next chunk only
    out = sample_many(buf, 200)
    assert out["env_step"].max() <= 2 and len(buf) == len(truth.sampleable())
    buf.add(episodes_to_transitions(next(calls)))
    out = unique_rows(sample_many(buf, 4000))
    rows = (out["episode"] == truth.key_of[0]) & (out["env_step"] == 3)
    assert rows.any()
    for i in np.flatnonzero(rows):  # every transition at t=3 sees the agent that spawned at t+1=4
        others = {int(s[1]) for s in out["next_others_state"][i][out["next_others_mask"][i]]}
        assert 4 in others or out["agent"][i] == 4
    check_rows(out, truth, buf)


def test_converter_on_list_episodes_and_chunk_structure():
    truth, envs = make_stream()
    n_chunks = 0
    seen = set()
    for chunks in run_fake_runner(envs, CALLS, truth, to_numpy=False):
        n_chunks += len(chunks)
        b = episodes_to_transitions(chunks)
        for e, a, t, term, trunc in zip(b.episode, b.agent, b.env_step, b.terminateds, b.truncateds):
            key = (_q_of(truth, int(e)), int(a), int(t))
            assert key not in seen  # each transition exactly once over all chunks
            seen.add(key)
            kind = truth.kind[key]
            assert bool(term) == (kind == "term") and bool(trunc) == (kind == "trunc")
        for i in range(len(b)):
            q, a, t = _q_of(truth, int(b.episode[i])), int(b.agent[i]), int(b.env_step[i])
            np.testing.assert_array_equal(b.obs[i], obs_of(q, a, t))
            np.testing.assert_array_equal(b.new_state[i], state_of(q, a, t + 1, truth.kind[(q, a, t)] is not None))
            assert b.global_rewards[i] == np.float32(global_reward_of(q, t + 1))
    assert seen == set(truth.kind)
    assert n_chunks > len(CALLS)
    assert agent_key("agent12") == 12 and agent_key("agent_3") == 3 and agent_key(5) == 5
    assert agent_key("car-x") == agent_key("car-x") != agent_key("car-y")  # other ids: a stable hash
    assert episode_key("abc") == episode_key("abc") != episode_key("abd") and episode_key("abc") >= 0
    empty = episodes_to_transitions([])
    assert len(empty) == 0


def test_time_limit_agents_are_truncated_not_terminated():
    # RLlib marks every agent alive at the end of an episode terminated *and* truncated; the converter keeps truncated only
    truth = Truth()
    env = ScriptedEnv([(0, 2, 3, lambda t, acting, rng: ([], [], 0))], truth, np.random.default_rng(0))
    finished: list = []
    for _ in range(3):
        env.step(finished)
    (ep,) = finished
    assert all(sa.is_terminated and sa.is_truncated for sa in ep.agent_episodes.values())
    b = episodes_to_transitions([ep])
    assert b.truncateds.sum() == 2 and not b.terminateds.any()
    assert list(b.ended_episodes) == [truth.key_of[0]]


def test_seeded_sampling_and_state_round_trip():
    def build(seed):
        buf = JointStepReplayBuffer(10_000, OBS_DIM, STATE_DIM, ACT_DIM, max_others=MAX_OTHERS, seed=seed)
        fill(buf, CALLS[:15])
        return buf

    a, b, c = build(7), build(7), build(8)  # same data, but each build has its own random RLlib episode ids
    for _ in range(3):
        sa, sb = sample_full(a, 64), sample_full(b, 64)
        for k in sa:
            if k != "episode":  # the episode column is a hash of RLlib's random episode uuid
                np.testing.assert_array_equal(sa[k], sb[k])
    assert not np.array_equal(sample_full(a, 64)["env_step"], sample_full(c, 64)["env_step"])

    state = pickle.loads(pickle.dumps(a.get_state()))
    expected = [sample_full(a, 32) for _ in range(3)]
    sample_full(a, 5)  # mutating the original afterwards must not touch the saved state
    restored = JointStepReplayBuffer(10_000, OBS_DIM, STATE_DIM, ACT_DIM, max_others=MAX_OTHERS, seed=123)
    restored.set_state(state)
    assert len(restored) == len(b)
    for want in expected:
        got = sample_full(restored, 32)
        for k in want:
            np.testing.assert_array_equal(got[k], want[k])
    # adding the same data after a restore keeps both in lockstep
    truth, envs = make_stream()
    stream = list(run_fake_runner(envs, CALLS, truth))
    x = JointStepReplayBuffer(10_000, OBS_DIM, STATE_DIM, ACT_DIM, max_others=MAX_OTHERS, seed=3)
    for chunks in stream[:10]:
        x.add(episodes_to_transitions(chunks))
    y = JointStepReplayBuffer(10_000, OBS_DIM, STATE_DIM, ACT_DIM, max_others=MAX_OTHERS, seed=99)
    y.set_state(x.get_state())
    for chunks in stream[10:]:
        batch = episodes_to_transitions(chunks)
        x.add(batch)
        y.add(batch)
        sx, sy = sample_full(x, 16), sample_full(y, 16)
        for k in sx:
            np.testing.assert_array_equal(sx[k], sy[k])
    other_cfg = JointStepReplayBuffer(10_000, OBS_DIM, STATE_DIM, ACT_DIM, max_others=MAX_OTHERS + 1, seed=0)
    with pytest.raises(ValueError, match="config"):
        other_cfg.set_state(x.get_state())


@pytest.mark.parametrize(
    "capacity,obs_capacity,step_capacity",
    [(40, None, None), (60, 55, 500), (100, 1000, 20), (45, 60, 22)],
)
def test_eviction_never_yields_overwritten_data(capacity, obs_capacity, step_capacity):
    masked = [0]

    def after_add(buf, truth):
        added = [k for batch in truth.batches for k in batch]
        assert buf.num_added == len(added)
        if len(buf) == 0:
            return
        out = unique_rows(sample_many(buf, 300))
        check_rows(out, truth, buf, subset=True)
        # a sampled transition is among the last `capacity` added ones
        recent = set()
        after = 0
        for batch in reversed(truth.batches):
            if after >= capacity:
                break
            recent.update(batch)
            after += len(batch)
        for e, a, t in zip(out["episode"], out["agent"], out["env_step"]):
            key = (_q_of(truth, int(e)), int(a), int(t))
            assert key in recent and key in truth.sampleable()
        for i in range(out["obs"].shape[0]):
            q, a, t = (int(v) for v in out["obs"][i, [2, 1, 0]])
            masked[0] += len(truth.acting[(q, t)] - {a}) - int(out["others_mask"][i].sum())
        assert len(buf) <= capacity

    buf = JointStepReplayBuffer(
        capacity, OBS_DIM, STATE_DIM, ACT_DIM, max_others=MAX_OTHERS, seed=1, obs_capacity=obs_capacity, step_capacity=step_capacity
    )
    fill(buf, CALLS, after_add=after_add)
    assert buf.num_added > 4 * capacity
    if obs_capacity is not None and obs_capacity < capacity:
        assert masked[0] > 0  # rows of others evicted before the transitions: masked out, never wrong


def test_bad_inputs_raise_clear_errors():
    buf = JointStepReplayBuffer(1000, OBS_DIM, STATE_DIM, ACT_DIM, max_others=3, seed=0)
    with pytest.raises(ValueError, match="only 0 are sampleable"):
        buf.sample(1)
    truth, envs = make_stream()
    chunks = next(run_fake_runner(envs, [8], truth))
    batch = episodes_to_transitions(chunks)
    # episode 0 has 5 agents with an observation at env step 7 (agent2's terminal obs, 3, 5 and the spawns 6, 7)
    with pytest.raises(
        ValueError, match=r"has (\d+) agents with an observation \(ego \+ (\d+) others\) but max_others=3; raise max_others"
    ):
        buf.add(batch)
    assert len(buf) == 0 and buf.num_added == 0 and buf.num_pending == 0  # nothing stored
    big = JointStepReplayBuffer(1000, OBS_DIM, STATE_DIM, ACT_DIM, max_others=MAX_OTHERS, seed=0)
    big.add(batch)
    n = len(big)
    with pytest.raises(ValueError, match=f"cannot sample {n + 1} transitions: only {n} are sampleable"):
        big.sample(n + 1)
    for bad in (0, -3, 2.5):
        with pytest.raises(ValueError, match="batch_size"):
            big.sample(bad)
    with pytest.raises(ValueError, match="duplicate transition"):
        big.add(TransitionBatch.concat([batch, batch]))
    with pytest.raises(ValueError, match=r"TransitionBatch.obs has shape \(\d+, 6\), expected \(\d+, 7\)"):
        JointStepReplayBuffer(1000, 7, STATE_DIM, ACT_DIM, max_others=MAX_OTHERS).add(batch)
    with pytest.raises(ValueError, match="exceeds the buffer capacity 10"):
        JointStepReplayBuffer(10, OBS_DIM, STATE_DIM, ACT_DIM, max_others=MAX_OTHERS).add(batch)
    with pytest.raises(ValueError, match="max_others must be an integer"):
        JointStepReplayBuffer(10, OBS_DIM, max_others=-1)


# ----------------------------------------------------------------------------- memory that grows with use
M_COLS = MAX_OTHERS + 1
# bytes of one row of each ring, from the column types the module doc lists (float32 obs / state / action /
# rewards, int64 write indices and keys, int32 entry columns, bool flags)
POOL_ROW = 4 * (OBS_DIM + STATE_DIM) + 3 * 8  # obs, state; owner, transition acting from it, transition arriving in it
TRANSITION = 4 * 8 + 4 * ACT_DIM + 2 * 4 + 2 + 3 * 8 + 1  # o_t, o_t+1, entries t, t+1; action; rewards; flags; step, episode, agent; ok
ENTRY = 4 * M_COLS + 4 + 2 * 8  # pool rows, row count; episode, env step


def stored_bytes(truth: Truth) -> int:
    """Bytes the rows of everything added so far need: one pool row per distinct observation, one entry per (episode, step)."""
    added = [k for batch in truth.batches for k in batch]
    rows = {(q, a, s) for q, a, t in added for s in (t, t + 1)}
    entries = {(q, s) for q, a, t in added for s in (t, t + 1)}
    return len(rows) * POOL_ROW + len(added) * TRANSITION + len(entries) * ENTRY


def full_bytes(capacity: int) -> int:
    """Bytes of a full buffer with the default ring sizes (plus the pool's and the actions' padding rows)."""
    obs_capacity, step_capacity = capacity + capacity // 4 + 64, capacity // 2 + 64
    return (obs_capacity + 1) * POOL_ROW + capacity * TRANSITION + 4 * ACT_DIM + step_capacity * ENTRY


def assert_same_samples(x: JointStepReplayBuffer, y: JointStepReplayBuffer, draws: int = 3, batch_size: int = 32) -> None:
    """``x`` and ``y`` return the same samples, column by column."""
    assert len(x) == len(y)
    for _ in range(draws):
        sx, sy = sample_full(x, batch_size), sample_full(y, batch_size)
        assert sx.keys() == sy.keys()
        for k in sx:
            np.testing.assert_array_equal(sx[k], sy[k])


def test_memory_is_proportional_to_what_is_stored(monkeypatch):
    monkeypatch.setattr(buffer_module, "INITIAL_ROWS", 16)
    capacity = 10_000_000  # the official code's capacity
    buf = JointStepReplayBuffer(capacity, OBS_DIM, STATE_DIM, ACT_DIM, max_others=MAX_OTHERS, seed=0)
    assert buf.capacity_nbytes == full_bytes(capacity)
    sizes = [buf.nbytes]
    first_rows = 16 * (POOL_ROW + TRANSITION + ENTRY) + POOL_ROW + 4 * ACT_DIM  # initial rows and the two padding rows
    assert sizes[0] == first_rows

    def after_add(buf, truth):
        need = stored_bytes(truth)
        assert need <= buf.nbytes <= 2 * need + first_rows  # every ring at most doubles past what it holds
        sizes.append(buf.nbytes)

    truth = fill(buf, CALLS, after_add=after_add)
    assert sizes == sorted(sizes) and sizes[-1] > 4 * sizes[0]  # grew monotonically with the data
    assert buf.nbytes < buf.capacity_nbytes / 1000
    check_rows(unique_rows(sample_many(buf, 2000)), truth, buf)
    # with the default first allocation a small run still takes about a megabyte, not gigabytes
    monkeypatch.undo()
    small_run = JointStepReplayBuffer(capacity, OBS_DIM, STATE_DIM, ACT_DIM, max_others=MAX_OTHERS, seed=0)
    fill(small_run, CALLS)
    assert small_run.nbytes < 2**21 and small_run.capacity_nbytes > 2 * 10**9

    # a small buffer grows to its full size once its rings wrap, and stops there
    monkeypatch.setattr(buffer_module, "INITIAL_ROWS", 16)
    small = JointStepReplayBuffer(40, OBS_DIM, STATE_DIM, ACT_DIM, max_others=MAX_OTHERS, seed=0)
    sizes = [small.nbytes]
    fill(small, CALLS, after_add=lambda buf, truth: sizes.append(buf.nbytes))
    assert small.capacity_nbytes == full_bytes(40)
    assert sizes == sorted(sizes) and sizes[0] < sizes[-1] == small.capacity_nbytes
    assert sizes.index(sizes[-1]) < len(sizes) // 2  # reached early (the stream wraps every ring several times), then flat


@pytest.mark.parametrize("initial_rows", [1, 5])
def test_rings_growing_from_a_few_rows_store_sample_evict_and_checkpoint_exactly(monkeypatch, initial_rows):
    monkeypatch.setattr(buffer_module, "INITIAL_ROWS", initial_rows)
    test_scripted_stream_every_column_matches_the_record()
    test_seeded_sampling_and_state_round_trip()
    for capacity, obs_capacity, step_capacity in [(40, None, None), (60, 55, 500), (100, 1000, 20), (45, 60, 22)]:
        test_eviction_never_yields_overwritten_data(capacity, obs_capacity, step_capacity)


def test_checkpoint_of_a_small_run_is_small_and_resumes_identically():
    capacity = 10_000_000
    truth, envs = make_stream()
    stream = [episodes_to_transitions(chunks) for chunks in run_fake_runner(envs, CALLS, truth)]
    x = JointStepReplayBuffer(capacity, OBS_DIM, STATE_DIM, ACT_DIM, max_others=MAX_OTHERS, seed=4)
    for batch in stream[:12]:
        truth.batches.append([(_q_of(truth, int(e)), int(a), int(t)) for e, a, t in zip(batch.episode, batch.agent, batch.env_step)])
        x.add(batch)
    blob = pickle.dumps(x.get_state())
    need = stored_bytes(truth)
    assert need <= len(blob) <= need + 2**15  # the rows written (and the small index maps), not the capacity
    assert len(blob) < x.capacity_nbytes / 10_000
    y = JointStepReplayBuffer(capacity, OBS_DIM, STATE_DIM, ACT_DIM, max_others=MAX_OTHERS, seed=99)
    y.set_state(pickle.loads(blob))
    assert y.nbytes == x.nbytes and y.num_added == x.num_added and y.num_obs_added == x.num_obs_added
    assert_same_samples(x, y)
    for batch in stream[12:]:  # both keep growing in lockstep
        x.add(batch)
        y.add(batch)
        assert_same_samples(x, y, draws=1, batch_size=16)
    assert y.nbytes == x.nbytes


def v1_state(state: dict, capacity: int, obs_capacity: int, step_capacity: int) -> dict:
    """A version-1 state (every array at full size, as coin_app saved it before) with the content of a version-2 ``state``."""
    P, C, K = obs_capacity, capacity, step_capacity
    rows_fill = {  # array -> (rows in version 1, value of unwritten rows)
        **{name: (P + 1, 0) for name in ("_pool_obs", "_pool_state")},
        **{name: (P + 1, -1) for name in ("_pool_owner", "_pool_tr_obs", "_pool_tr_next")},
        "_tr_action": (C + 1, 0),
        **{
            name: (C, 0)
            for name in (
                "_tr_obs", "_tr_next", "_tr_entry_t", "_tr_entry_t1", "_tr_reward", "_tr_greward",
                "_tr_term", "_tr_trunc", "_tr_step", "_tr_episode", "_tr_agent", "_ok",
            )
        },
        "_step_rows": (K, P),
        **{name: (K, 0) for name in ("_step_count", "_step_episode", "_step_t")},
    }  # fmt: skip
    out = dict(state, version=1)
    for name, (rows, fill) in rows_fill.items():
        arr = np.asarray(state[name])
        full = np.full((rows, *arr.shape[1:]), fill, arr.dtype)
        full[: arr.shape[0]] = arr
        out[name] = full
    return out


@pytest.mark.parametrize("capacity", [10_000, 40])  # 40: every ring has wrapped
def test_version_1_state_still_loads(capacity):
    truth, envs = make_stream()
    stream = [episodes_to_transitions(chunks) for chunks in run_fake_runner(envs, CALLS, truth)]
    x = JointStepReplayBuffer(capacity, OBS_DIM, STATE_DIM, ACT_DIM, max_others=MAX_OTHERS, seed=2)
    for batch in stream[:14]:
        x.add(batch)
    old = v1_state(x.get_state(), capacity, capacity + capacity // 4 + 64, capacity // 2 + 64)
    old = pickle.loads(pickle.dumps(old))
    y = JointStepReplayBuffer(capacity, OBS_DIM, STATE_DIM, ACT_DIM, max_others=MAX_OTHERS, seed=7)
    y.set_state(old)
    assert y.nbytes == x.nbytes  # restored at the size its rows need, not at full size
    assert_same_samples(x, y)
    saved_again = y.get_state()
    assert saved_again["version"] == 2
    for k, v in x.get_state().items():
        if isinstance(v, np.ndarray):
            np.testing.assert_array_equal(saved_again[k], v)
    for batch in stream[14:]:
        x.add(batch)
        y.add(batch)
        assert_same_samples(x, y, draws=1, batch_size=8)
    # states that fit neither version are refused and leave the buffer as it was
    z = JointStepReplayBuffer(capacity, OBS_DIM, STATE_DIM, ACT_DIM, max_others=MAX_OTHERS, seed=7)
    with pytest.raises(ValueError, match="version 3"):
        z.set_state(dict(x.get_state(), version=3))
    bad = dict(old)
    bad["_tr_reward"] = bad["_tr_reward"][:-1]  # version 1 wants the full size
    with pytest.raises(ValueError, match="_tr_reward has shape"):
        z.set_state(bad)
    cut = x.get_state()
    cut["_pool_obs"] = cut["_pool_obs"][:-1]  # version 2 wants every written row
    with pytest.raises(ValueError, match="_pool_obs has shape"):
        z.set_state(cut)
    assert len(z) == 0 and z.num_added == 0 and z.nbytes == JointStepReplayBuffer(capacity, OBS_DIM, STATE_DIM, ACT_DIM, MAX_OTHERS).nbytes


# ----------------------------------------------------------------------------- the real RLlib path
@pytest.fixture(scope="module")
def real_runner_data():
    import torch
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig
    from ray.rllib.env.multi_agent_env_runner import MultiAgentEnvRunner
    from ray.tune.registry import register_env

    from coin_app.adapters.rllib_env import CoinMultiAgentEnv
    from coin_app.algorithms.common import policy_mapping_fn

    class LoggingEnv(CoinMultiAgentEnv):
        """Records every (episode, env step, agent) -> obs / state / action / reward / flags it hands out."""

        def __init__(self, config=None):
            super().__init__(config)
            self.n_episodes = 0
            self.log = {}  # (episode no, env step, agent) -> dict

        def reset(self, *, seed=None, options=None):
            obs, infos = super().reset(seed=seed, options=options)
            self.n_episodes += 1
            for aid, info in infos.items():
                info["log_id"] = (id(self), self.n_episodes)
                self.log[(self.n_episodes, info["env_step"], aid)] = {"obs": obs[aid].copy(), "state": info["state"].copy()}
            return obs, infos

        def step(self, action_dict):
            t = self.driving_env.sim.episode_step
            for aid, act in action_dict.items():
                self.log[(self.n_episodes, t, aid)]["action"] = np.asarray(act, np.float32).copy()
            obs, rewards, terms, truncs, infos = super().step(action_dict)
            for aid, info in infos.items():
                info["log_id"] = (id(self), self.n_episodes)
                self.log[(self.n_episodes, info["env_step"], aid)] = {
                    "obs": obs[aid].copy(),
                    "state": info["state"].copy(),
                    "g": info["global_reward"],
                }
            for aid in rewards:
                rec = self.log[(self.n_episodes, t, aid)]
                rec.update(reward=rewards[aid], term=terms[aid], trunc=truncs[aid])
            return obs, rewards, terms, truncs, infos

    torch.set_num_threads(1)
    register_env("coin-replay-logging-v0", lambda cfg: LoggingEnv(cfg))
    # the brief's tiny config; cars without brakes so that some crash or leave the road and respawn
    env_config = {"num_agents": 4, "horizon": 40, "max_agent_steps": 30, "delay_done": 2, "dynamics": NO_BRAKES}
    config = (
        PPOConfig()
        .environment("coin-replay-logging-v0", env_config=env_config)
        .env_runners(num_env_runners=0, num_envs_per_env_runner=2)
        .multi_agent(policies={"shared"}, policy_mapping_fn=policy_mapping_fn)
        .rl_module(model_config=DefaultModelConfig(fcnet_hiddens=[8]))
        .debugging(seed=0)
    )
    runner = MultiAgentEnvRunner(config=config)
    buf = JointStepReplayBuffer(20_000, obs_dim=91, state_dim=10, act_dim=2, max_others=12, seed=0)
    episode_of: dict[int, tuple[int, int]] = {}  # episode key -> (env id, episode no)
    done: set[int] = set()
    converted = []
    try:
        for _ in range(20):
            chunks = runner.sample(num_timesteps=14, random_actions=True)  # 7 env steps per env per call
            for ep in chunks:
                for sa in ep.agent_episodes.values():
                    for info in sa.get_infos():
                        episode_of.setdefault(episode_key(ep.id_), info["log_id"])
                if ep.is_done:
                    done.add(episode_key(ep.id_))
            batch = episodes_to_transitions(chunks)
            converted.append(batch)
            buf.add(batch)
        logs = {id(e.unwrapped): e.unwrapped.log for e in runner.env.unwrapped.envs}
    finally:
        runner.stop()
    return buf, TransitionBatch.concat(converted), episode_of, done, logs


def test_real_env_runner_stream_matches_the_env_log(real_runner_data):
    buf, batch, episode_of, done, logs = real_runner_data
    log = {(env, n, t, aid): rec for env, lg in logs.items() for (n, t, aid), rec in lg.items()}
    acting = defaultdict(set)  # (env, n, t) -> agents that got an action at t
    present = defaultdict(set)  # (env, n, t) -> agents with an observation at t
    for (env, n, t, aid), rec in log.items():
        present[(env, n, t)].add(aid)
        if "action" in rec:
            acting[(env, n, t)].add(aid)
    # converter: exactly the logged agent steps of the sampled episodes, once each
    sampled_eps = set(episode_of.values())
    logged = {(env, n, t, aid) for (env, n, t, aid), rec in log.items() if "reward" in rec and (env, n) in sampled_eps}
    converted = {(*episode_of[int(e)], int(t), f"agent{a}") for e, a, t in zip(batch.episode, batch.agent, batch.env_step)}
    assert converted == logged and len(converted) == len(batch)
    assert any(int(a) >= 4 for a in batch.agent)  # agents respawned mid-episode
    assert batch.terminateds.any() and batch.truncateds.any() and len(done) >= 2
    # completeness rule on the log
    frontier = defaultdict(int)
    for env, n, t, _aid in log:
        frontier[(env, n)] = max(frontier[(env, n)], t)
    key_done = {episode_of[k] for k in done}
    assert len(buf) == sum(1 for (env, n, t, aid) in logged if (env, n) in key_done or t + 2 <= frontier[(env, n)])

    out = unique_rows(sample_many(buf, 3 * len(buf)))
    for i in range(out["obs"].shape[0]):
        env, n = episode_of[int(out["episode"][i])]
        t, ego = int(out["env_step"][i]), f"agent{int(out['agent'][i])}"
        rec, nxt = log[(env, n, t, ego)], log[(env, n, t + 1, ego)]
        np.testing.assert_array_equal(out["obs"][i], rec["obs"])
        np.testing.assert_array_equal(out["state"][i], rec["state"])
        np.testing.assert_allclose(out["actions"][i], rec["action"], rtol=0, atol=1e-6)
        assert out["rewards"][i] == np.float32(rec["reward"]) and out["global_rewards"][i] == np.float32(nxt["g"])
        assert out["terminateds"][i] == rec["term"] and out["truncateds"][i] == rec["trunc"]
        np.testing.assert_array_equal(out["new_obs"][i], nxt["obs"])
        np.testing.assert_array_equal(out["new_state"][i], nxt["state"])
        # others at t: the logged states / actions of exactly the other agents that acted at env step t
        others = sorted(acting[(env, n, t)] - {ego})
        want = np.array([log[(env, n, t, o)]["state"] for o in others]).reshape(-1, 10)
        want_act = np.array([log[(env, n, t, o)]["action"] for o in others]).reshape(-1, 2)
        m = out["others_mask"][i]
        got, got_act = out["others_state"][i][m], out["others_actions"][i][m]
        assert got.shape == want.shape
        order_got, order_want = np.lexsort(got.T[::-1]), np.lexsort(want.T[::-1])  # order-free compare
        np.testing.assert_array_equal(got[order_got], want[order_want])
        np.testing.assert_allclose(got_act[order_got], want_act[order_want], rtol=0, atol=1e-6)
        # next others: every other agent with an observation at t+1
        others1 = sorted(present[(env, n, t + 1)] - {ego})
        want1 = np.array([log[(env, n, t + 1, o)]["state"] for o in others1]).reshape(-1, 10)
        want1_obs = np.array([log[(env, n, t + 1, o)]["obs"] for o in others1]).reshape(-1, 91)
        m1 = out["next_others_mask"][i]
        got1, got1_obs = out["next_others_state"][i][m1], out["next_others_obs"][i][m1]
        assert got1.shape == want1.shape
        o_got, o_want = np.lexsort(got1.T[::-1]), np.lexsort(want1.T[::-1])
        np.testing.assert_array_equal(got1[o_got], want1[o_want])
        np.testing.assert_array_equal(got1_obs[o_got], want1_obs[o_want])
