"""The TD3 family's centralized-critic connector: a learner-connector piece that injects the global state into the train batch.

The joint-step replay (``buffer.py``) samples per-agent transitions and, with each row, its lookups
(``columns.LOOKUP``): the rows of the replay's joint records (``JointStepReplayBuffer.joint_columns``)
that hold the other agents at the row's env step t and t+1 and the global reward. :class:`JointState`,
the one piece of the family's learner connector pipeline, replaces the lookups by the global columns
(``columns.GLOBAL``, COIN §4.2, Eqs. 9-11) with one indexed copy per column:

    others_state      = pool_state[others_rows]        others_actions  = actions[others_transitions]
    others_rewards    = rewards[others_transitions]    global_rewards  = global_rewards[transition]
    next_others_state = pool_state[next_others_rows]   next_others_obs = pool_obs[next_others_rows]
    others_mask = others_rows >= 0                     next_others_mask = next_others_rows >= 0

where a masked lookup (-1) reads the padding row (zeros; masked rewards are zero). The records it
reads are the replay's own arrays when the learner shares the algorithm's process (``num_learners=0``),
and a :class:`JointRecordsCopy` in a remote learner (``num_learners=1``), kept current by the deltas
the algorithm sends with each update (``JointStepReplayBuffer.joint_delta``): per update the learner
gets the sampled rows, the int32 lookups and the rows written since the last update, not the
others' padded columns. A batch without lookups (one that already has the global columns) passes
unchanged.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol

import numpy as np
from ray.rllib.connectors.connector_v2 import ConnectorV2

from coin_app.algorithms.td3 import columns as col


class JointRecords(Protocol):
    """What :class:`JointState` reads: the joint records by name (``buffer.JOINT_RECORDS``)."""

    def joint_columns(self) -> Mapping[str, np.ndarray]:
        """The records by name; a lookup of -1 reads each one's last row."""
        ...


def inject_global_state(records: Mapping[str, np.ndarray], rows: dict[str, Any]) -> dict[str, Any]:
    """``rows`` without its lookups (``columns.LOOKUP``) and with the global columns (``columns.GLOBAL``) gathered from ``records``."""
    others, others_tr, nxt = (np.asarray(rows.pop(c)) for c in (col.OTHERS_ROWS, col.OTHERS_TRANSITIONS, col.NEXT_OTHERS_ROWS))
    slot = np.asarray(rows.pop(col.TRANSITION))
    mask, next_mask = others >= 0, nxt >= 0
    rows[col.GLOBAL_REWARDS] = np.take(records["global_rewards"], slot)
    rows[col.OTHERS_STATE] = np.take(records["pool_state"], others, axis=0, mode="wrap")
    rows[col.OTHERS_ACTIONS] = np.take(records["actions"], others_tr, axis=0, mode="wrap")
    rows[col.OTHERS_MASK] = mask
    rows[col.OTHERS_REWARDS] = np.where(mask, np.take(records["rewards"], others_tr, mode="wrap"), np.float32(0.0))
    rows[col.NEXT_OTHERS_STATE] = np.take(records["pool_state"], nxt, axis=0, mode="wrap")
    rows[col.NEXT_OTHERS_OBS] = np.take(records["pool_obs"], nxt, axis=0, mode="wrap")
    rows[col.NEXT_OTHERS_MASK] = next_mask
    return rows


class JointRecordsCopy:
    """A copy of a replay's joint records in another process, kept current by the replay's ``joint_delta``\\ s applied in order."""

    def __init__(self) -> None:
        self.records: dict[str, np.ndarray] = {}
        self.written: tuple[int, int] | None = None  # the replay's write counts the copy is current with

    def apply(self, delta: Mapping[str, Any]) -> None:
        """Write a delta's rows, first growing each record to the replay's allocated rows (new rows zero, like the replay's)."""
        for name, rows in delta["rows"].items():
            values = np.asarray(delta["values"][name])
            have = self.records.get(name)
            if have is None or have.shape[0] < rows:
                grown = np.zeros((rows, *values.shape[1:]), values.dtype)
                if have is not None:  # an old padding row (zero) becomes a row the replay also holds zero until written
                    grown[: have.shape[0]] = have
                self.records[name] = have = grown
            have[delta["index"][name]] = values
        self.written = tuple(delta["written"])

    def joint_columns(self) -> Mapping[str, np.ndarray]:
        """The copied records by name."""
        return self.records


class JointState(ConnectorV2):
    """Learner connector: each module batch's replay lookups -> the global state (others at t and t+1, global reward)."""

    def __init__(self, *args: Any, records: JointRecords | None = None, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.records: JointRecords = records if records is not None else JointRecordsCopy()

    def __call__(self, *, rl_module: Any, batch: dict[str, Any], episodes: list[Any], **kwargs: Any) -> dict[str, Any]:
        """Replace the lookups of every module batch that has them by the global columns."""
        for module_id, rows in batch.items():
            if col.TRANSITION in rows:
                columns = self.records.joint_columns()
                if not columns:
                    raise RuntimeError(
                        f"module {module_id!r}: the batch has replay lookups but this learner holds no joint records "
                        "(a remote learner gets them with the update's joint_delta)"
                    )
                inject_global_state(columns, rows)
        return batch
