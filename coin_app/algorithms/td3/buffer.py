"""Joint-step replay buffer of the TD3 family: storage by env step and sampling; the learner connector gathers the global state.

A sample row is one per-agent transition (``transitions.py``) plus its lookups: the rows of the
buffer's joint records (``joint_columns``) that hold the states and actions of the other agents that
acted at its env step t, the states and observations of every other agent with an observation at
t+1, and its global reward (COIN §4.2, Eqs. 9-11; the columns are named in ``columns.py``). The
centralized-critic connector, ``connector.JointState`` in the learner's connector pipeline, turns
the lookups into those columns; a remote learner reads a copy of the joint records kept current by
``joint_delta`` (``docs/decisions.md`` §6.4).

Why a custom buffer (``docs/decisions.md`` §6.2 and §6.4)
---------------------------------------------------------
* RLlib's ``MultiAgentEpisodeReplayBuffer`` crashes when an agent spawns on the last step of a
  chunk (§6.2 item 1), is unseeded (item 7), is not checkpointed on the new stack (item 8), and
  its ``env_t_to_agent_t`` is wrong for respawned agents (item 11). In independent mode it returns
  one-transition ``SingleAgentEpisode``\\ s, so cross-agent data must be looked up per item in
  Python (option (b) of §6.4): slow and tied to the buffer's internals.
* Env-side augmentation (option (a) of §6.4) stores ``N_max`` other-agent rows inside *every*
  agent's observation (``N_max x d`` floats per agent step, x2 for the next step), cannot show the
  others' actions at t in o_t, and misses agents that spawn at t+1.
* Here every observation (episode, agent, env step) is stored **once** in an observation pool;
  a step index per (episode, env step) lists the pool rows present at that step, and each pool
  row knows the transition that acts from it. Sampling gathers the others through padded index
  tables with a handful of vectorized numpy ``take``\\ s. Alignment is by the env's own
  ``infos[schema.ENV_STEP]`` stamp, so it is exact across respawns, terminations and chunk
  boundaries. Sampling uses the buffer's own seeded ``np.random.Generator``; ``get_state`` /
  ``set_state`` include that generator's state.

Storage (three FIFO rings, each with a watermark: write indices below it are evicted)
----------------------------------------------------------------------------------------
* observation pool, ``obs_capacity`` rows (default ``capacity + capacity // 4 + 64``): obs and
  state, the step entry and column the row sits in, the transition acting from it (o_t) and the
  one arriving in it (o_{t+1}). A transition adds ~1 row (o_{t+1} of step k is o_t of step k+1;
  a life adds one extra terminal row), so the pool does not bind before the transition ring
  unless lives are shorter than ~4 steps.
* transitions, ``capacity`` slots: pool write indices of o_t and o_{t+1}, step-entry write
  indices of t and t+1, action, rewards, flags, (episode, agent, env step).
* step entries, ``step_capacity`` (default ``capacity // 2 + 64``, enough for >= 2 agents per
  step): ``max_others + 1`` pool rows (int32) per (episode, env step). Pass
  ``step_capacity=capacity`` for scenarios with a single agent per step.

Memory (float32 obs/state, ``O`` = obs_dim, ``S`` = state_dim, ``A`` = act_dim, ``M`` = max_others + 1):
a pool row takes ``4 (O + S) + 24`` bytes, a transition ``4 A + 67``, a step entry ``4 M + 20``. Full
rings with the default sizes hold 1.25 pool rows and 0.5 entries per transition: with O=91, S=10,
A=2, M=48, 535 + 75 + 106 = ~716 bytes per transition, 6.7 GiB at the official code's capacity of
10,000,000 transitions (``docs/decisions.md`` §2.1; :attr:`JointStepReplayBuffer.capacity_nbytes`).
In use with 30 agents per step a transition needs ~510 bytes (one pool row, one transition, 1/29 of
an entry).
Env-side augmentation would need ``2 x N x (O + S + A)`` floats, ~40 KB per agent step at N=47.

The rings are allocated on demand, so a small run does not pay for the capacity: each ring starts
with :data:`INITIAL_ROWS` rows (at most its capacity) and, before an add writes past its allocated
rows, doubles (capped at its capacity) until every physical index the add writes fits. Ring
semantics do not change (physical index = write index % capacity; a ring that has wrapped has its
full capacity). Unwritten rows hold the fill values (0; -1 for the pool's owner and transition
links; ``P`` for empty entry columns). The padding rows (pool id ``P`` = ``obs_capacity``, action id
``C`` = ``capacity``) are kept as the last row of the allocated arrays and are read with
``np.take(..., mode="clip")``, which maps a padding id past the allocated rows onto them.
:attr:`JointStepReplayBuffer.nbytes` (what is allocated) thus stays within about twice what the
stored rows need, plus the initial rows: measured with the stream of ``benchmarks/replay_sampling.py``
(30 agents per step) at capacity 10M, 8.7 MiB holding 10k transitions and 516 MiB (541 bytes per
transition) holding 1M, against 6.7 GiB allocated up front before. Growing copies a ring's arrays,
one at a time, into new ones (amortized O(1) per row); while one is copied, its old and new copies
coexist (at capacity 10M the pool observations' last doubling, 8.4M -> 12.5M rows, briefly takes
2.8 GiB extra).
Checkpoints (:meth:`JointStepReplayBuffer.get_state`, version 2) hold only the rows written so far
(a ring's capacity once it has wrapped), so a small run's checkpoint is small; version-1 states
(every array at full size) are still read.

Adding a batch: plan, evict, write
----------------------------------
``add`` first *plans* where everything goes without touching the buffer (layout order, which
observations are already stored, new pool rows, step entries and their columns, write indices,
the watermarks after the add); every input error is raised there, so a refused batch stores
nothing. It then *evicts* (advances the watermarks, making transitions that reference
overwritten data unsampleable) and finally *writes* the entries, rows and transitions.

Completeness rule (why fresh transitions are not sampleable at once)
---------------------------------------------------------------------
The others at t+1 include agents that spawn at t+1. When a chunk is cut at env step t+1, a
spawned agent's first observation only arrives with the *next* chunk (RLlib puts a
``SingleAgentEpisode`` with one observation and no action in the first chunk, which carries
no transition). So a transition acting at env step t becomes sampleable only once data of
env step t+2 of its episode has been added (the chunk covering t+1 -> t+2 is in) or the
episode has ended (``MultiAgentEpisode.is_done``; the env adapter drops spawns in the last
step). ``len(buffer)`` counts only sampleable transitions. ``add`` expects whole chunks, as
``MultiAgentEnvRunner.sample()`` returns them (all agents of an episode for the same env steps
in one call), in env-step order per episode.

Eviction: a transition whose o_t / o_{t+1} pool row or whose step entry (t or t+1) was
overwritten is never sampled again; another agent whose row (or acting transition) was
evicted is masked out of ``others_*`` / ``next_others_*``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from coin_app.algorithms.td3 import columns as col
from coin_app.algorithms.td3.transitions import TransitionBatch
from coin_app.sim import schema

STATE_VERSION = 2  # 2: arrays hold the rows written so far; 1: every array at full capacity (still read)
INITIAL_ROWS = 4096  # rows each ring allocates first (capped at its capacity); it doubles from there on demand

# the joint records the sample's lookups index (name -> storage array), see joint_columns
JOINT_RECORDS = {
    "pool_obs": "_pool_obs",
    "pool_state": "_pool_state",
    "actions": "_tr_action",
    "rewards": "_tr_reward",
    "global_rewards": "_tr_greward",
}

# ring -> (attribute holding its capacity, attribute counting its writes)
_RINGS: dict[str, tuple[str, str]] = {
    "pool": ("obs_capacity", "_pool_written"),
    "transitions": ("capacity", "_tr_written"),
    "steps": ("step_capacity", "_step_written"),
}


class _ArraySpec(NamedTuple):
    """One storage array: its ring, the shape of a row, dtype, the value of unwritten rows, and whether a padding row ends it."""

    ring: str
    row_shape: tuple[int, ...]
    dtype: type
    fill: int
    padded: bool


@dataclass
class _Layout:
    """A batch's transitions in buffer layout order (episodes by first appearance, then agent, then env step)."""

    order: np.ndarray  # (n,) batch row of each transition
    ep_rank: np.ndarray  # (n,) rank of its episode (order of first appearance in the batch)
    rank_key: np.ndarray  # (E,) episode key of each rank
    ep: np.ndarray  # (n,) int64 episode key
    ag: np.ndarray  # (n,) int64 agent key
    t: np.ndarray  # (n,) int64 env step of o_t
    term: np.ndarray  # (n,) bool
    trunc: np.ndarray  # (n,) bool
    same: np.ndarray  # (n,) bool: same (episode, agent) as the previous transition
    chain_prev: np.ndarray  # (n,) bool: o_t is the previous transition's o_{t+1} (same agent, consecutive steps)
    chain_next: np.ndarray  # (n,) bool: o_{t+1} is the next transition's o_t

    @property
    def done(self) -> np.ndarray:
        """Terminated or truncated, (n,) bool."""
        return self.term | self.trunc


