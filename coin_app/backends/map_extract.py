"""Extract the native simulator's maps (``coin_app/sim/maps/<scene>.json``) from MetaDrive 0.4.3's multi-agent scenes.

Usage (needs the MetaDrive extra)::

    python -m coin_app.backends.map_extract                  # rewrite every scene's map in coin_app/sim/maps/
    python -m coin_app.backends.map_extract --check          # exit 1 if a committed map differs from MetaDrive's
    python -m coin_app.backends.map_extract --scenario bottleneck --out /tmp/maps

Each scene's MetaDrive env (``Scene.metadrive_class``) is built headless with its default config and
reset once with the spawn manager seeded 0. What MetaDrive builds is read, not recomputed: the road
network and every lane's geometry, the physical lane-line boxes as MetaDrive's blocks construct them
(recorded from ``BaseBlock._construct_lane_line_segment``), the sidewalk polygons, the spawn slots and
respawn places of its spawn manager, and the routes its navigation takes (breadth-first
``shortest_path`` to every destination its spawn manager can draw, or the bottleneck's fixed
``auto_assign_task``). A lane's on-lane region is the convex hull of its polygon (MetaDrive builds a
Bullet convex hull of it). Numbers are rounded to 6 decimals, and the JSON is written with
``indent=1``, so a rerun on the same MetaDrive gives the same bytes.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from coin_app.backends.metadrive import _import_metadrive, bottleneck_center_line
from coin_app.sim.road_map import MAP_DIR
from coin_app.sim.scenes import DRIVING_SCENARIOS, scene

DECIMALS = 6
ON_LANE_RULE = (
    "vehicle.on_lane = a vertical ray at the vehicle centre hits any lane body. Each lane body is a BulletConvexHullShape of "
    "lane.polygon (field 'polygon'; straight: rectangle |r|<=w/2, 0<=s<=length; circular: arc strip sampled every 1 m plus 1-m "
    "tangent extensions at both ends). Because it is a CONVEX HULL, a curved lane's localisation region also covers the area "
    "between the arc and its chord. 'localization_hull' stores that hull (CCW). Bullet margin adds ~0.04-0.05 m around it. "
    "out_of_road includes (not on_lane)."
)
COORDINATE_FRAME = (
    "MetaDrive world frame, right-handed, metres; x/y as returned by vehicle.position; headings in rad, CCW from +x. Lane local "
    "coords: longitudinal s along lane from its start; lateral r positive to the RIGHT of the driving direction "
    "(StraightLane.direction_lateral=(dy,-dx)). Lane index 0 is the left-most lane of a road (next to the centre line); higher "
    "indices are further right. line_types/line_colors are [left(r=-w/2), right(r=+w/2)]."
)
SPAWN_RULE = (
    "SpawnManager: for each spawn road r, for each lane_idx in range(map_config.lane_num), for j in range(num_slots) with "
    "num_slots=floor((exit_length-10)/8)=6: slot at longitude 4+8*j, lateral 0 on lane r.lane_index(lane_idx). At env.reset() "
    "num_agents slots are drawn without replacement (spawn_manager np_random, unseeded unless force_seed_spawn_manager) and each "
    "is jittered: longitude += U(-1,1) [(8-MAX_LENGTH 10)/2 -> bounds (1,-1)], lateral += U(-0.25,0.25) [(3-2.5)/2]. Respawn "
    "places are only the j==0 slots (longitude exactly 4, lateral 0, no jitter because random_traffic=False). A respawn place is "
    "available if a 8 m (along lane heading) x 3 m (lateral) x 2 m box centred at the spawn point, swept from z=10 to z=-1, hits "
    "no body in CollisionGroup.Vehicle (dynamic world; includes dying/static vehicles). Each place used at most once per env step."
)
DRAWN_DESTINATION_RULE = (
    "intersection/roundabout: update_destination_for picks end_road = -choice(spawn_roads) uniformly (spawn_manager np_random; "
    "U-turn back to own spawn road is allowed since lane_num=2) and sets destination = end_road.end_node. Route = BFS shortest "
    "node path (road_network.shortest_path) from the spawn lane's start node to destination. final_lane = last (right-most) lane "
    "of the final road."
)
FIXED_DESTINATION_RULE = (
    "bottleneck: no destination set (base SpawnManager.update_destination_for). NodeNetworkNavigation.auto_assign_task: if spawn "
    "road is negative -> first block (FirstPGBlock) socket, destination = socket.negative_road.end_node ('->>'); else last block "
    "(Split) socket, destination = socket.positive_road.end_node. Each block has exactly one socket so it is deterministic."
)
CONFIG_KEYS = (
    "num_agents", "map_config", "spawn_roads", "horizon", "delay_done", "allow_respawn", "crash_done", "out_of_road_done",
    "decision_repeat", "physics_world_step_size", "random_traffic", "success_reward", "out_of_road_penalty",
    "crash_vehicle_penalty", "crash_object_penalty", "driving_reward", "speed_reward", "use_lateral_reward",
)  # fmt: skip
LIDAR_KEYS = ("num_lasers", "distance", "num_others", "gaussian_noise", "dropout_prob", "add_others_navi")
DETECTOR_KEYS = ("num_lasers", "distance", "gaussian_noise", "dropout_prob")


def _round(value: Any) -> Any:
    """Floats rounded to ``DECIMALS`` (numpy scalars and arrays as plain lists), everything else as it is."""
    if isinstance(value, dict):
        return {k: _round(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_round(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return round(float(value), DECIMALS)
    return value


@contextlib.contextmanager
def _recorded_line_segments() -> Iterator[list[dict[str, Any]]]:
    """Every lane-line box MetaDrive's blocks build while the context is open, as its Bullet body placed it.

    A box is read back from its body (float32: centre, heading, half extents), so the end points are those
    of the box MetaDrive collides with.
    """
    from metadrive.component.block.base_block import BaseBlock  # optional: the MetaDrive extra
    from metadrive.constants import PGLineColor, PGLineType  # optional: the MetaDrive extra
    from metadrive.type import MetaDriveType  # optional: the MetaDrive extra

    built: list[dict[str, Any]] = []
    original = BaseBlock._construct_lane_line_segment

    def record(self: Any, start_point: Any, end_point: Any, line_color: Any, line_type: Any) -> list:
        nodes = original(self, start_point, end_point, line_color, line_type)
        if nodes:  # what MetaDrive built (it skips empty segments and those off the terrain), named as it names them
            white = line_color == PGLineColor.GREY
            if PGLineType.prohibit(line_type):
                kind = MetaDriveType.LINE_SOLID_SINGLE_WHITE if white else MetaDriveType.LINE_SOLID_SINGLE_YELLOW
            else:
                kind = MetaDriveType.LINE_BROKEN_SINGLE_WHITE if white else MetaDriveType.LINE_BROKEN_SINGLE_YELLOW
            body = nodes[0]
            pos, heading = body.getPos(), math.radians(body.getH())
            shape = body.node().getShape(0)
            extents = shape.getHalfExtentsWithMargin()  # the box as built: (length / 2, line width / 4, ghost height)
            along = np.array([math.cos(heading), math.sin(heading)]) * extents.x
            centre = np.array([pos.x, pos.y])
            built.append(
                {
                    "type": kind,
                    "p1": centre - along,
                    "p2": centre + along,
                    "half_width": extents.y,
                    "z_center": pos.z,
                    "half_height": extents.z,
                }
            )
        return nodes

    BaseBlock._construct_lane_line_segment = record
    try:
        yield built
    finally:
        BaseBlock._construct_lane_line_segment = original


def _line_name(line_type: Any) -> str:
    """PGLineType's constant name in lower case: none, broken, continuous, side, guardrail."""
    from metadrive.constants import PGLineType  # optional: the MetaDrive extra

    return next(n.lower() for n in ("NONE", "BROKEN", "CONTINUOUS", "SIDE", "GUARDRAIL") if getattr(PGLineType, n) == line_type)


