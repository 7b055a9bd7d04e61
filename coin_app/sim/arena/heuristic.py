"""A scripted arena driver (no learning): reach the target's centre line from behind, then track it and stop.

From the observation only (``observation.py``), in the target's frame (``a`` along the
target heading, ``e`` to its left, ``psi`` the vehicle heading relative to the target's):

* **line phase** when the vehicle is behind the target or just past it (a < 1), inside a cone around the
  line (|e| < 0.6 max(-a, 0) + 0.8) and roughly aligned (|psi| < 1.4): Stanley steering
  ``-psi - atan(k e / (|v| + 0.5))`` and a speed that lets the 1 m/s² pedal stop the car on the
  target;
* otherwise **approach**: pure pursuit of the point 10 m behind the target on its line (circling
  there until aligned).

``heuristic_actions`` ignores obstacles and the other vehicles: the arena's reference for tests
and a floor for learned policies. ``avoiding_actions`` is the same driver with one reflex for the
closest entity of the observation (nav_ppo's optional teacher): when it lies ahead, in a
corridor about its own width, closer to the vehicle than the target and within a look-ahead that
grows with speed, steer at full lock away from it and slow to a crawl (brake when nearly touching).

``planning_actions`` is the plain driver behind a safety filter over short rollouts: it simulates
a fixed set of constant actions (and the plain driver's own) for ``horizon`` steps with the arena's
dynamics (Eq. 1), every observed entity (the paper's observation: the closest one only) moving at
its observed speed and heading, and takes the
plain driver's action if its rollout keeps ``margin`` of clearance, else the admissible action
closest to it, else the one whose rollout keeps the most clearance (a sampling-based filter in the
spirit of Wabersich & Zeilinger 2018; nothing of it is in the paper). The vehicle's footprint is two
circles along its axis; an entity is its bounding circle.

``candidate_features`` turns the filter's rollouts into observation numbers (the arena's
``candidate_features`` option, ``observation.py``). Every driver accepts observations with or
without them and reads only the own numbers and the entity blocks.

``DRIVERS`` names all three.
"""

from __future__ import annotations

import numba
import numpy as np

from coin_app.sim.arena.config import ENTITY_WIDTH, OWN_WIDTH
from coin_app.sim.arena.observation import POSITION_SCALE, SIZE_SCALE, SPEED_SCALE, layout_of
from coin_app.sim.dynamics import friction_bicycle_tan

OWN_RADIUS = 0.5 * float(np.hypot(2.5, 1.0))  # the bounding radius of the arena's 2.5 x 1.0 m vehicles
# the planning filter's footprint: two circles at +-OFFSET along the axis, each covering half the 2.5 x 1.0 m box
FOOTPRINT_OFFSET = 0.625
FOOTPRINT_RADIUS = float(np.hypot(0.625, 0.5))
# the planning filter's constant candidate actions: 7 steering values x 3 pedals (brake, coast, full)
CANDIDATES = np.array([(st, pd) for st in np.linspace(-1.0, 1.0, 7) for pd in (-1.0, 0.0, 1.0)])
FILTER_HORIZON = 25  # steps of each candidate rollout (2.5 s at dt 0.1), chosen on training scenarios (docs/arena/README.md)
FILTER_MARGIN = 0.6  # m of clearance a rollout must keep to be admissible
CLEARANCE_CAP = 3.0  # m: the candidate features' clearances are capped here (every margin of interest is below it)


def as_rows(obs: np.ndarray) -> np.ndarray:
    """Arena observations as float64 rows (N, 6 + 7 k [+ 44]); one observation becomes one row (``observation.layout_of``)."""
    obs = np.asarray(obs, float)
    rows = obs.reshape(1, -1) if obs.ndim == 1 else obs
    if rows.ndim != 2:
        raise ValueError(f"arena observations must have shape (N, 6 + 7 k) with k >= 1 (+ 44 candidate features), got {obs.shape}")
    layout_of(rows.shape[1])
    return rows


