"""Road networks of the native scenarios, loaded from MetaDrive 0.4.3 map data.

The JSON files in ``maps/`` are MetaDrive's own multi-agent maps (Apache-2.0, see
``maps/NOTICE.md``). A lane is either straight or circular; every query here is
vectorized over an array of lane ids so that all vehicles are handled in one call.

Lane-local coordinates follow MetaDrive: ``s`` along the lane from its start, ``r``
positive to the *right* of the driving direction.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numba
import numpy as np

from coin_app.sim.collision import _grid_row
from coin_app.sim.scenes import DRIVING_SCENARIOS

MAP_DIR = Path(__file__).parent / "maps"
MAP_NAMES = DRIVING_SCENARIOS  # one map file per driving scenario (sim/scenes.py)
SOLID_LINE_TYPES = ("ROAD_LINE_SOLID_SINGLE_WHITE", "ROAD_LINE_SOLID_SINGLE_YELLOW")


@numba.njit(cache=True)
def wrap_to_pi(angle: np.ndarray) -> np.ndarray:
    """Wrap angles to [-pi, pi)."""
    return (angle + np.pi) % (2 * np.pi) - np.pi


@numba.njit(cache=True, error_model="numpy")
def _lane_sr(rows: np.ndarray, is_circ: np.ndarray, lane: int, x: float, y: float) -> tuple[float, float]:
    """Lane-local (s, r) of the point (x, y) on ``lane`` (``RoadMap.lane_rows``; see ``RoadMap.local_coordinates``)."""
    row = rows[lane]
    if not is_circ[lane]:
        rx, ry = x - row[0], y - row[1]
        return rx * row[2] + ry * row[3], rx * row[3] - ry * row[2]
    dx, dy = x - row[4], y - row[5]
    sp, direc, mid, rad = row[6], row[7], row[8], row[9]
    # wrap around the arc's middle (mid), not its start: MetaDrive wraps around the start,
    # which flips s to negative near the end of its 180-degree U-turn lanes
    dphi = mid + wrap_to_pi(np.arctan2(dy, dx) - sp - mid)
    return direc * dphi * rad, direc * (np.hypot(dx, dy) - rad)


@numba.njit(cache=True)
def _local_coordinates(rows: np.ndarray, is_circ: np.ndarray, lane: np.ndarray, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    s, r = np.empty(len(lane)), np.empty(len(lane))
    for i in range(len(lane)):
        s[i], r[i] = _lane_sr(rows, is_circ, lane[i], pos[i, 0], pos[i, 1])
    return s, r


@numba.njit(cache=True, error_model="numpy")
def _lane_heading(
    unit: np.ndarray, start_phase: np.ndarray, direction: np.ndarray, radius: np.ndarray, is_circ: np.ndarray, lane: int, s: float
) -> float:
    """Heading (rad) of ``lane`` at longitudinal position ``s`` (``RoadMap.heading_at``)."""
    if not is_circ[lane]:
        return np.arctan2(unit[lane, 1], unit[lane, 0])
    return start_phase[lane] + direction[lane] * s / radius[lane] + direction[lane] * np.pi / 2


@numba.njit(cache=True)
def _heading_at(
    unit: np.ndarray,
    start_phase: np.ndarray,
    direction: np.ndarray,
    radius: np.ndarray,
    is_circ: np.ndarray,
    lane: np.ndarray,
    s: np.ndarray,
) -> np.ndarray:
    out = np.empty(len(lane))
    for i in range(len(lane)):
        out[i] = _lane_heading(unit, start_phase, direction, radius, is_circ, lane[i], s[i])
    return out


@numba.njit(cache=True, error_model="numpy")
def _lane_position(lanes: tuple, lane: int, s: float, r: float) -> tuple[float, float]:
    """World position of lane-local (s, r) on ``lane``; ``lanes``: ``RoadMap.lane_arrays``."""
    start, unit, center, start_phase, direction, radius, is_circ = lanes
    if not is_circ[lane]:
        u0, u1 = unit[lane, 0], unit[lane, 1]
        return start[lane, 0] + u0 * s + u1 * r, start[lane, 1] + u1 * s + -u0 * r
    direc, rad = direction[lane], radius[lane]
    phi = start_phase[lane] + direc * s / rad
    rr = rad + r * direc
    return center[lane, 0] + rr * np.cos(phi), center[lane, 1] + rr * np.sin(phi)


@numba.njit(cache=True, error_model="numpy")
def _lane_right_normal(lanes: tuple, lane: int, x: float, y: float) -> tuple[float, float]:
    """Unit vector to the right of ``lane``'s direction at (x, y); ``lanes``: ``RoadMap.lane_arrays``."""
    start, unit, center, start_phase, direction, radius, is_circ = lanes
    if not is_circ[lane]:
        return unit[lane, 1], -unit[lane, 0]
    dx, dy = x - center[lane, 0], y - center[lane, 1]
    nrm = max(np.hypot(dx, dy), 1e-9)
    return direction[lane] * dx / nrm, direction[lane] * dy / nrm