class _Allocation(NamedTuple):
    """The new pool rows and step entries of an add, and the watermarks they push the pool and entry rings to."""

    reuse_w: np.ndarray  # (n,) pool write index of every o_t that is already stored (-1: it gets a new row)
    new_t_idx: np.ndarray  # transitions (layout positions) whose o_t gets a new pool row
    new_n_idx: np.ndarray  # transitions whose o_{t+1} gets a new pool row
    pairs: np.ndarray  # (U, 2) (episode key, env step) of the entries the new rows go into, sorted
    inv: np.ndarray  # (R,) entry (index into pairs) of every new row: o_t rows first, then o_{t+1} rows
    existing: np.ndarray  # (U,) write index of each stored entry, -1 if none
    is_new: np.ndarray  # (U,) bool: the entry is allocated by this add
    pool_wm: int  # pool watermark after the add
    step_wm: int  # step-entry watermark after the add


@dataclass
class _AddPlan:
    """Where one add's transitions, observation rows and step entries go (computed before anything is mutated)."""

    lay: _Layout
    new_t_idx: np.ndarray  # transitions whose o_t gets a new pool row
    new_n_idx: np.ndarray  # transitions whose o_{t+1} gets a new pool row
    row_w: np.ndarray  # (R,) pool write index of every new row (o_t rows first, then o_{t+1} rows)
    row_entry: np.ndarray  # (R,) step-entry write index the row sits in
    row_col: np.ndarray  # (R,) its column in that entry
    pairs: np.ndarray  # (U, 2) (episode key, env step) of every entry that gets rows
    entry_w: np.ndarray  # (U,) its write index
    is_new: np.ndarray  # (U,) bool: allocated by this add
    entry_count: np.ndarray  # (U,) rows in the entry after the add
    tr_w: np.ndarray  # (n,) write index of every transition
    obs_w: np.ndarray  # (n,) pool write index of its o_t
    next_w: np.ndarray  # (n,) pool write index of its o_{t+1}
    pool_wm: int  # watermarks after the add (write indices below them are evicted)
    step_wm: int
    tr_wm: int