def _color_name(color: Any) -> str:
    from metadrive.constants import PGLineColor  # optional: the MetaDrive extra

    return "white" if color == PGLineColor.GREY else "yellow"


def _lane_record(lane: Any, key: tuple[str, str, int], num_lanes: int, block: str, built: list[bool]) -> dict[str, Any]:
    """One lane as MetaDrive built it (see the JSON conventions in docs/reference/scenarios.md)."""
    from metadrive.component.lane.circular_lane import CircularLane  # optional: the MetaDrive extra
    from metadrive.component.road_network import Road  # optional: the MetaDrive extra
    from scipy.spatial import ConvexHull  # optional: a dependency of the MetaDrive extra

    length = float(lane.length)
    rec: dict[str, Any] = {
        "key": "|".join(str(k) for k in key),
        "from_node": key[0],
        "to_node": key[1],
        "index": key[2],
        "road_num_lanes": num_lanes,
        "block": block,
        "negative_road": Road(key[0], key[1]).is_negative_road(),
        "width": lane.width,
        "length": length,
        "speed_limit_km_h": float(lane.speed_limit),
        "surface_type": str(lane.metadrive_type),
        "line_types": [_line_name(t) for t in lane.line_types],
        "line_colors": [_color_name(c) for c in lane.line_colors],
        "lines_physically_built": built,
        "heading_start": lane.heading_theta_at(0.0),
        "heading_end": lane.heading_theta_at(length),
        "start_point": lane.position(0.0, 0.0),
        "end_point": lane.position(length, 0.0),
    }
    if isinstance(lane, CircularLane):
        rec.update(
            type="circular",
            center=lane.center,
            radius=float(lane.radius),
            start_phase=lane.start_phase,
            end_phase=lane.end_phase,
            angle=lane.angle,
            clockwise=lane.is_clockwise(),
            direction=int(lane.direction),
        )
    else:
        rec.update(type="straight", start=np.asarray(lane.start, float), end=np.asarray(lane.end, float))
    s = [*np.arange(0.0, length, 1.0), length]
    rec["centerline_s_x_y_heading"] = [[si, *lane.position(si, 0.0), lane.heading_theta_at(si)] for si in s]
    polygon = np.asarray(lane.polygon, dtype=float)[:, :2]
    rec["polygon"] = polygon
    rec["localization_hull"] = polygon[ConvexHull(polygon).vertices]
    return rec


