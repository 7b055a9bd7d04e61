"""``scenarios``: every scenario, preset and ``--set`` key with its default (reads the algorithm registry: imports RLlib)."""

from __future__ import annotations

import argparse
from dataclasses import fields

from coin_app.algorithms import registry
from coin_app.sim.arena.config import ArenaConfig
from coin_app.sim.config import PRESETS, ScenarioConfig, make_config
from coin_app.sim.scenes import ARENA, SCENES, env_id


def cmd_scenarios(args: argparse.Namespace) -> int:
    """List the scenarios, presets and every config key with its default."""

    for name, s in SCENES.items():
        print(f"{name:<13} {s.default_vehicles:>3} agents  obs {make_config(name).obs_dim}  registered as {s.env_id}")
    print(f"presets: {', '.join(PRESETS)}")
    print("config keys (--set key=value):")
    cfg = ScenarioConfig()
    for f in fields(ScenarioConfig):
        if f.name not in ("scenario", "dynamics"):
            print(f"  {f.name:<20} {getattr(cfg, f.name)!r}")
    print("  dynamics             a dict of DynamicsConfig fields, e.g. --set \"dynamics={'max_speed_kmh': 60}\"")

    arena = ArenaConfig()
    arena_id = env_id(ARENA)
    print(f"arena          {arena.num_vehicles:>3} vehicles, {arena.num_obstacles} obstacles  obs {arena.obs_dim}  {arena_id} (nav_ppo)")
    print("arena keys (--set key=value):")
    for f in fields(ArenaConfig):
        if f.name != "reward":
            print(f"  {f.name:<20} {getattr(arena, f.name)!r}")
    print("  reward               a dict of RewardConfig fields (Eqs. 2-6), e.g. --set \"reward={'success_reward': 100}\"")
    for name, spec in registry.ALGORITHMS.items():
        print(f"\n{name} keys (--set key=value; {spec.description}; scenarios: {', '.join(spec.scenarios)}):")
        for key, (default, meaning) in spec.hyperparameters.items():
            print(f"  {key:<30} {default!r:<14} {meaning}")
    print("\nkeys of every algorithm (how it samples, where its learner runs):")
    for key, (default, meaning) in registry.COMMON_KEYS.items():
        print(f"  {key:<30} {default!r:<14} {meaning}")
    return 0