def entity_views(obs: np.ndarray) -> list[np.ndarray]:
    """One paper-layout (N, 13) view per observed entity block of ``obs`` (N, 6 + 7 k [+ 44]): own numbers, then that entity's."""
    rows = as_rows(obs)
    k, features = layout_of(rows.shape[1])
    if k == 1 and not features:
        return [rows]
    own = rows[:, :OWN_WIDTH]
    return [np.concatenate([own, rows[:, OWN_WIDTH + ENTITY_WIDTH * b : OWN_WIDTH + ENTITY_WIDTH * (b + 1)]], 1) for b in range(k)]


@numba.njit(cache=True)
def _heuristic_actions(obs: np.ndarray, cruise: float, dt: float, friction: float, max_steer: float) -> np.ndarray:
    out = np.empty((len(obs), 2))
    for i in range(len(obs)):
        tx, ty = obs[i, 0] * POSITION_SCALE, obs[i, 1] * POSITION_SCALE  # the target in the vehicle frame
        rel = np.arctan2(obs[i, 2], obs[i, 3])  # target heading in the vehicle frame
        speed = obs[i, 4] * SPEED_SCALE
        c, s = np.cos(rel), np.sin(rel)
        # the vehicle (origin) in the target frame
        a = -(c * tx + s * ty)
        e = -(-s * tx + c * ty)
        psi = -rel
        line = a < 1.0 and abs(e) < 0.6 * max(-a, 0.0) + 0.8 and abs(psi) < 1.4
        bx, by = tx - 10.0 * c, ty - 10.0 * s  # 10 m behind the target on its line
        pursuit = np.arctan2(by, bx)
        if line:
            steer = -psi - np.arctan(1.5 * e / (abs(speed) + 0.5))  # Stanley
            v_des = min(cruise, 0.8 * np.sqrt(2.0 * 0.8 * max(-a - 0.3, 0.0)))  # stop on the target at 0.8 m/s^2
        else:
            steer = 1.5 * pursuit
            v_des = 1.5 if abs(pursuit) > 1.0 else min(cruise, 0.5 + 0.4 * np.sqrt(bx * bx + by * by))
        out[i, 0] = min(max(steer / max_steer, -1.0), 1.0)
        out[i, 1] = min(max((v_des - friction * speed) / dt, -1.0), 1.0)
    return out


def heuristic_actions(obs: np.ndarray, cruise: float = 4.0, dt: float = 0.1, friction: float = 0.99, max_steer: float = 0.8) -> np.ndarray:
    """(steering, pedal) in [-1, 1] for observations (N, 6 + 7 k) (only the target and own numbers are read)."""
    return _heuristic_actions(as_rows(obs), float(cruise), float(dt), float(friction), float(max_steer))


def avoiding_actions(
    obs: np.ndarray, look: float = 4.0, lateral: float = 1.8, crawl: float = 2.5, dt: float = 0.1, friction: float = 0.99
) -> np.ndarray:
    """``heuristic_actions`` with a reflex away from the closest entity ahead (see module doc) for observations (N, 6 + 7 k)."""
    obs = entity_views(obs)[0]
    actions = heuristic_actions(obs, dt=dt, friction=friction)
    near = obs[:, 6:8] * POSITION_SCALE  # the entity's centre in the vehicle frame
    speed = obs[:, 4] * SPEED_SCALE
    distance = np.linalg.norm(near, axis=1)
    clearance = distance - obs[:, 10] * SIZE_SCALE - OWN_RADIUS
    ahead = (
        (obs[:, 12] > 0.5)
        & (near[:, 0] > 0.0)
        & (np.abs(near[:, 1]) < obs[:, 10] * SIZE_SCALE + lateral)
        & (clearance < look + np.abs(speed))
        & (distance < np.linalg.norm(obs[:, 0:2] * POSITION_SCALE, axis=1))  # not beyond the target
    )
    away = np.where(near[:, 1] >= 0.0, -1.0, 1.0)  # full lock to the side the entity is not on
    crawl_pedal = np.clip((crawl - friction * speed) / dt, -1.0, 1.0)
    pedal = np.where(ahead, np.minimum(actions[:, 1], crawl_pedal), actions[:, 1])
    pedal = np.where(ahead & (clearance < 0.5), -1.0, pedal)
    return np.stack([np.where(ahead, away, actions[:, 0]), pedal], 1)