def _config(env: Any) -> dict[str, Any]:
    cfg = env.config
    out = {k: cfg[k] for k in CONFIG_KEYS}
    out["map_config"] = {**cfg["map_config"], "start_position": str(list(cfg["map_config"]["start_position"]))}
    out["spawn_roads"] = [[r.start_node, r.end_node] for r in cfg["spawn_roads"]]
    vehicle = cfg["vehicle_config"]
    out["lidar"] = {k: vehicle["lidar"][k] for k in LIDAR_KEYS}
    out["side_detector"] = {k: vehicle["side_detector"][k] for k in DETECTOR_KEYS}
    out["lane_line_detector"] = {k: vehicle["lane_line_detector"][k] for k in DETECTOR_KEYS}
    out["vehicle_model"] = vehicle["vehicle_model"]
    out["cross_yellow_line_done"] = cfg.get("cross_yellow_line_done")
    out["observation_dim"] = int(env.observation_space[next(iter(env.observation_space.keys()))].shape[0])
    return out


def _slot(place: Any, road_network: Any, respawn: bool | None) -> dict[str, Any]:
    c = place["config"]
    lane_index = c["spawn_lane_index"]
    lane = road_network.get_lane(lane_index)
    out = {
        "identifier": place["identifier"],
        "lane": list(lane_index),
        "longitude": float(c["spawn_longitude"]),
        "lateral": float(c["spawn_lateral"]),
        "position": lane.position(c["spawn_longitude"], c["spawn_lateral"]),
        "heading": lane.heading_theta_at(c["spawn_longitude"]),
    }
    if respawn is not None:
        out["is_respawn_place"] = respawn
    return out


def _routes(env: Any, destinations: list[str] | None) -> list[dict[str, Any]]:
    """Every spawn lane's route to each destination it can draw (or to its fixed one)."""
    from metadrive.component.navigation_module.node_network_navigation import NodeNetworkNavigation  # optional: the extra

    m = env.engine.current_map
    network = m.road_network
    routes = []
    for road in env.config["spawn_roads"]:
        for lane_idx in range(env.config["map_config"]["lane_num"]):
            lane_index = road.lane_index(lane_idx)
            for dest in destinations or [NodeNetworkNavigation.auto_assign_task(m, lane_index)]:
                cps = network.shortest_path(lane_index, dest)  # as NodeNetworkNavigation.set_route
                lanes = network.graph[cps[-2]][cps[-1]]
                routes.append(
                    {
                        "spawn_lane": list(lane_index),
                        "destination_node": dest,
                        "checkpoints": list(cps),
                        "final_road": [cps[-2], cps[-1]],
                        "final_lane": [cps[-2], cps[-1], len(lanes) - 1],
                        "final_road_num_lanes": len(lanes),
                        "total_length_lane0": sum(network.graph[a][b][0].length for a, b in zip(cps[:-1], cps[1:])),
                    }
                )
    return routes


def _initial_agents(env: Any) -> dict[str, Any]:
    out = {}
    for aid, v in env.agents.items():
        c = v.config
        out[aid] = {
            "spawn_lane": list(c["spawn_lane_index"]),
            "spawn_longitude": c["spawn_longitude"],
            "spawn_lateral": c["spawn_lateral"],
            "position": v.position,
            "heading": v.heading_theta,
            "destination": c["destination"],
            "checkpoints": list(v.navigation.checkpoints),
            "final_lane": list(v.navigation.final_lane.index),
        }
    return out


def extract(name: str, solid_center_line: bool = False) -> dict[str, Any]:
    """The map of scene ``name`` as MetaDrive 0.4.3 builds it (the JSON's structure, rounded); optionally COIN's bottleneck."""
    from metadrive.manager.spawn_manager import SpawnManager  # optional: the MetaDrive extra
    from metadrive.version import VERSION  # optional: the MetaDrive extra

    marl = _import_metadrive("skip")
    bottleneck_center_line(solid_center_line)
    env_class = getattr(marl, scene(name).metadrive_class)
    with _recorded_line_segments() as segments:
        env = env_class(
            {
                "use_render": False,
                "log_level": logging.CRITICAL,
                "start_seed": 0,
                "num_scenarios": 1,
                "force_seed_spawn_manager": True,
            }
        )
        try:
            env.reset(seed=0)
            out = _collect(name, env, segments, VERSION, SpawnManager)
        finally:
            env.close()
    return _round(out)