@numba.njit(cache=True)
def _positions(lanes: tuple, lane: np.ndarray, s: np.ndarray, r: np.ndarray) -> np.ndarray:
    out = np.empty((len(lane), 2))
    for i in range(len(lane)):
        out[i, 0], out[i, 1] = _lane_position(lanes, lane[i], s[i], r[i])
    return out


@numba.njit(cache=True)
def _right_normals(lanes: tuple, lane: np.ndarray, pos: np.ndarray) -> np.ndarray:
    out = np.empty((len(lane), 2))
    for i in range(len(lane)):
        out[i, 0], out[i, 1] = _lane_right_normal(lanes, lane[i], pos[i, 0], pos[i, 1])
    return out


@numba.njit(cache=True)
def _in_hull(normals: np.ndarray, offsets: np.ndarray, bbox: np.ndarray, lane: int, x: float, y: float, margin: float) -> bool:
    """Whether (x, y) lies within ``margin`` of lane ``lane``'s on-lane region (its bounding box, then its half-planes)."""
    bb = bbox[lane]
    if not (x >= bb[0] - margin and x <= bb[2] + margin and y >= bb[1] - margin and y <= bb[3] + margin):
        return False
    for k in range(normals.shape[1]):
        if not normals[lane, k, 0] * x + normals[lane, k, 1] * y - offsets[lane, k] <= margin:
            return False
    return True


@numba.njit(cache=True)
def _hull_contains(
    table: np.ndarray, origin: np.ndarray, cell: float, shape: np.ndarray, normals: np.ndarray, offsets: np.ndarray, bbox: np.ndarray,
    pos: np.ndarray, margin: float,
) -> np.ndarray:  # fmt: skip
    out = np.zeros((len(pos), len(bbox)), np.bool_)
    for i in range(len(pos)):
        for lane in _grid_row(table, origin, cell, shape, pos[i, 0], pos[i, 1]):
            if lane < 0:
                break
            out[i, lane] = _in_hull(normals, offsets, bbox, lane, pos[i, 0], pos[i, 1], margin)
    return out


@numba.njit(cache=True, error_model="numpy")
def localize(
    pos: np.ndarray,
    heading: np.ndarray,
    idx: np.ndarray,
    route: np.ndarray,
    ref_idx: np.ndarray,
    lane: np.ndarray,
    grid: tuple,
    hull: tuple,
    lanes: tuple,
    routes: tuple,
    ckpt_range: float,
) -> np.ndarray:
    """Localise the vehicles ``idx`` (slots of the per-slot arrays): update ``lane`` and ``ref_idx`` in place; (n,) on a lane.

    A vehicle's lane is, among the lanes whose on-lane region (within 5 cm) holds its centre and that point its way
    (cos of the heading difference > 0), the first by route priority (its reference road, then the next, then any)
    and then by distance off the lane (|r| plus how far s lies beyond either end); none keeps the previous lane.
    The reference road switches to a later road of the route when the lane starts it (s < ``ckpt_range``).
    ``grid``: ``GridIndex`` (table, origin, cell, shape) of the hulls; ``hull``: (normals, offsets, bbox);
    ``lanes``: (lane_rows, is_circ, unit, start_phase, direction, radius, length, lane_road);
    ``routes``: (route_roads, route_nroads, route_road_pos).
    """
    table, origin, cell, shape = grid
    normals, offsets, bbox = hull
    rows, is_circ, unit, start_phase, direction, radius, length, lane_road = lanes
    route_roads, route_nroads, route_road_pos = routes
    on_lane = np.zeros(len(idx), np.bool_)
    for n in range(len(idx)):
        i = idx[n]
        x, y, hd = pos[i, 0], pos[i, 1], heading[i]
        rt, ref = route[i], ref_idx[i]
        cur_road = route_roads[rt, ref]
        nxt_road = route_roads[rt, min(ref + 1, route_nroads[rt] - 1)]
        best, best_key = -1, np.inf
        for ln in _grid_row(table, origin, cell, shape, x, y):
            if ln < 0:
                break
            if not _in_hull(normals, offsets, bbox, ln, x, y, 0.05):
                continue
            on_lane[n] = True
            s, r = _lane_sr(rows, is_circ, ln, x, y)
            if not np.cos(_lane_heading(unit, start_phase, direction, radius, is_circ, ln, s) - hd) > 0:
                continue
            l1 = abs(r) + max(s - length[ln], 0.0) + max(-s, 0.0)
            road = lane_road[ln]
            prio = 0.0 if road == cur_road else (1.0 if road == nxt_road else 2.0)
            key = prio * 1e6 + l1
            if key < best_key or (key == best_key and ln < best):
                best, best_key = ln, key
        if best >= 0:
            lane[i] = best
        # reference road: switch when the localised lane starts a later road of the route
        s_lane, _ = _lane_sr(rows, is_circ, lane[i], x, y)
        pos_in_route = route_road_pos[rt, lane_road[lane[i]]]
        if pos_in_route > ref and s_lane < ckpt_range:
            ref_idx[i] = pos_in_route
    return on_lane