@numba.njit(cache=True)
def _least_clearance(
    speed: float,
    steer: np.ndarray,
    pedal: np.ndarray,
    entity: np.ndarray,
    horizon: int,
    dt: float,
    wheelbase: float,
    friction: float,
) -> np.ndarray:
    """(P, K) least clearance of one vehicle's K constant-action rollouts (Eq. 1 from the origin of its frame at ``speed``;
    actions ``steer``, ``pedal`` (K,)) over ``horizon`` steps against P entities moving at constant velocity
    (``entity`` (P, 5): centre x, y, velocity x, y, reach = radius + the footprint circles' radius). Each rollout is
    stepped once for all entities; the vehicle's footprint is two circles at +-``FOOTPRINT_OFFSET`` along its axis."""
    # the least clearance min_t sqrt(d_t^2) - reach is sqrt(min_t d_t^2) - reach to the bit (sqrt and "- reach" are
    # monotonic in floating point), so the steps keep the least squared distance and take one square root at the end
    nearest = np.full((len(entity), len(steer)), np.inf)
    other = np.empty((horizon + 1, len(entity), 2))  # the entities' centres at each step
    for t in range(1, horizon + 1):
        for p in range(len(entity)):
            other[t, p, 0], other[t, p, 1] = entity[p, 0] + t * dt * entity[p, 2], entity[p, 1] + t * dt * entity[p, 3]
    for c in range(len(steer)):
        x, y, h, sp, tan_steer = 0.0, 0.0, 0.0, speed, np.tan(steer[c])
        for t in range(1, horizon + 1):
            x, y, h, sp, cos_h, sin_h = friction_bicycle_tan(x, y, h, sp, pedal[c], tan_steer, dt, wheelbase, friction)
            ax, ay = FOOTPRINT_OFFSET * cos_h, FOOTPRINT_OFFSET * sin_h
            for p in range(len(entity)):
                ox, oy = other[t, p, 0], other[t, p, 1]
                dx, dy = x + ax - ox, y + ay - oy
                front = dx * dx + dy * dy
                dx, dy = x + -1.0 * ax - ox, y + -1.0 * ay - oy
                nearest[p, c] = min(min(nearest[p, c], front), dx * dx + dy * dy)
    least = np.empty_like(nearest)
    for p in range(len(entity)):
        for c in range(len(steer)):
            least[p, c] = np.sqrt(nearest[p, c]) - entity[p, 4]
    return least


@numba.njit(cache=True)
def _entity(row: np.ndarray, col: int) -> tuple[float, float, float, float, float]:
    """(centre x, y, velocity x, y, reach) of the entity block at column ``col`` of an observation row (``observation.py``)."""
    speed = row[col + 5] * SPEED_SCALE
    return (
        row[col] * POSITION_SCALE, row[col + 1] * POSITION_SCALE, speed * row[col + 3], speed * row[col + 2],
        row[col + 4] * SIZE_SCALE + FOOTPRINT_RADIUS,
    )  # fmt: skip


