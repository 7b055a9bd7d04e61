"""The TD3 family's centralized-critic connector (``td3/connector.py``) against the replay's gather it replaced.

The independent expectation is the joint-step replay's own gather as it was before the connector
existed (``old_gather`` below, verbatim from commit 58649bf's ``JointStepReplayBuffer._gather``): the
same stored stream and the same drawn rows must give the same train batch, column by column and bit
for bit, whether the connector reads the replay's records in place (a learner in the algorithm's
process) or a copy kept current by the replay's deltas (a remote learner), through rings that grow,
wrap and evict.
"""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from ray.rllib.core.learner.training_data import TrainingData
from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch
from test_cig_td3_replay import ACT_DIM, CALLS, MAX_OTHERS, OBS_DIM, STATE_DIM, make_stream, run_fake_runner

from coin_app.algorithms.td3 import buffer as buffer_module
from coin_app.algorithms.td3 import columns as col
from coin_app.algorithms.td3.buffer import JointStepReplayBuffer
from coin_app.algorithms.td3.connector import JointRecordsCopy, JointState, inject_global_state
from coin_app.algorithms.td3.transitions import episodes_to_transitions


def old_gather(self: JointStepReplayBuffer, slots: np.ndarray) -> dict[str, np.ndarray]:
    """The replay's gather before the connector (commit 58649bf), verbatim: every column of the transitions in ``slots``."""
    C, P, K, N, M = self.capacity, self.obs_capacity, self.step_capacity, self.max_others, self.max_others + 1
    tw = self._tr_written - 1 - (self._tr_written - 1 - slots) % C  # write index held by each slot
    if not self._valid(tw).all():  # cheap guard against internal inconsistencies
        raise RuntimeError("internal error: a sampled transition references evicted data")
    r0 = self._tr_obs[slots] % P
    r1 = self._tr_next[slots] % P
    e0 = self._tr_entry_t[slots]
    e1 = self._tr_entry_t1[slots]
    shift = np.arange(N)[None, :]
    out: dict[str, np.ndarray] = {
        col.OBS: self._pool_obs[r0],
        col.STATE: self._pool_state[r0],
        col.ACTIONS: self._tr_action[slots],
        col.REWARDS: self._tr_reward[slots],
        col.GLOBAL_REWARDS: self._tr_greward[slots],
        col.TERMINATEDS: self._tr_term[slots],
        col.TRUNCATEDS: self._tr_trunc[slots],
        col.NEXT_OBS: self._pool_obs[r1],
        col.NEXT_STATE: self._pool_state[r1],
    }
    # others acting at t: rows of entry (episode, t) without the ego's column
    cols0 = shift + (shift >= (self._pool_owner[r0] % M)[:, None])
    rows0 = np.take_along_axis(self._step_rows[e0 % K], cols0, axis=1)
    ok0 = np.take(self._pool_owner, rows0, mode="clip") == e0[:, None] * M + cols0
    tr0 = np.take(self._pool_tr_obs, rows0, mode="clip")
    ok0 &= tr0 >= self._tr_wm
    ok0 &= tr0 >= 0
    out[col.OTHERS_STATE] = np.take(self._pool_state, np.where(ok0, rows0, P), axis=0, mode="clip")
    out[col.OTHERS_ACTIONS] = np.take(self._tr_action, np.where(ok0, tr0 % C, C), axis=0, mode="clip")
    out[col.OTHERS_MASK] = ok0
    out[col.OTHERS_REWARDS] = np.where(ok0, np.take(self._tr_reward, tr0 % C, mode="clip"), np.float32(0.0))
    # every other agent with an observation at t+1
    cols1 = shift + (shift >= (self._pool_owner[r1] % M)[:, None])
    rows1 = np.take_along_axis(self._step_rows[e1 % K], cols1, axis=1)
    ok1 = np.take(self._pool_owner, rows1, mode="clip") == e1[:, None] * M + cols1
    rows1 = np.where(ok1, rows1, P)
    out[col.NEXT_OTHERS_STATE] = np.take(self._pool_state, rows1, axis=0, mode="clip")
    out[col.NEXT_OTHERS_OBS] = np.take(self._pool_obs, rows1, axis=0, mode="clip")
    out[col.NEXT_OTHERS_MASK] = ok1
    out[col.ENV_STEP] = self._tr_step[slots].copy()
    out[col.EPISODE] = self._tr_episode[slots].copy()
    out[col.AGENT] = self._tr_agent[slots].copy()
    return out


def old_sample(buf: JointStepReplayBuffer, n: int) -> dict[str, np.ndarray]:
    """What the replay's ``sample(n)`` returned before the connector, drawn with the buffer's RNG left as it was."""
    rng_state = buf._rng.bit_generator.state
    out = old_gather(buf, buf._draw(n))
    buf._rng.bit_generator.state = rng_state
    return out


def assert_bitwise(got: dict[str, np.ndarray], want: dict[str, np.ndarray]) -> None:
    """Same columns, each with the same dtype, shape and bytes."""
    assert sorted(got) == sorted(want)
    for k in want:
        g, w = np.asarray(got[k]), np.asarray(want[k])
        assert (g.dtype, g.shape) == (w.dtype, w.shape), k
        assert g.tobytes() == w.tobytes(), k


