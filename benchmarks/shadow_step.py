"""Shadow steps: every step of a MetaDrive episode, repeated by the native simulator from MetaDrive's own state.

Usage (needs the MetaDrive extra and the COIN authors' actors, see ``python -m coin_app evaluate-reference --help``)::

    python benchmarks/shadow_step.py --actors DIR [--scene intersection] [--actor-seed 1000] [--seed 1000] [--steps 1000]

The authors' actor drives one MetaDrive episode of the reference protocol (``evaluate-reference``'s scenario and
episode seed). Before every step, every vehicle MetaDrive holds — active ones with their chassis state, route, route
progress and step count, wrecks with their countdown — is put into a native simulator; both simulators then take the
step with the same actions (the actor's, on MetaDrive's observations). Closed-loop episodes of the two simulators part
within seconds (the traffic is chaotic), so comparing whole episodes says little about where they differ; one step
from one state says it exactly. Printed at the end:

* poses after the step: position, heading and speed error over the vehicles active before and after it in both;
* outcomes: per flag (arrival, crash, off-road, step limit), how often MetaDrive and the native step disagree, and
  each disagreement (step, agent, speed, what each said);
* respawns: vehicles spawned by the step in each (the places are drawn by different generators, the count should agree);
* observations at MetaDrive's poses before the step: ego and navigation error (per column), lidar error, the beams
  off by more than 0.2 sorted by cause (a vehicle the last step spawned or retired, a grazed outline), and how far
  the actor's action on the native observation is from its action on MetaDrive's;
* each simulator's own observations after the step: the lidar beams off by more than 0.2.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from coin_app.backends.shadow import FLAGS, shadow_episode
from coin_app.evaluation.reference import reference_config
from coin_app.inference.coin_actors import actors_root, find_coin_actors, load_coin_actor


def summary(out: dict[str, Any]) -> None:
    """Print the comparisons (module doc)."""
    pos, hd, sp = (np.array(out[k]) for k in ("pos_err", "heading_err", "speed_err"))
    q = [50, 99, 100]
    print(f"{out['steps']} steps shadowed, {len(pos)} vehicle steps active in both before and after")
    print(f"  position error (m) median / p99 / max: {' / '.join(f'{v:.4f}' for v in np.percentile(pos, q))}")
    print(f"  heading error (deg): {' / '.join(f'{v:.4f}' for v in np.degrees(np.percentile(hd, q)))}")
    print(f"  speed error (km/h): {' / '.join(f'{v:.4f}' for v in np.percentile(sp, q))}")
    for flag in FLAGS:
        a, b = np.array(out[f"{flag}_md"]), np.array(out[f"{flag}_native"])
        print(f"  {flag:<13} MetaDrive {int(a.sum()):4d}, native {int(b.sum()):4d}, both {int((a & b).sum()):4d}")
    for t, aid, flag, a, b, v in out["events"]:
        print(f"    step {t:4d} {aid:<9} {flag:<13} MetaDrive {a!s:<5} native {b!s:<5} at {v:5.1f} km/h")
    smd, snat = np.array(out["spawned_md"]), np.array(out["spawned_native"])
    print(f"  respawns: MetaDrive {int(smd.sum())}, native {int(snat.sum())}, steps where the counts differ: {int((smd != snat).sum())}")
    for t, md_new, nat_new, live in out["spawn_events"]:
        print(f"    step {t:4d}: MetaDrive spawned at {md_new}, native at {nat_new} (MetaDrive active + dying after: {live})")
    ego, lid, act = (np.array(out[k]) for k in ("ego_err", "lidar_err", "action_err"))
    flips = np.array(out["lidar_flips"]).sum() / len(act)
    exact = np.array(out["flip_exact"], bool).reshape(-1, 2)
    print(
        f"  of the {len(exact)} beams off by more than 0.2, exact ray-rectangle geometry (MetaDrive's pose against the others' "
        "chassis) agrees with the "
        f"native beam on {int(exact[:, 0].sum())} and with MetaDrive's on {int(exact[:, 1].sum())}"
    )
    detail = np.array(out["flip_detail"], float).reshape(-1, 7)
    for name, rows in (("MetaDrive's beam longer", detail[:, 1] > detail[:, 0]), ("MetaDrive's beam shorter", detail[:, 1] < detail[:, 0])):
        d = detail[rows]
        if len(d):
            near = np.abs(d[:, 3]) < 0.05
            print(
                f"    {name}: {len(d)}; the nearer hit's distance from the nearest box outline median {np.median(d[:, 2]):.3f} m; "
                f"the beam's clearance with that box (chord if it hits, minus the miss) median {np.median(d[:, 3]):+.3f} m, "
                f"within 5 cm of grazing {int(near.sum())}; the box a vehicle spawned by the last step {int(d[:, 4].sum())}; "
                f"MetaDrive's hit within 0.3 m of a vehicle the last step retired {int((d[:, 5] < 0.3).sum())}; "
                f"seen by a vehicle spawned by the last step {int(d[:, 6].sum())}"
            )
    print(
        f"  observations: ego and navigation max error {ego.max():.4f}; lidar mean error per step median {np.median(lid):.4f}, "
        f"max {lid.max():.4f}; beams off by more than 0.2 (a grazed box seen by one simulator only): {flips:.3f} per vehicle step"
    )
    sf, sb = np.sum(out["step_lidar_flips"]), np.sum(out["step_lidar_beams"])
    print(
        f"  the step's own observations of the vehicles that acted (each simulator's poses after the step): {sf} of {sb} "
        f"lidar beams off by more than 0.2 ({sf / max(sb, 1) * 72:.3f} per vehicle step)"
    )
    cols = np.sum(out["ego_columns_off"], 0)
    print(
        "  ego and navigation columns off by more than 0.01 (vehicle steps): "
        + (", ".join(f"column {c}: {int(cols[c])}" for c in np.nonzero(cols)[0]) or "none")
    )
    for t, aid, c, a, b in out["ego_events"][:20]:
        print(f"    step {t:4d} {aid:<9} column {c:2d}: native {a:.4f}, MetaDrive {b:.4f}")
    print(
        f"  the actor's action on the native observation against MetaDrive's, per vehicle step: median {np.median(act):.4f}, "
        f"p90 {np.percentile(act, 90):.4f}, p99 {np.percentile(act, 99):.4f}, max {act.max():.4f}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--actors", default=None, help="the authors' actors (default: $COIN_OFFICIAL_ACTORS)")
    ap.add_argument("--scene", default="intersection", choices=("intersection", "roundabout", "bottleneck"))
    ap.add_argument("--actor-seed", type=int, default=1000, help="training seed of the actor")
    ap.add_argument("--seed", type=int, default=1000, help="episode seed (the reference protocol's: 1000 + 100 i)")
    ap.add_argument("--steps", type=int, default=1000, help="steps to shadow (the episode's horizon: 1000)")
    args = ap.parse_args()
    policy = load_coin_actor(find_coin_actors(actors_root(args.actors), args.scene)[args.actor_seed])
    start = time.perf_counter()
    with threadpool_limits(limits=1, user_api="blas"):
        out = shadow_episode(reference_config(args.scene, "metadrive"), policy, args.seed, args.steps)
    summary(out)
    print(f"wall {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