@numba.njit(cache=True)
def _may_come_near(row: np.ndarray, col: int, horizon: int, margin: float, dt: float, max_pedal: float) -> bool:
    """``may_come_near`` of the entity block at column ``col`` of an observation row."""
    t = horizon * dt
    own = t * (abs(row[4] * SPEED_SCALE) + horizon * max_pedal * dt)
    other = t * abs(row[col + 5] * SPEED_SCALE)
    x, y = row[col] * POSITION_SCALE, row[col + 1] * POSITION_SCALE
    gap = np.sqrt(x * x + y * y) - row[col + 4] * SIZE_SCALE - FOOTPRINT_RADIUS - FOOTPRINT_OFFSET
    return row[col + 6] > 0.5 and gap - own - other < margin + 1.0


@numba.njit(cache=True)
def _rollout_clearance(
    obs: np.ndarray, steer: np.ndarray, pedal: np.ndarray, horizon: int, dt: float, wheelbase: float, friction: float
) -> np.ndarray:
    out = np.full(steer.shape, np.inf)
    entity = np.empty((1, 5))
    for i in range(len(obs)):
        if obs[i, 12] > 0.5:
            entity[0, 0], entity[0, 1], entity[0, 2], entity[0, 3], entity[0, 4] = _entity(obs[i], 6)
            out[i] = _least_clearance(obs[i, 4] * SPEED_SCALE, steer[i], pedal[i], entity, horizon, dt, wheelbase, friction)[0]
    return out


def rollout_clearance(
    obs: np.ndarray,
    actions: np.ndarray,
    horizon: int,
    dt: float = 0.1,
    friction: float = 0.99,
    wheelbase: float = 2.0,
    max_steer: float = 0.8,
    max_pedal: float = 1.0,
) -> np.ndarray:
    """(N, K) least clearance over ``horizon`` steps between each vehicle holding action k of ``actions`` (N, K, 2) and its
    closest entity (moving at its observed speed and heading); inf without an entity. ``obs`` (N, 13): the paper's layout."""
    obs = as_rows(obs)
    actions = np.asarray(actions, float)
    steer, pedal = (np.ascontiguousarray(actions[..., k] * scale) for k, scale in ((0, max_steer), (1, max_pedal)))
    return _rollout_clearance(obs, steer, pedal, int(horizon), float(dt), float(wheelbase), float(friction))


@numba.njit(cache=True)
def _may_come_near_all(obs: np.ndarray, horizon: int, margin: float, dt: float, max_pedal: float) -> np.ndarray:
    out = np.empty(len(obs), np.bool_)
    for i in range(len(obs)):
        out[i] = _may_come_near(obs[i], 6, horizon, margin, dt, max_pedal)
    return out


def may_come_near(obs: np.ndarray, horizon: int, margin: float, dt: float = 0.1, max_pedal: float = 1.0) -> np.ndarray:
    """(N,) whether any rollout of ``horizon`` steps could bring the vehicle within ``margin`` of its entity (obs (N, 13)).

    A bound, not a rollout: the vehicle's speed grows by at most ``max_pedal * dt`` a step, so it travels at most
    ``T (|v| + horizon max_pedal dt)`` in ``T = horizon dt`` seconds, and the entity at most ``T |v_entity|``; pairs
    farther apart than that (plus 1 m of slack) keep more than ``margin`` under every action. False without an entity.
    """
    return _may_come_near_all(as_rows(obs), int(horizon), float(margin), float(dt), float(max_pedal))


@numba.njit(cache=True)
def _candidate_clearance(
    obs: np.ndarray, blocks: int, steer: np.ndarray, pedal: np.ndarray, horizon: int, margin: float, dt: float, physics: tuple
) -> np.ndarray:
    wheelbase, friction, max_pedal = physics
    out = np.full(steer.shape, np.inf)
    entity = np.empty((blocks, 5))
    for i in range(len(obs)):
        near = 0
        for b in range(blocks):
            col = OWN_WIDTH + ENTITY_WIDTH * b
            if _may_come_near(obs[i], col, horizon, margin, dt, max_pedal):
                entity[near, 0], entity[near, 1], entity[near, 2], entity[near, 3], entity[near, 4] = _entity(obs[i], col)
                near += 1
        if near:
            least = _least_clearance(obs[i, 4] * SPEED_SCALE, steer[i], pedal[i], entity[:near], horizon, dt, wheelbase, friction)
            for p in range(near):
                for c in range(steer.shape[1]):
                    out[i, c] = min(out[i, c], least[p, c])
    return out