def _pad(polys: list[np.ndarray]) -> np.ndarray:
    """Stack polygons into (P, K, 2), repeating each one's last vertex as padding."""
    k = max(len(p) for p in polys)
    out = np.empty((len(polys), k, 2))
    for i, p in enumerate(polys):
        out[i, : len(p)] = p
        out[i, len(p) :] = p[-1]
    return out


class GridIndex:
    """Uniform grid over the map listing, per cell, the items whose box touches the cell (``table``: a row per cell, -1 padded;
    the kernels read the row of a point's cell with ``collision._grid_row``)."""

    def __init__(self, bbox: np.ndarray, reach: float, cell: float = 4.0):
        lo = bbox[:, :2].min(0) - reach - cell
        hi = bbox[:, 2:].max(0) + reach + cell
        self.origin, self.cell = lo, cell
        self.shape = np.ceil((hi - lo) / cell).astype(int)
        c0 = np.floor((bbox[:, :2] - reach - lo) / cell).astype(int)
        c1 = np.floor((bbox[:, 2:] + reach - lo) / cell).astype(int)
        cells: list[list[int]] = [[] for _ in range(int(np.prod(self.shape)))]
        for item, (a, b) in enumerate(zip(c0, c1)):
            for x in range(a[0], b[0] + 1):
                for y in range(a[1], b[1] + 1):
                    cells[x * self.shape[1] + y].append(item)
        k = max(1, max(len(c) for c in cells))
        self.table = np.full((len(cells), k), -1, dtype=np.int64)
        for i, c in enumerate(cells):
            self.table[i, : len(c)] = c


@dataclass(frozen=True)
class Route:
    """A spawn lane's route to one destination: the ordered roads and the final lane."""

    spawn_lane: int
    destination: str
    roads: tuple[int, ...]
    final_lane: int