def stream():
    """The scripted stream of ``test_cig_td3_replay`` (respawns, terminal observations and chunk cuts on every boundary)."""
    truth, envs = make_stream()
    return [episodes_to_transitions(chunks) for chunks in run_fake_runner(envs, CALLS, truth)]


CAPACITIES = [(10_000, None, None), (60, 55, 500), (100, 1000, 20), (45, 60, 22)]  # roomy; wrapping and evicting rings


@pytest.mark.parametrize("capacity,obs_capacity,step_capacity", CAPACITIES)
def test_connector_gives_the_old_gather_bit_for_bit_in_place_and_from_a_copy(monkeypatch, capacity, obs_capacity, step_capacity):
    monkeypatch.setattr(buffer_module, "INITIAL_ROWS", 8)  # the rings grow (and the copy with them) while they fill
    buf = JointStepReplayBuffer(
        capacity, OBS_DIM, STATE_DIM, ACT_DIM, MAX_OTHERS, 5, obs_capacity=obs_capacity, step_capacity=step_capacity
    )
    copy, written, checked = JointRecordsCopy(), None, 0
    for i, batch in enumerate(stream()):
        buf.add(batch)
        if len(buf) < 8 or i % 3 == 1:  # some adds reach the copy only with a later delta
            continue
        delta = pickle.loads(pickle.dumps(buf.joint_delta(written)))  # as it travels to a remote learner
        copy.apply(delta)
        written = delta["written"]
        want = old_sample(buf, 8)
        lookups = buf.sample(8)
        assert set(lookups) == set(col.SAMPLED)
        assert_bitwise(inject_global_state(buf.joint_columns(), dict(lookups)), want)
        assert_bitwise(inject_global_state(copy.joint_columns(), dict(lookups)), want)
        checked += 1
    assert checked >= 10


def test_a_copy_restarted_from_a_full_delta_after_a_restore_reads_the_same():
    x = JointStepReplayBuffer(60, OBS_DIM, STATE_DIM, ACT_DIM, MAX_OTHERS, 1, obs_capacity=55, step_capacity=500)
    batches = stream()
    copy = JointRecordsCopy()
    for batch in batches[:12]:
        x.add(batch)
    copy.apply(x.joint_delta())
    for batch in batches[12:20]:  # the copy falls behind by more than a ring
        x.add(batch)
    y = JointStepReplayBuffer(60, OBS_DIM, STATE_DIM, ACT_DIM, MAX_OTHERS, 9, obs_capacity=55, step_capacity=500)
    y.set_state(pickle.loads(pickle.dumps(x.get_state())))
    copy.apply(y.joint_delta(None))  # what the algorithm sends after restoring its replay: every stored row
    for batch in batches[20:]:
        y.add(batch)
        copy.apply(y.joint_delta(copy.written))
        want = old_sample(y, 16)
        assert_bitwise(inject_global_state(copy.joint_columns(), y.sample(16)), want)


def test_piece_injects_lookups_passes_full_batches_and_refuses_lookups_without_records():
    buf = JointStepReplayBuffer(10_000, OBS_DIM, STATE_DIM, ACT_DIM, MAX_OTHERS, 0)
    for batch in stream()[:10]:
        buf.add(batch)
    want = old_sample(buf, 32)
    piece = JointState(records=buf)
    out = piece(rl_module=None, batch={"shared": buf.sample(32)}, episodes=[])
    assert_bitwise(out["shared"], want)
    full = {k: v.copy() for k, v in want.items()}
    assert_bitwise(piece(rl_module=None, batch={"shared": full}, episodes=[])["shared"], want)  # already global: unchanged
    with pytest.raises(RuntimeError, match="no joint records"):
        JointState()(rl_module=None, batch={"shared": buf.sample(4)}, episodes=[])


@pytest.mark.parametrize("algo", ["cig_td3", "traco", "itd3"])
def test_learner_train_batch_equals_the_old_replay_batch(algo):
    from coin_app.adapters.rllib_env import CoinMultiAgentEnv
    from coin_app.training import build_config

    cfg = build_config(algo, "bottleneck", {"num_agents": 3, "hidden": 16, "train_batch_size_per_learner": 16}, 0)
    learner = cfg.build_learner(env=CoinMultiAgentEnv(cfg.env_config))
    assert [type(p) for p in learner._learner_connector.connectors] == [JointState]  # the family's pipeline: the connector alone
    buf = JointStepReplayBuffer(10_000, OBS_DIM, STATE_DIM, ACT_DIM, MAX_OTHERS, 2)
    for batch in stream()[:14]:
        buf.add(batch)
    learner.joint_state.records = buf  # what the algorithm does with a learner in its process
    for _ in range(3):
        want = old_sample(buf, 16)
        got = learner._make_batch_if_necessary(TrainingData(batch=MultiAgentBatch({"shared": SampleBatch(buf.sample(16))}, 16)))
        old = learner._make_batch_if_necessary(TrainingData(batch=MultiAgentBatch({"shared": SampleBatch(want)}, 16)))
        g, w = got.policy_batches["shared"], old.policy_batches["shared"]
        assert sorted(g.keys()) == sorted(w.keys()) == sorted(col.EGO + col.OTHERS + col.ORIGIN)
        for k in w.keys():
            assert g[k].dtype == w[k].dtype and g[k].shape == w[k].shape and bool((g[k] == w[k]).all()), k
            np.testing.assert_array_equal(g[k].cpu().numpy(), want[k])