def _collect(name: str, env: Any, segments: list, version: str, base_spawn_manager: type) -> dict[str, Any]:
    m = env.engine.current_map
    network = m.road_network
    block_of = {(a, b): blk.ID for blk in m.blocks for a, to in blk.block_network.graph.items() for b in to}
    lanes = []
    for a, to in network.graph.items():
        for b, road_lanes in to.items():
            for i, lane in enumerate(road_lanes):
                built = [True, True] if i == len(road_lanes) - 1 else [True, False]  # PGBlock.create_in_world
                lanes.append(_lane_record(lane, (a, b, i), len(road_lanes), block_of[(a, b)], built))
    sidewalks = [
        {"lane": key, "type": sw["type"], "polygon": sw["polygon"], "height": sw["height"]}
        for blk in m.blocks
        for key, sw in blk.sidewalks.items()
    ]
    crosswalks = [{"lane": key, "type": cw["type"], "polygon": cw["polygon"]} for blk in m.blocks for key, cw in blk.crosswalks.items()]
    manager = env.engine.spawn_manager
    respawn_ids = set(manager.safe_spawn_places)
    drawn = type(manager).update_destination_for is not base_spawn_manager.update_destination_for
    destinations = [(-r).end_node for r in env.config["spawn_roads"]] if drawn else None
    cfg = env.config
    return {
        "scenario": name,
        "on_lane_rule": ON_LANE_RULE,
        "env_class": scene(name).metadrive_class,
        "metadrive_version": version,
        "coordinate_frame": COORDINATE_FRAME,
        "config": _config(env),
        "graph": {a: list(to) for a, to in network.graph.items()},
        "lanes": lanes,
        "line_segments_physical": segments,
        "sidewalks": sidewalks,
        "crosswalks": crosswalks,
        "spawn": {
            "rule": SPAWN_RULE,
            "RESPAWN_REGION_LONGITUDE": manager.RESPAWN_REGION_LONGITUDE,
            "RESPAWN_REGION_LATERAL": manager.RESPAWN_REGION_LATERAL,
            "MAX_VEHICLE_LENGTH": manager.MAX_VEHICLE_LENGTH,
            "MAX_VEHICLE_WIDTH": manager.MAX_VEHICLE_WIDTH,
            "num_slots_per_lane": int(manager.exit_length // manager.RESPAWN_REGION_LONGITUDE),
            "max_capacity": manager.max_capacity(cfg["spawn_roads"], cfg["map_config"]["exit_length"], cfg["map_config"]["lane_num"]),
            "slots": [_slot(p, network, p["identifier"] in respawn_ids) for p in manager.available_agent_configs],
            "respawn_places": [_slot(p, network, None) for p in manager.safe_spawn_places.values()],
            "initial_agents_example_seed0": _initial_agents(env),
        },
        "destinations": {
            "destination_nodes": destinations,
            "rule": DRAWN_DESTINATION_RULE if drawn else FIXED_DESTINATION_RULE,
            "routes": _routes(env, destinations),
        },
    }


def map_text(data: dict[str, Any]) -> str:
    """A map as the committed file's text."""
    return json.dumps(data, indent=1)


def main(argv: list[str] | None = None) -> int:
    """Write (or ``--check``) the maps of the named scenes; one process per scene (MetaDrive runs one engine per process)."""
    parser = argparse.ArgumentParser(prog="python -m coin_app.backends.map_extract", description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", nargs="+", choices=DRIVING_SCENARIOS, default=list(DRIVING_SCENARIOS))
    parser.add_argument("--out", type=Path, default=MAP_DIR, help="folder of the map files (default: the package's maps)")
    parser.add_argument("--check", action="store_true", help="compare with the files in --out instead of writing them")
    parser.add_argument("--solid-center-line", action="store_true", help="COIN's bottleneck (solid neck centre line), not 0.4.3's")
    args = parser.parse_args(argv)
    stale = []
    for name in args.scenario:
        text = map_text(extract(name, args.solid_center_line))
        path = args.out / scene(name).map_file
        if args.check:
            if not path.is_file() or path.read_text() != text:
                stale.append(str(path))
        else:
            args.out.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
            print(f"wrote {path}")
    if stale:
        print(f"differ from MetaDrive {', '.join(stale)}; rerun without --check to rewrite them", file=sys.stderr)
    return 1 if stale else 0


if __name__ == "__main__":
    raise SystemExit(main())