class JointStepReplayBuffer:
    """FIFO replay of per-agent transitions whose samples carry the other agents at t and t+1 (see module doc).

    ``capacity`` counts transitions; ``max_others`` (N) is the most other agents with an
    observation at one env step (a step with more raises ``ValueError`` in :meth:`add`).
    ``obs_capacity`` (pool rows) and ``step_capacity`` (step entries) default to sizes that
    let the transition ring bind first (module doc). Sampling is uniform with replacement over
    the sampleable transitions, driven by ``np.random.default_rng(seed)``.
    """

    _COUNTERS = ("_pool_written", "_pool_wm", "_tr_written", "_tr_wm", "_step_written", "_step_wm", "_num_ok")

    def __init__(
        self,
        capacity: int,
        obs_dim: int,
        state_dim: int = schema.STATE_DIM,
        act_dim: int = schema.ACT_DIM,
        max_others: int = 47,
        seed: int | None = 0,
        *,
        obs_capacity: int | None = None,
        step_capacity: int | None = None,
    ):
        for name, v in (
            ("capacity", capacity),
            ("obs_dim", obs_dim),
            ("state_dim", state_dim),
            ("act_dim", act_dim),
            ("max_others", max_others),
        ):
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < (0 if name == "max_others" else 1):
                raise ValueError(f"{name} must be an integer >= {0 if name == 'max_others' else 1}, got {v!r}")
        self.capacity = C = int(capacity)
        self.obs_capacity = P = int(obs_capacity) if obs_capacity is not None else C + C // 4 + 64
        self.step_capacity = K = int(step_capacity) if step_capacity is not None else C // 2 + 64
        if P < 2 or K < 2:
            raise ValueError(f"obs_capacity and step_capacity must be >= 2, got {P} and {K}")
        self.obs_dim, self.state_dim, self.act_dim = int(obs_dim), int(state_dim), int(act_dim)
        self.max_others = int(max_others)
        self.seed = seed
        self._rng = np.random.default_rng(seed)
        # storage: one array per column of the three rings (see _array_specs), allocated on demand
        self._spec = self._array_specs()
        self._rows = {ring: self._ring_rows(ring, 0) for ring in _RINGS}  # real rows allocated per ring
        for name, spec in self._spec.items():
            setattr(self, name, _new_array(spec, self._rows[spec.ring]))
        # write counters and eviction watermarks (write indices < watermark are evicted)
        self._pool_written = self._pool_wm = 0
        self._tr_written = self._tr_wm = 0
        self._step_written = self._step_wm = 0
        self._num_ok = 0
        self._pending = np.zeros(0, np.int64)  # valid transitions waiting for their step t+1 to be complete
        self._entry_of: dict[tuple[int, int], int] = {}  # (episode, env step) -> step-entry write index
        self._last_obs: dict[tuple[int, int], tuple[int, int]] = {}  # (episode, agent) -> (env step, pool write index)
        self._episodes: dict[int, list[int]] = {}  # episode -> [frontier env step, ended]
        self._last_obs_prune_at = 1024

    # ------------------------------------------------------------------ public API
    def __len__(self) -> int:
        """Number of sampleable transitions (stored, complete, not invalidated by eviction)."""
        return int(self._num_ok)

    @property
    def num_added(self) -> int:
        """Transitions added over the buffer's lifetime."""
        return int(self._tr_written)

    @property
    def num_obs_added(self) -> int:
        """Observation-pool rows written over the buffer's lifetime (one per distinct (episode, agent, env step))."""
        return int(self._pool_written)

    @property
    def num_pending(self) -> int:
        """Stored transitions waiting for their env step t+1 to be complete."""
        return int(self._pending.shape[0])

    @property
    def nbytes(self) -> int:
        """Bytes allocated by the buffer's arrays now (they grow with what is stored, see the module doc)."""
        return int(sum(getattr(self, name).nbytes for name in self._spec))

    @property
    def capacity_nbytes(self) -> int:
        """Bytes the buffer's arrays take once every ring is full (what :attr:`nbytes` grows to)."""
        return int(
            sum(
                (self._ring_capacity(spec.ring) + spec.padded) * int(np.prod(spec.row_shape)) * np.dtype(spec.dtype).itemsize
                for spec in self._spec.values()
            )
        )

    def add(self, batch: TransitionBatch) -> None:
        """Store a batch of whole chunks (see module doc); raises ``ValueError`` on inconsistent input, storing nothing."""
        n = len(batch)
        self._check_batch(batch)
        if n > self.capacity:
            raise ValueError(f"batch of {n} transitions exceeds the buffer capacity {self.capacity}; add it in parts of whole chunks")
        if n:
            plan = self._plan(batch)
            self._reserve(
                {
                    "pool": self._pool_written + plan.row_w.shape[0],
                    "transitions": self._tr_written + n,
                    "steps": self._step_written + int(plan.is_new.sum()),
                }
            )
            self._evict(plan)
            self._write(batch, plan)
        for key in np.asarray(batch.ended_episodes, dtype=np.int64).tolist():
            self._episodes.setdefault(key, [-1, 0])[1] = 1
        self._update_pending(np.arange(self._tr_written - n, self._tr_written, dtype=np.int64))

    def sample(self, batch_size: int) -> dict[str, np.ndarray]:
        """Uniformly sample ``batch_size`` transitions (with replacement): their own columns and their lookups (``columns.SAMPLED``).

        The lookups name the rows of :meth:`joint_columns` that hold the other agents at t and t+1
        and the global reward; the learner connector (``connector.py``) gathers them into the
        global columns (``columns.GLOBAL``).
        """
        if not isinstance(batch_size, (int, np.integer)) or isinstance(batch_size, bool) or batch_size < 1:
            raise ValueError(f"batch_size must be an integer >= 1, got {batch_size!r}")
        if batch_size > self._num_ok:
            raise ValueError(
                f"cannot sample {batch_size} transitions: only {self._num_ok} are sampleable "
                f"({self._tr_written - self._tr_wm} stored, {self.num_pending} waiting for env step t+2)"
            )
        slots = self._draw(int(batch_size))
        return self._gather(slots)

    def joint_columns(self) -> dict[str, np.ndarray]:
        """The joint records the lookups of :meth:`sample` index, by name (``JOINT_RECORDS``): the live arrays, not copies.

        A masked lookup (-1) reads the last row with ``np.take(..., mode="wrap")``: the padding row
        (zero) of the pool and of the actions; the rewards' is masked by the reader.
        """
        return {name: getattr(self, attr) for name, attr in JOINT_RECORDS.items()}

    def joint_delta(self, since: tuple[int, int] | None = None) -> dict[str, Any]:
        """The joint records written after ``since`` (an earlier delta's ``"written"``; None: every stored row), to copy elsewhere.

        Applied in order to a copy (``connector.JointRecordsCopy``) that started empty, the deltas make
        that copy's rows equal to :meth:`joint_columns` at every row a later :meth:`sample` can look up.
        Returns ``{"written": (pool rows, transitions) written so far, "rows": {record: rows
        allocated}, "index": {record: physical rows}, "values": {record: their values}}``.
        """
        written = (self._pool_written, self._tr_written)
        rings = {"pool": (self._pool_written, self.obs_capacity, None if since is None else since[0])}
        rings["transitions"] = (self._tr_written, self.capacity, None if since is None else since[1])
        index = {}
        for ring, (n, cap, start) in rings.items():
            lo = max(0, n - cap) if start is None else max(int(start), n - cap)
            index[ring] = np.arange(lo, n, dtype=np.int64) % cap
        delta: dict[str, Any] = {"written": written, "rows": {}, "index": {}, "values": {}}
        for name, attr in JOINT_RECORDS.items():
            arr, ring = getattr(self, attr), self._spec[attr].ring
            delta["rows"][name] = arr.shape[0]
            delta["index"][name] = index[ring]
            delta["values"][name] = arr[index[ring]]
        return delta

    def get_state(self) -> dict[str, Any]:
        """State for checkpointing: copies of the rows written so far (not the capacity), index maps, counters, RNG state."""
        state: dict[str, Any] = {"version": STATE_VERSION, "config": self._config()}
        for name, spec in self._spec.items():
            state[name] = getattr(self, name)[: self._ring_held(spec.ring)].copy()
        for name in self._COUNTERS:
            state[name] = int(getattr(self, name))
        state["_pending"] = self._pending.copy()
        state["_entry_of"] = np.array([[e, t, w] for (e, t), w in self._entry_of.items()], np.int64).reshape(-1, 3)
        state["_last_obs"] = np.array([[e, a, t, w] for (e, a), (t, w) in self._last_obs.items()], np.int64).reshape(-1, 4)
        state["_episodes"] = np.array([[e, f, d] for e, (f, d) in self._episodes.items()], np.int64).reshape(-1, 3)
        state["_last_obs_prune_at"] = int(self._last_obs_prune_at)
        state["rng"] = self._rng.bit_generator.state
        return state

    def set_state(self, state: Mapping[str, Any]) -> None:
        """Restore a state from :meth:`get_state` (the buffer's configuration must match); also reads version-1 states.

        Version 1 saved every array at full capacity (the padding rows included); version 2 saves the
        rows written so far. Either way each ring is allocated at the size the doubling rule gives for
        the rows it holds (module doc). Every check runs before anything is replaced, so a refused
        state leaves the buffer as it was.
        """
        version = state.get("version")
        if version not in (1, STATE_VERSION):
            raise ValueError(f"replay state version {version!r} is not 1 or {STATE_VERSION}")
        if dict(state["config"]) != self._config():
            raise ValueError(f"replay state was saved with config {dict(state['config'])}, this buffer has {self._config()}")
        counters = {name: int(state[name]) for name in self._COUNTERS}
        held = {ring: min(counters[_RINGS[ring][1]], self._ring_capacity(ring)) for ring in _RINGS}
        rows = {ring: self._ring_rows(ring, held[ring]) for ring in _RINGS}
        arrays = {}
        for name, spec in self._spec.items():
            arr = np.asarray(state[name])
            n = self._ring_capacity(spec.ring) + spec.padded if version == 1 else held[spec.ring]
            if arr.shape != (n, *spec.row_shape):
                raise ValueError(f"replay state array {name} has shape {arr.shape}, expected {(n, *spec.row_shape)}")
            # rows past those written hold the fill values in both versions (writes go to physical rows < held)
            arrays[name] = _new_array(spec, rows[spec.ring], arr[: held[spec.ring]])
        for name, arr in arrays.items():
            setattr(self, name, arr)
        self._rows = rows
        for name, v in counters.items():
            setattr(self, name, v)
        self._pending = np.asarray(state["_pending"], np.int64).copy()
        self._entry_of = {(int(e), int(t)): int(w) for e, t, w in np.asarray(state["_entry_of"]).reshape(-1, 3)}
        self._last_obs = {(int(e), int(a)): (int(t), int(w)) for e, a, t, w in np.asarray(state["_last_obs"]).reshape(-1, 4)}
        self._episodes = {int(e): [int(f), int(d)] for e, f, d in np.asarray(state["_episodes"]).reshape(-1, 3)}
        self._last_obs_prune_at = int(state["_last_obs_prune_at"])
        self._rng = np.random.default_rng()
        self._rng.bit_generator.state = state["rng"]

    # ------------------------------------------------------------------ storage: arrays that grow on demand
    def _array_specs(self) -> dict[str, _ArraySpec]:
        """Every storage array: its ring, the shape of a row, dtype, the value of unwritten rows, and whether it has a padding row."""
        O, S, A, M, P = self.obs_dim, self.state_dim, self.act_dim, self.max_others + 1, self.obs_capacity
        f32, i32, i64 = np.float32, np.int32, np.int64
        return {
            # observation pool; its padding row (id P, kept as the last row) is all zero / -1 and is read by masked gathers
            "_pool_obs": _ArraySpec("pool", (O,), f32, 0, True),
            "_pool_state": _ArraySpec("pool", (S,), f32, 0, True),
            "_pool_owner": _ArraySpec("pool", (), i64, -1, True),  # entry write index * (max_others + 1) + column of the row
            "_pool_tr_obs": _ArraySpec("pool", (), i64, -1, True),  # transition acting from this row (its o_t)
            "_pool_tr_next": _ArraySpec("pool", (), i64, -1, True),  # transition whose o_{t+1} is this row
            # transitions; the action padding row (id C, kept as the last row) is all zero
            "_tr_obs": _ArraySpec("transitions", (), i64, 0, False),  # pool write index of o_t
            "_tr_next": _ArraySpec("transitions", (), i64, 0, False),  # pool write index of o_{t+1}
            "_tr_entry_t": _ArraySpec("transitions", (), i64, 0, False),  # step-entry write index of (episode, t)
            "_tr_entry_t1": _ArraySpec("transitions", (), i64, 0, False),  # step-entry write index of (episode, t+1)
            "_tr_action": _ArraySpec("transitions", (A,), f32, 0, True),
            "_tr_reward": _ArraySpec("transitions", (), f32, 0, False),
            "_tr_greward": _ArraySpec("transitions", (), f32, 0, False),
            "_tr_term": _ArraySpec("transitions", (), bool, 0, False),
            "_tr_trunc": _ArraySpec("transitions", (), bool, 0, False),
            "_tr_step": _ArraySpec("transitions", (), i64, 0, False),
            "_tr_episode": _ArraySpec("transitions", (), i64, 0, False),
            "_tr_agent": _ArraySpec("transitions", (), i64, 0, False),
            "_ok": _ArraySpec("transitions", (), bool, 0, False),  # slot holds a valid, complete (sampleable) transition
            # step entries: pool rows (physical) present at (episode, env step); P = empty column
            "_step_rows": _ArraySpec("steps", (M,), i32, P, False),
            "_step_count": _ArraySpec("steps", (), i32, 0, False),
            "_step_episode": _ArraySpec("steps", (), i64, 0, False),
            "_step_t": _ArraySpec("steps", (), i64, 0, False),
        }

    def _ring_capacity(self, ring: str) -> int:
        """Slots of a ring ("pool", "transitions" or "steps")."""
        return int(getattr(self, _RINGS[ring][0]))

    def _ring_held(self, ring: str) -> int:
        """Physical rows of a ring written so far (all of them once it has wrapped)."""
        return min(int(getattr(self, _RINGS[ring][1])), self._ring_capacity(ring))

    def _ring_rows(self, ring: str, need: int) -> int:
        """Rows to allocate for ``need`` physical rows: ``INITIAL_ROWS`` doubled until they fit, capped at the ring's capacity."""
        cap = self._ring_capacity(ring)
        rows = min(cap, max(1, INITIAL_ROWS))
        while rows < min(need, cap):
            rows = min(cap, 2 * rows)
        return rows

    def _reserve(self, written: Mapping[str, int]) -> None:
        """Grow every ring (by doubling) so that its write count after an add, ``written[ring]``, fits its physical rows."""
        for ring, w in written.items():
            old, rows = self._rows[ring], self._ring_rows(ring, w)
            if rows <= old:
                continue
            for name, spec in self._spec.items():
                if spec.ring == ring:
                    setattr(self, name, _new_array(spec, rows, getattr(self, name)[:old]))
            self._rows[ring] = rows

    # ------------------------------------------------------------------ adding: checks
    def _config(self) -> dict[str, int]:
        """The sizes a saved state must match."""
        return {
            "capacity": self.capacity,
            "obs_capacity": self.obs_capacity,
            "step_capacity": self.step_capacity,
            "obs_dim": self.obs_dim,
            "state_dim": self.state_dim,
            "act_dim": self.act_dim,
            "max_others": self.max_others,
        }

    def _check_batch(self, b: TransitionBatch) -> None:
        """Raise ``ValueError`` when a column of ``b`` has the wrong shape or an env step is negative."""
        n = len(b)
        if n == 0:  # e.g. only episodes that ended without a new transition; column widths are unknown then
            return
        want = {
            col.EPISODE: (n,),
            col.AGENT: (n,),
            col.ENV_STEP: (n,),
            col.OBS: (n, self.obs_dim),
            col.STATE: (n, self.state_dim),
            col.ACTIONS: (n, self.act_dim),
            col.REWARDS: (n,),
            col.GLOBAL_REWARDS: (n,),
            col.TERMINATEDS: (n,),
            col.TRUNCATEDS: (n,),
            col.NEXT_OBS: (n, self.obs_dim),
            col.NEXT_STATE: (n, self.state_dim),
        }
        for name, shape in want.items():
            got = np.shape(getattr(b, name))
            if got != shape:
                raise ValueError(
                    f"TransitionBatch.{name} has shape {got}, expected {shape} "
                    f"(obs_dim={self.obs_dim}, state_dim={self.state_dim}, act_dim={self.act_dim})"
                )
        if n and np.min(b.env_step) < 0:
            raise ValueError(f"env_step must be >= 0, got min {int(np.min(b.env_step))}")

    # ------------------------------------------------------------------ adding: plan (no mutation)
    def _plan(self, b: TransitionBatch) -> _AddPlan:
        """Where the batch's transitions, new observation rows and step entries go; raises before anything is mutated."""
        lay = _layout(b)
        n = lay.ep.shape[0]
        alloc = self._allocate(lay, self._stored_obs_rows(lay))
        entry_w, entry_count, row_entry, row_col, row_order = self._place_rows(alloc)
        R, nt = row_order.shape[0], alloc.new_t_idx.shape[0]
        row_w = np.empty(R, np.int64)  # rows of one step are adjacent in the pool (locality when sampling)
        row_w[row_order] = self._pool_written + np.arange(R, dtype=np.int64)
        # o_t / o_{t+1} row of every transition: a stored row, a new row, or (o_{t+1}) the next transition's o_t
        obs_w = alloc.reuse_w.copy()
        obs_w[alloc.new_t_idx] = row_w[:nt]
        next_w = np.empty(n, np.int64)
        next_w[alloc.new_n_idx] = row_w[nt:]
        cn = np.flatnonzero(lay.chain_next)
        next_w[cn] = obs_w[cn + 1]
        # transitions are laid out step-major (episode, env step, agent) so that the ones acting at one
        # step are adjacent in the ring (sampling gathers them together)
        tr_w = np.empty(n, np.int64)
        tr_w[np.lexsort((lay.ag, lay.t, lay.ep_rank))] = self._tr_written + np.arange(n, dtype=np.int64)
        return _AddPlan(
            lay=lay,
            new_t_idx=alloc.new_t_idx,
            new_n_idx=alloc.new_n_idx,
            row_w=row_w,
            row_entry=row_entry,
            row_col=row_col,
            pairs=alloc.pairs,
            entry_w=entry_w,
            is_new=alloc.is_new,
            entry_count=entry_count,
            tr_w=tr_w,
            obs_w=obs_w,
            next_w=next_w,
            pool_wm=alloc.pool_wm,
            step_wm=alloc.step_wm,
            tr_wm=max(self._tr_wm, self._tr_written + n - self.capacity),
        )

    def _stored_obs_rows(self, lay: _Layout) -> np.ndarray:
        """Pool write index of every transition's o_t that is already stored and still valid, else -1."""
        P, M = self.obs_capacity, self.max_others + 1
        # o_t of a chunk's first transition is normally the o_{t+1} stored with the previous chunk
        reuse_w = np.full(lay.ep.shape[0], -1, np.int64)
        for k in np.flatnonzero(~lay.chain_prev).tolist():
            hit = self._last_obs.get((int(lay.ep[k]), int(lay.ag[k])))
            if hit is not None and hit[0] == lay.t[k] and hit[1] >= self._pool_wm and self._pool_owner[hit[1] % P] // M >= self._step_wm:
                reuse_w[k] = hit[1]
        return reuse_w

    def _allocate(self, lay: _Layout, reuse_w: np.ndarray) -> _Allocation:
        """The new pool rows and step entries and the watermarks after them; raises when the batch cannot fit."""
        P, K, M = self.obs_capacity, self.step_capacity, self.max_others + 1
        reuse_w = reuse_w.copy()
        new_n_idx = np.flatnonzero(~lay.chain_next)
        while True:  # drop reuses of rows / entries that this very add evicts (tiny capacities), then plan again
            new_t_idx = np.flatnonzero(reuse_w < 0)
            R = new_t_idx.shape[0] + new_n_idx.shape[0]
            if R > P:
                raise ValueError(f"batch needs {R} new observation rows > obs_capacity {P}; add it in smaller parts")
            pool_wm = max(self._pool_wm, self._pool_written + R - P)
            row_rank = np.concatenate([lay.ep_rank[new_t_idx], lay.ep_rank[new_n_idx]])
            row_t = np.concatenate([lay.t[new_t_idx], lay.t[new_n_idx] + 1])
            pairs, inv = _unique_pairs(row_rank, row_t)
            pairs[:, 0] = lay.rank_key[pairs[:, 0]]  # (episode key, env step), in layout order
            existing = np.array([self._entry_of.get((int(e), int(s)), -1) for e, s in pairs.tolist()], np.int64).reshape(-1)
            is_new = existing < self._step_wm
            while True:  # entries that this add's allocations would evict count as new as well
                step_wm = max(self._step_wm, self._step_written + int(is_new.sum()) - K)
                more = ~is_new & (existing < step_wm)
                if not more.any():
                    break
                is_new |= more
            if int(is_new.sum()) > K:
                raise ValueError(f"batch needs {int(is_new.sum())} new step entries > step_capacity {K}; add it in smaller parts")
            owner = np.take(self._pool_owner, reuse_w % P, mode="clip")  # -1 % P may lie past the allocated rows
            bad = (reuse_w >= 0) & ((reuse_w < pool_wm) | (owner // M < step_wm))
            if not bad.any():
                return _Allocation(reuse_w, new_t_idx, new_n_idx, pairs, inv, existing, is_new, pool_wm, step_wm)
            reuse_w[bad] = -1

    def _place_rows(self, alloc: _Allocation) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(entry write indices, rows per entry after the add, entry and column of every new row, pool order of the rows).

        Raises ``ValueError`` when an env step would hold more than ``max_others + 1`` rows.
        """
        K, M = self.step_capacity, self.max_others + 1
        pairs, inv, existing, is_new = alloc.pairs, alloc.inv, alloc.existing, alloc.is_new
        entry_w = existing.copy()
        entry_w[is_new] = self._step_written + np.arange(int(is_new.sum()), dtype=np.int64)
        base = np.where(is_new, 0, self._step_count[np.maximum(existing, 0) % K]).astype(np.int64)
        counts = np.bincount(inv, minlength=pairs.shape[0])
        total = base + counts
        if (total > M).any():
            j = int(np.argmax(total))
            raise ValueError(
                f"env step {int(pairs[j, 1])} of episode {int(pairs[j, 0])} has {int(total[j])} agents with an observation "
                f"(ego + {int(total[j]) - 1} others) but max_others={self.max_others}; raise max_others to at least {int(total[j]) - 1}"
            )
        R = inv.shape[0]
        row_order = np.argsort(inv, kind="stable")  # rows grouped by entry
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        rank = np.empty(R, np.int64)
        rank[row_order] = np.arange(R) - np.repeat(starts, counts)
        return entry_w, total, entry_w[inv], base[inv] + rank, row_order

    # ------------------------------------------------------------------ adding: evict
    def _evict(self, plan: _AddPlan) -> None:
        """Advance the three watermarks to the plan's; transitions referencing overwritten rows or entries become unsampleable."""
        P, K, M = self.obs_capacity, self.step_capacity, self.max_others + 1
        if plan.pool_wm > self._pool_wm:
            ev = np.arange(self._pool_wm, plan.pool_wm, dtype=np.int64) % P
            self._invalidate(np.concatenate([self._pool_tr_obs[ev], self._pool_tr_next[ev]]))
            self._pool_wm = plan.pool_wm
        if plan.step_wm > self._step_wm:
            ev_w = np.arange(self._step_wm, plan.step_wm, dtype=np.int64)
            ev_s = ev_w % K
            rows = self._step_rows[ev_s]
            live = np.take(self._pool_owner, rows, mode="clip") == ev_w[:, None] * M + np.arange(M)[None, :]
            rows = rows[live]
            self._invalidate(np.concatenate([self._pool_tr_obs[rows], self._pool_tr_next[rows]]))
            for e, s in zip(self._step_episode[ev_s].tolist(), self._step_t[ev_s].tolist()):  # keep _entry_of to stored entries
                if self._entry_of.get((e, s), -2) < plan.step_wm:
                    self._entry_of.pop((e, s), None)
            self._step_wm = plan.step_wm
        if plan.tr_wm > self._tr_wm:
            self._invalidate(np.arange(self._tr_wm, plan.tr_wm, dtype=np.int64))
            self._tr_wm = plan.tr_wm

    # ------------------------------------------------------------------ adding: write
    def _write(self, b: TransitionBatch, plan: _AddPlan) -> None:
        """Write the plan's step entries and pool rows, then its transitions, then the per-agent and per-episode index."""
        self._write_rows(b, plan)
        self._write_transitions(b, plan)
        self._index_agents(plan)

    def _write_rows(self, b: TransitionBatch, plan: _AddPlan) -> None:
        """Open the new step entries and write the new observation rows into the pool and their entries."""
        P, K, M = self.obs_capacity, self.step_capacity, self.max_others + 1
        order, is_new = plan.lay.order, plan.is_new
        new_slots = plan.entry_w[is_new] % K
        self._step_rows[new_slots] = P
        self._step_count[new_slots] = 0
        self._step_episode[new_slots] = plan.pairs[is_new, 0]
        self._step_t[new_slots] = plan.pairs[is_new, 1]
        for (e, s), w in zip(plan.pairs[is_new].tolist(), plan.entry_w[is_new].tolist()):
            self._entry_of[(e, s)] = w
        self._step_written += int(is_new.sum())
        nt = plan.new_t_idx.shape[0]
        phys = plan.row_w % P
        self._pool_obs[phys[:nt]] = np.asarray(b.obs, np.float32)[order][plan.new_t_idx]
        self._pool_obs[phys[nt:]] = np.asarray(b.new_obs, np.float32)[order][plan.new_n_idx]
        self._pool_state[phys[:nt]] = np.asarray(b.state, np.float32)[order][plan.new_t_idx]
        self._pool_state[phys[nt:]] = np.asarray(b.new_state, np.float32)[order][plan.new_n_idx]
        self._pool_owner[phys] = plan.row_entry * M + plan.row_col
        self._pool_tr_obs[phys] = -1
        self._pool_tr_next[phys] = -1
        self._pool_written += plan.row_w.shape[0]
        self._step_rows[plan.row_entry % K, plan.row_col] = phys
        self._step_count[plan.entry_w % K] = plan.entry_count

    def _write_transitions(self, b: TransitionBatch, plan: _AddPlan) -> None:
        """Write the transitions (pending, not yet sampleable) and link their o_t / o_{t+1} rows back to them."""
        C, P, M = self.capacity, self.obs_capacity, self.max_others + 1
        lay, obs_w, next_w = plan.lay, plan.obs_w, plan.next_w
        slots = plan.tr_w % C
        self._tr_obs[slots] = obs_w
        self._tr_next[slots] = next_w
        self._tr_entry_t[slots] = self._pool_owner[obs_w % P] // M
        self._tr_entry_t1[slots] = self._pool_owner[next_w % P] // M
        self._tr_action[slots] = np.asarray(b.actions, np.float32)[lay.order]
        self._tr_reward[slots] = np.asarray(b.rewards, np.float32)[lay.order]
        self._tr_greward[slots] = np.asarray(b.global_rewards, np.float32)[lay.order]
        self._tr_term[slots] = lay.term
        self._tr_trunc[slots] = lay.trunc
        self._tr_step[slots] = lay.t
        self._tr_episode[slots] = lay.ep
        self._tr_agent[slots] = lay.ag
        self._ok[slots] = False
        self._pool_tr_obs[obs_w % P] = plan.tr_w
        self._pool_tr_next[next_w % P] = plan.tr_w
        self._tr_written += plan.tr_w.shape[0]

    def _index_agents(self, plan: _AddPlan) -> None:
        """Remember every live agent's last observation (the next chunk's first o_t) and every episode's frontier."""
        lay = plan.lay
        last = np.flatnonzero(~np.concatenate([lay.same[1:], [False]]))
        done = lay.done
        for e, a, s, w, d in zip(
            lay.ep[last].tolist(), lay.ag[last].tolist(), lay.t[last].tolist(), plan.next_w[last].tolist(), done[last].tolist()
        ):
            if d:
                self._last_obs.pop((e, a), None)
            else:
                self._last_obs[(e, a)] = (s + 1, w)
        ep_start = np.flatnonzero(np.concatenate([[True], lay.ep[1:] != lay.ep[:-1]]))  # episodes are contiguous
        ep_max = np.maximum.reduceat(lay.t, ep_start) + 1
        for e, f in zip(lay.ep[ep_start].tolist(), ep_max.tolist()):
            rec = self._episodes.setdefault(e, [-1, 0])
            rec[0] = max(rec[0], f)
        if len(self._last_obs) > self._last_obs_prune_at:
            self._last_obs = {k: v for k, v in self._last_obs.items() if v[1] >= self._pool_wm}
            self._last_obs_prune_at = max(1024, 2 * len(self._last_obs))

    # ------------------------------------------------------------------ validity and completeness
    def _valid(self, tw: np.ndarray) -> np.ndarray:
        """Whether transitions (write indices) and all rows / entries they reference are still stored."""
        s = tw % self.capacity
        return (
            (tw >= self._tr_wm)
            & (tw < self._tr_written)
            & (self._tr_obs[s] >= self._pool_wm)
            & (self._tr_next[s] >= self._pool_wm)
            & (self._tr_entry_t[s] >= self._step_wm)
            & (self._tr_entry_t1[s] >= self._step_wm)
        )

    def _invalidate(self, tw: np.ndarray) -> None:
        """Make transitions (write indices; -1 and already evicted ones ignored) unsampleable."""
        tw = tw[tw >= max(self._tr_wm, 0)]
        if tw.shape[0]:
            slots = np.unique(tw % self.capacity)
            self._num_ok -= int(self._ok[slots].sum())
            self._ok[slots] = False

    def _update_pending(self, new_tw: np.ndarray) -> None:
        """Mark pending transitions whose env step t+1 is complete as sampleable; keep the rest pending."""
        cand = np.concatenate([self._pending, new_tw])
        cand = cand[self._valid(cand)]
        if cand.shape[0]:
            s = cand % self.capacity
            eps = self._tr_episode[s]
            u, inv = np.unique(eps, return_inverse=True)
            recs = [self._episodes.get(e, [-1, 0]) for e in u.tolist()]
            frontier = np.array([r[0] for r in recs], np.int64)[inv]
            ended = np.array([r[1] for r in recs], bool)[inv]
            complete = ended | (self._tr_step[s] + 2 <= frontier)
            done_slots = s[complete]
            self._num_ok += int((~self._ok[done_slots]).sum())
            self._ok[done_slots] = True
            cand = cand[~complete]
        self._pending = cand.astype(np.int64)
        for e in [e for e, r in self._episodes.items() if r[1]]:
            del self._episodes[e]  # every transition of an ended episode is complete now

    # ------------------------------------------------------------------ sampling
    def _draw(self, B: int) -> np.ndarray:
        """``B`` ring slots drawn uniformly (with replacement) from the sampleable ones."""
        filled = min(self._tr_written, self.capacity)
        frac = self._num_ok / filled
        if frac >= 0.5:  # rejection sampling: exact uniform over ok slots, O(B)
            parts, got = [], 0
            while got < B:
                cand = self._rng.integers(0, filled, size=int((B - got) / frac * 1.1) + 16)
                cand = cand[self._ok[cand]][: B - got]
                parts.append(cand)
                got += cand.shape[0]
            return np.concatenate(parts)
        ok = np.flatnonzero(self._ok[:filled])
        return ok[self._rng.integers(0, ok.shape[0], size=B)]

    def _gather(self, slots: np.ndarray) -> dict[str, np.ndarray]:
        """The transitions in ``slots`` and where the joint records hold the others at t and t+1 (``columns.LOOKUP``, -1: masked out)."""
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
            col.TERMINATEDS: self._tr_term[slots],
            col.TRUNCATEDS: self._tr_trunc[slots],
            col.NEXT_OBS: self._pool_obs[r1],
            col.NEXT_STATE: self._pool_state[r1],
        }
        # others acting at t: rows of entry (episode, t) without the ego's column, and the transitions acting from them
        cols0 = shift + (shift >= (self._pool_owner[r0] % M)[:, None])
        rows0 = np.take_along_axis(self._step_rows[e0 % K], cols0, axis=1)
        ok0 = np.take(self._pool_owner, rows0, mode="clip") == e0[:, None] * M + cols0
        tr0 = np.take(self._pool_tr_obs, rows0, mode="clip")
        ok0 &= tr0 >= self._tr_wm
        ok0 &= tr0 >= 0
        out[col.OTHERS_ROWS] = np.where(ok0, rows0, -1).astype(np.int32)
        out[col.OTHERS_TRANSITIONS] = np.where(ok0, tr0 % C, -1).astype(np.int32)
        # every other agent with an observation at t+1
        cols1 = shift + (shift >= (self._pool_owner[r1] % M)[:, None])
        rows1 = np.take_along_axis(self._step_rows[e1 % K], cols1, axis=1)
        ok1 = np.take(self._pool_owner, rows1, mode="clip") == e1[:, None] * M + cols1
        out[col.NEXT_OTHERS_ROWS] = np.where(ok1, rows1, -1).astype(np.int32)
        out[col.TRANSITION] = slots.astype(np.int32)
        out[col.ENV_STEP] = self._tr_step[slots].copy()
        out[col.EPISODE] = self._tr_episode[slots].copy()
        out[col.AGENT] = self._tr_agent[slots].copy()
        return out


def _new_array(spec: _ArraySpec, rows: int, head: np.ndarray | None = None) -> np.ndarray:
    """An array of ``rows`` rows (plus the padding row if ``spec.padded``) that starts with ``head`` and holds ``spec.fill`` after it."""
    arr = np.empty((rows + spec.padded, *spec.row_shape), spec.dtype)
    k = 0 if head is None else head.shape[0]
    if k:
        arr[:k] = head
    arr[k:] = spec.fill
    return arr


def _layout(b: TransitionBatch) -> _Layout:
    """The batch in layout order; raises ``ValueError`` on duplicate transitions or an action after a done one."""
    # Layout order: episodes by first appearance in the batch (not by key: keys hash RLlib's random
    # uuids, and a key-dependent layout would make same-seed runs sample differently), agent, step.
    ep_raw = np.asarray(b.episode, np.int64)
    _, first_idx, ep_inv = np.unique(ep_raw, return_index=True, return_inverse=True)
    rank_key = ep_raw[np.sort(first_idx)]  # episode key of each rank
    ep_rank_raw = np.argsort(np.argsort(first_idx))[ep_inv]
    order = np.lexsort((b.env_step, b.agent, ep_rank_raw))
    ep = ep_raw[order]
    ag = np.asarray(b.agent, np.int64)[order]
    t = np.asarray(b.env_step, np.int64)[order]
    term = np.asarray(b.terminateds, bool)[order]
    trunc = np.asarray(b.truncateds, bool)[order]
    done = term | trunc
    n = ep.shape[0]
    same = np.zeros(n, bool)
    same[1:] = (ep[1:] == ep[:-1]) & (ag[1:] == ag[:-1])
    dup = same[1:] & (t[1:] == t[:-1])
    if dup.any():
        k = int(np.flatnonzero(dup)[0])
        raise ValueError(f"duplicate transition: episode {ep[k]}, agent {ag[k]}, env step {t[k]} appears twice in the batch")
    after_done = same[1:] & done[:-1]
    if after_done.any():
        k = int(np.flatnonzero(after_done)[0])
        raise ValueError(f"agent {ag[k]} of episode {ep[k]} acts at env step {t[k + 1]} after its done transition at env step {t[k]}")
    chain_prev = np.zeros(n, bool)
    chain_prev[1:] = same[1:] & (t[1:] == t[:-1] + 1)
    chain_next = np.zeros(n, bool)
    chain_next[:-1] = chain_prev[1:]
    return _Layout(order, ep_rank_raw[order], rank_key, ep, ag, t, term, trunc, same, chain_prev, chain_next)


def _unique_pairs(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lexicographically sorted unique (a, b) int64 pairs, shape (U, 2), and the index of every input pair in them."""
    n = a.shape[0]
    if n == 0:
        return np.zeros((0, 2), np.int64), np.zeros(0, np.int64)
    order = np.lexsort((b, a))
    sa, sb = a[order], b[order]
    first = np.ones(n, bool)
    first[1:] = (sa[1:] != sa[:-1]) | (sb[1:] != sb[:-1])
    group = np.cumsum(first) - 1
    inv = np.empty(n, np.int64)
    inv[order] = group
    return np.stack([sa[first], sb[first]], axis=1), inv
