"""A record of the driving rules' outputs on long seeded episodes, to check that a refactor of the rules changes nothing.

    python tests/data/rules_record.py     # rewrite tests/data/rules_record.npz with this checkout's simulator

Every scene on MetaDrive 0.4.3's roads (the bottleneck's broken centre line, as when the record was made), two envs
each, 8 vehicles, horizon 300, each vehicle's step limit 400 and the force stop at 2 x 300:
the heuristic driver, every third vehicle with seeded steering and pedal noise, so the episodes hold arrivals, crashes, off-road exits,
step limits, respawns and the force stop. Per acting vehicle and step the record keeps the reward, the four outcome
flags, terminated, truncated and the vehicle's step count; per env step the mean reward, ``episode_over`` and sums of
the observations and states (plain and absolute). ``tests/test_rules.py`` replays the episodes and compares every
event, id and count exactly, the floats to round-off (numpy's transcendental functions round the last bit otherwise on
other CPUs; a hash of the observations' bytes, kept before 2026-12, held only on the machine that wrote it).

The record holds this machine's floating-point results; rewrite it (and say why in the commit) only when the
simulator's dynamics or rules change on purpose. The first step's positions are kept as well, so that a failing
comparison tells a change of the dynamics from a change of the rules.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path[:1]:
    sys.path.insert(0, str(ROOT))

from coin_app.sim.config import make_config  # noqa: E402
from coin_app.sim.heuristic import HeuristicDriver  # noqa: E402
from coin_app.sim.scenes import DRIVING_SCENARIOS  # noqa: E402
from coin_app.sim.simulator import DrivingSimulator  # noqa: E402

RECORD = Path(__file__).with_name("rules_record.npz")
STEPS = 600  # the force stop ends the episodes at step 2 x horizon
SETTINGS = {"num_agents": 8, "horizon": 300, "max_agent_steps": 400, "force_stop_factor": 2, "solid_center_line": False}
NOISY = 3  # every third vehicle (by its number) drives with noisy steering and pedals
FLAGS = ("arrive_dest", "crash_vehicle", "out_of_road", "max_step", "terminated", "truncated")


def _sums(obs: np.ndarray, state: np.ndarray) -> np.ndarray:
    return np.array([obs.sum(), np.abs(obs).sum(), state.sum(), np.abs(state).sum()])


def episode(scenario: str, seed: int = 7) -> dict[str, np.ndarray]:
    """The arrays of one scene's episodes (two envs seeded ``seed``, ``seed + 1``) as the simulator gives them now."""
    sim = DrivingSimulator(make_config(scenario, **SETTINGS), num_envs=2)
    driver = HeuristicDriver(sim)
    rng = np.random.default_rng(seed)
    res = sim.reset(seed)
    rows: dict[str, list] = {k: [] for k in ("step", "slot", "agent", "reward", "episode_length", "flags")}
    per_step: dict[str, list] = {k: [] for k in ("global_reward", "episode_over", "sums", "spawned")}
    first_pos = None
    for t in range(STEPS):
        noise = rng.normal(0.0, 0.5, (sim.num_slots, 2)) * (sim.agent_num % NOISY == 0)[:, None]
        res = sim.step(driver.act_all() + noise)
        if first_pos is None:
            first_pos = sim.pos.copy()
        acted = np.nonzero(res.acted)[0]
        rows["step"].append(np.full(len(acted), t))
        rows["slot"].append(acted)
        rows["agent"].append(res.agent_num[acted])
        rows["reward"].append(res.reward[acted])
        rows["episode_length"].append(res.episode_length[acted])
        rows["flags"].append(np.stack([getattr(res, f)[acted] for f in FLAGS], 1))
        per_step["global_reward"].append(res.global_reward)
        per_step["episode_over"].append(res.episode_over)
        per_step["sums"].append(_sums(res.obs, res.state))
        per_step["spawned"].append(int(res.spawned.sum()))
        if res.episode_over.all():
            break
    out = {k: np.concatenate(v) for k, v in rows.items()}
    out.update({k: np.array(v) for k, v in per_step.items()})
    out["first_pos"] = first_pos
    return out


def record() -> dict[str, np.ndarray]:
    """Every scene's arrays, keyed ``scenario/name``."""
    return {f"{name}/{k}": v for name in DRIVING_SCENARIOS for k, v in episode(name).items()}


if __name__ == "__main__":
    arrays = record()
    np.savez_compressed(RECORD, **arrays)
    for name in DRIVING_SCENARIOS:
        flags = arrays[f"{name}/flags"].sum(0)
        print(name, dict(zip(FLAGS, flags.tolist())), "respawns", int(arrays[f"{name}/spawned"].sum()))
    print(f"wrote {RECORD} ({RECORD.stat().st_size} bytes)")