class RoadMap:
    """Lane geometry, roads, routes, lines, sidewalks and spawn places of one map."""

    def __init__(self, name: str, solid_center_line: bool = False):
        if name not in MAP_NAMES:
            raise ValueError(f"unknown map {name!r}; allowed: {', '.join(MAP_NAMES)}")
        data = json.loads((MAP_DIR / f"{name}.json").read_text())
        self.name = name
        lanes = data["lanes"]
        self.lane_keys = [tuple(lane["key"].split("|")[:2]) + (int(lane["index"]),) for lane in lanes]
        self.lane_index = {k: i for i, k in enumerate(self.lane_keys)}
        n = len(lanes)
        self.num_lanes = n
        self.is_circ = np.array([lane["type"] == "circular" for lane in lanes])
        self.length = np.array([lane["length"] for lane in lanes], dtype=float)
        self.width = np.array([lane["width"] for lane in lanes], dtype=float)
        self.start = np.array([lane["start_point"] for lane in lanes], dtype=float)
        self.end = np.array([lane["end_point"] for lane in lanes], dtype=float)
        self.center = np.zeros((n, 2))
        self.radius = np.ones(n)
        self.start_phase = np.zeros(n)
        self.direction = np.zeros(n)  # +1 CCW, -1 CW, 0 straight (MetaDrive's nav "dir")
        self.angle = np.zeros(n)
        for i, lane in enumerate(lanes):
            if lane["type"] == "circular":
                self.center[i] = lane["center"]
                self.radius[i] = lane["radius"]
                self.start_phase[i] = lane["start_phase"]
                self.direction[i] = lane["direction"]
                self.angle[i] = lane["angle"]
        d = self.end - self.start
        self.unit = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
        self.unit[self.is_circ] = 0.0
        # what local_coordinates reads of each lane, gathered in one step: start (2), unit (2), centre (2),
        # start phase, direction, the arc's middle phase offset, radius
        self.lane_rows = np.column_stack(
            [self.start, self.unit, self.center, self.start_phase, self.direction, self.direction * self.angle / 2, self.radius]
        )
        # what the position and normal kernels read of each lane (_lane_position, _lane_right_normal)
        self.lane_arrays = (self.start, self.unit, self.center, self.start_phase, self.direction, self.radius, self.is_circ)
        self.polygons = [np.array(lane["polygon"], dtype=float) for lane in lanes]
        self.centerlines = [np.array(lane["centerline_s_x_y_heading"], dtype=float)[:, 1:3] for lane in lanes]

        # roads: (from, to) -> lanes ordered by index (0 = left-most, next to the centre line)
        road_keys = sorted({k[:2] for k in self.lane_keys}, key=lambda rk: self.lane_index[rk + (0,)])
        self.road_keys = road_keys
        self.road_index = {rk: i for i, rk in enumerate(road_keys)}
        self.road_nlanes = np.array([sum(1 for k in self.lane_keys if k[:2] == rk) for rk in road_keys])
        self.road_lanes = np.full((len(road_keys), int(self.road_nlanes.max())), -1, dtype=np.int64)
        for i, k in enumerate(self.lane_keys):
            self.road_lanes[self.road_index[k[:2]], k[2]] = i
        self.road_negative = np.array(["-" in rk[1] for rk in road_keys])
        self.lane_road = np.array([self.road_index[k[:2]] for k in self.lane_keys])
        self.road_first_lane = self.road_lanes[:, 0]
        self.road_last_lane = self.road_lanes[np.arange(len(road_keys)), self.road_nlanes - 1]

        # on-lane test regions: MetaDrive's convex hulls (CCW) as half-planes
        hulls = [np.array(lane["localization_hull"], dtype=float) for lane in lanes]
        self.hull_vertices = _pad(hulls)
        edges = np.roll(self.hull_vertices, -1, axis=1) - self.hull_vertices
        norm = np.linalg.norm(edges, axis=2, keepdims=True)
        # outward normal of a CCW polygon edge (ex, ey) is (ey, -ex); padded edges get 0
        self.hull_normals = np.where(norm > 1e-9, np.stack([edges[..., 1], -edges[..., 0]], -1) / np.maximum(norm, 1e-9), 0.0)
        self.hull_offsets = np.einsum("lkd,lkd->lk", self.hull_normals, self.hull_vertices)
        self.hull_bbox = np.concatenate([self.hull_vertices.min(1), self.hull_vertices.max(1)], axis=1)
        self.hull_grid = GridIndex(self.hull_bbox, reach=0.1)

        # physical solid lines (touching one is out of road); broken lines never terminate
        all_segs = self._solid_center_lines(data) if solid_center_line else data["line_segments_physical"]
        segs = [s for s in all_segs if s["type"] in SOLID_LINE_TYPES]
        self.solid_p1 = np.array([s["p1"] for s in segs], dtype=float).reshape(-1, 2)
        self.solid_p2 = np.array([s["p2"] for s in segs], dtype=float).reshape(-1, 2)
        self.solid_half_width = float(segs[0]["half_width"]) if segs else 0.0375
        self.line_p1 = np.array([s["p1"] for s in all_segs], dtype=float).reshape(-1, 2)
        self.line_p2 = np.array([s["p2"] for s in all_segs], dtype=float).reshape(-1, 2)
        self.line_solid = np.array([s["type"] in SOLID_LINE_TYPES for s in all_segs], dtype=bool)
        self.sidewalks = _pad([np.array(s["polygon"], dtype=float) for s in data["sidewalks"]])
        self.sidewalk_bbox = np.concatenate([self.sidewalks.min(1), self.sidewalks.max(1)], axis=1)
        # each sidewalk polygon is a strip: inner edge points, then the outer edge reversed;
        # split it into triangles (always convex) for exact, cheap point tests
        tris = []
        for sw in data["sidewalks"]:
            poly = np.array(sw["polygon"], dtype=float)
            half = len(poly) // 2
            inner, outer = poly[:half], poly[::-1][:half]
            for i in range(half - 1):
                for t in (np.stack([inner[i], inner[i + 1], outer[i + 1]]), np.stack([inner[i], outer[i + 1], outer[i]])):
                    area = 0.5 * np.sum(t[:, 0] * np.roll(t[:, 1], -1) - np.roll(t[:, 0], -1) * t[:, 1])
                    if abs(area) > 1e-9:
                        tris.append(t if area > 0 else t[::-1])
        self.sidewalk_quads = np.array(tris).reshape(-1, 3, 2)
        qe = np.roll(self.sidewalk_quads, -1, axis=1) - self.sidewalk_quads
        qn = np.stack([qe[..., 1], -qe[..., 0]], -1)
        self.sidewalk_normals = qn / np.maximum(np.linalg.norm(qn, axis=2, keepdims=True), 1e-12)
        self.sidewalk_offsets = np.einsum("qkd,qkd->qk", self.sidewalk_normals, self.sidewalk_quads)
        self.sidewalk_quad_bbox = np.concatenate([self.sidewalk_quads.min(1), self.sidewalk_quads.max(1)], axis=1)

        spawn = data["spawn"]
        self.spawn_slot_lane = np.array([self.lane_index[tuple(s["lane"][:2]) + (int(s["lane"][2]),)] for s in spawn["slots"]])
        self.spawn_slot_s = np.array([s["longitude"] for s in spawn["slots"]], dtype=float)
        places = spawn["respawn_places"]
        self.respawn_lane = np.array([self.lane_index[tuple(p["lane"][:2]) + (int(p["lane"][2]),)] for p in places])
        self.respawn_s = np.array([p["longitude"] for p in places], dtype=float)
        self.respawn_region = (float(spawn["RESPAWN_REGION_LONGITUDE"]), float(spawn["RESPAWN_REGION_LATERAL"]))

        # routes: one per (spawn lane, destination node)
        self.routes: list[Route] = []
        for rec in data["destinations"]["routes"]:
            cps = rec["checkpoints"]
            roads = tuple(self.road_index[(a, b)] for a, b in zip(cps[:-1], cps[1:]))
            fl = rec["final_lane"]
            self.routes.append(
                Route(
                    spawn_lane=self.lane_index[tuple(rec["spawn_lane"][:2]) + (int(rec["spawn_lane"][2]),)],
                    destination=rec["destination_node"],
                    roads=roads,
                    final_lane=self.lane_index[(fl[0], fl[1], int(fl[2]))],
                )
            )
        self.routes_by_spawn_lane: dict[int, list[int]] = {}
        for i, r in enumerate(self.routes):
            self.routes_by_spawn_lane.setdefault(r.spawn_lane, []).append(i)

        def neg(node: str) -> str:
            return node[1:] if node.startswith("-") else "-" + node

        # a route that leaves by the reverse of its spawn road returns to its own arm
        self.route_returns = np.array(
            [road_keys[r.roads[-1]] == (neg(road_keys[r.roads[0]][1]), neg(road_keys[r.roads[0]][0])) for r in self.routes]
        )
        max_roads = max(len(r.roads) for r in self.routes)
        self.route_roads = np.full((len(self.routes), max_roads), -1, dtype=np.int64)
        self.route_nroads = np.array([len(r.roads) for r in self.routes])
        self.route_final_lane = np.array([r.final_lane for r in self.routes])
        # position of each road inside each route (-1 = not on the route)
        self.route_road_pos = np.full((len(self.routes), len(road_keys)), -1, dtype=np.int64)
        for i, r in enumerate(self.routes):
            self.route_roads[i, : len(r.roads)] = r.roads
            for j, rd in enumerate(r.roads):
                if self.route_road_pos[i, rd] < 0:
                    self.route_road_pos[i, rd] = j

        allp = np.concatenate([self.hull_vertices.reshape(-1, 2), self.sidewalks.reshape(-1, 2)])
        self.bounds = np.concatenate([allp.min(0), allp.max(0)])
        self.centre = 0.5 * (self.bounds[:2] + self.bounds[2:])
        self.scale = 0.5 * float(np.max(self.bounds[2:] - self.bounds[:2]))

    def _solid_center_lines(self, data: dict) -> list[dict]:
        """The line boxes with every broken yellow centre line built solid, as MetaDrive builds a continuous line.

        A continuous line is boxes between the lane's left-edge points every 4 m and at its end
        (``PGBlock._construct_lane_line_in_block``, ``LANE_SEGMENT_LENGTH``); COIN's patched MetaDrive
        builds the bottleneck's neck centre line so (``BOTTLENECK_PARAMETER["solid_center_line"] = 1``).
        """
        broken = "ROAD_LINE_BROKEN_SINGLE_YELLOW"
        segs = [s for s in data["line_segments_physical"] if s["type"] != broken]
        box = next((s for s in data["line_segments_physical"] if s["type"] == broken), None)
        for i, lane in enumerate(data["lanes"]):
            if box is None or lane["line_types"][0] != "broken" or lane["line_colors"][0] != "yellow":
                continue
            s = np.array([*np.arange(0.0, self.length[i], 4.0), self.length[i]])
            pts = self.position(np.full(len(s), i), s, np.full(len(s), -self.width[i] / 2))
            segs += [{**box, "type": SOLID_LINE_TYPES[1], "p1": list(a), "p2": list(b)} for a, b in zip(pts[:-1], pts[1:])]
        return segs

    # ----------------------------------------------------------------- lane queries
    def position(self, lane: np.ndarray, s: np.ndarray, r: np.ndarray) -> np.ndarray:
        """World positions (N, 2) of lane-local coordinates (s, r) on lanes ``lane``."""
        lane = np.ascontiguousarray(lane, dtype=np.int64)
        s, r = (np.ascontiguousarray(np.broadcast_to(np.asarray(a, dtype=np.float64), lane.shape)) for a in (s, r))
        return _positions(self.lane_arrays, lane, s, r)

    def heading_at(self, lane: np.ndarray, s: np.ndarray) -> np.ndarray:
        """Lane heading (rad) at longitudinal positions ``s``."""
        lane = np.ascontiguousarray(lane, dtype=np.int64)
        s = np.ascontiguousarray(np.broadcast_to(np.asarray(s, dtype=np.float64), lane.shape))
        return _heading_at(self.unit, self.start_phase, self.direction, self.radius, self.is_circ, lane, s)

    def local_coordinates(self, lane: np.ndarray, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Lane-local (s, r) of world points ``pos`` (N, 2) on lanes ``lane`` (N,)."""
        lane = np.ascontiguousarray(lane, dtype=np.int64)
        return _local_coordinates(self.lane_rows, self.is_circ, lane, np.ascontiguousarray(pos, dtype=np.float64).reshape(len(lane), 2))

    def right_normal(self, lane: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """Unit vector pointing to the right of the lane's direction at ``pos``."""
        lane = np.ascontiguousarray(lane, dtype=np.int64)
        return _right_normals(self.lane_arrays, lane, np.ascontiguousarray(pos, dtype=np.float64).reshape(len(lane), 2))

    def hull_contains(self, pos: np.ndarray, margin: float = 0.05) -> np.ndarray:
        """(N, L) bool: point n lies in the on-lane region (convex hull) of lane l."""
        g = self.hull_grid
        pos = np.ascontiguousarray(pos, dtype=np.float64).reshape(-1, 2)
        return _hull_contains(g.table, g.origin, g.cell, g.shape, self.hull_normals, self.hull_offsets, self.hull_bbox, pos, float(margin))

    def successors(self) -> dict[int, list[int]]:
        """Physically continuing lanes: a lane's end meets the successor's start."""
        d = np.linalg.norm(self.end[:, None, :] - self.start[None, :, :], axis=2)
        h_end = self.heading_at(np.arange(self.num_lanes), self.length)
        h_start = self.heading_at(np.arange(self.num_lanes), np.zeros(self.num_lanes))
        same_heading = np.cos(h_end[:, None] - h_start[None, :]) > 0.99
        nxt = (d < 0.05) & same_heading
        return {i: list(np.nonzero(nxt[i])[0]) for i in range(self.num_lanes)}


@cache
def load_map(name: str, solid_center_line: bool = False) -> RoadMap:
    """The (cached, read-only) road map of a scenario; ``solid_center_line`` builds broken yellow centre lines solid."""
    return RoadMap(name, solid_center_line)