def candidate_clearance(
    obs: np.ndarray, horizon: int = FILTER_HORIZON, margin: float = FILTER_MARGIN, dt: float = 0.1, friction: float = 0.99, **physics: float
) -> tuple[np.ndarray, np.ndarray]:
    """The planning filter's candidates (N, 22, 2), the plain driver's action first, and each one's least rollout clearance
    (N, 22) over every observed entity (inf where none may come within ``margin``), for observations (N, 6 + 7 k [+ 44]).

    Only the (vehicle, entity) pairs that ``may_come_near`` are rolled out: the others cannot
    come within ``margin``, so a clearance left at inf stands for one of at least ``margin``.
    ``physics``: the arena's ``wheelbase``, ``max_steer`` and ``max_pedal`` where they are not the defaults.
    """
    rows = as_rows(obs)
    blocks, _ = layout_of(rows.shape[1])
    n = len(rows)
    physics = {"wheelbase": 2.0, "max_steer": 0.8, "max_pedal": 1.0} | physics
    nominal = heuristic_actions(rows[:, : OWN_WIDTH + ENTITY_WIDTH], dt=dt, friction=friction, max_steer=physics["max_steer"])
    candidates = np.concatenate([nominal[:, None, :], np.broadcast_to(CANDIDATES, (n, *CANDIDATES.shape))], axis=1)
    steer = np.ascontiguousarray(candidates[..., 0] * physics["max_steer"])
    pedal = np.ascontiguousarray(candidates[..., 1] * physics["max_pedal"])
    shape = (float(physics["wheelbase"]), float(friction), float(physics["max_pedal"]))
    return candidates, _candidate_clearance(rows, blocks, steer, pedal, int(horizon), float(margin), float(dt), shape)


def planning_actions(
    obs: np.ndarray, horizon: int = FILTER_HORIZON, margin: float = FILTER_MARGIN, dt: float = 0.1, friction: float = 0.99
) -> np.ndarray:
    """``heuristic_actions`` behind the rollout safety filter of the module doc, for observations (N, 6 + 7 k [+ 44]).

    With several observed entities a rollout's clearance is its least over all of them
    (``candidate_clearance``); the plain action if admissible, else the admissible candidate
    closest to it, else the candidate with the most clearance.
    """
    candidates, clearance = candidate_clearance(obs, horizon, margin, dt, friction)
    gap = ((candidates - candidates[:, :1, :]) ** 2).sum(-1)  # the nominal action itself: 0
    cost = np.where(clearance >= margin, gap, 1e6 - clearance)  # inadmissible: the most clearance first
    return candidates[np.arange(len(candidates)), np.argmin(cost, axis=1)]


def candidate_features(obs: np.ndarray, dt: float = 0.1, friction: float = 0.99, **physics: float) -> np.ndarray:
    """The 44 candidate features (N, 44) float32 of observations (N, 6 + 7 k; ``config.CANDIDATE_WIDTH``): each candidate's
    rollout clearance (``candidate_clearance``, capped at ``CLEARANCE_CAP`` and divided by it), then whether it keeps
    ``FILTER_MARGIN``. Pairs are pruned at the cap, not the margin, so every capped clearance is exact."""
    _, clearance = candidate_clearance(obs, margin=CLEARANCE_CAP, dt=dt, friction=friction, **physics)
    return np.concatenate([np.minimum(clearance, CLEARANCE_CAP) / CLEARANCE_CAP, clearance >= FILTER_MARGIN], 1).astype(np.float32)


DRIVERS = {"heuristic": heuristic_actions, "avoiding": avoiding_actions, "planning": planning_actions}  # the scripted drivers by name
