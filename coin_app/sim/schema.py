"""The data contract between the simulator and everything above it: per-agent info keys and dimensions.

Every backend (native, MetaDrive, arena) writes these info keys; the adapters, the
centralized-critic connector, the PPO-family critic inputs and the evaluation metrics read
them by these names only.
"""

from __future__ import annotations

ACT_DIM = 2  # [steer, throttle_brake], each in [-1, 1]
STATE_DIM = 10  # the local state s_i of COIN §4: position, velocity, heading, two navigation checkpoints

# per-agent info keys of a driving step
ARRIVE_DEST = "arrive_dest"  # reached its destination (terminated)
CRASH_VEHICLE = "crash_vehicle"  # collided with another vehicle (terminated)
OUT_OF_ROAD = "out_of_road"  # left the drivable area (terminated)
MAX_STEP = "max_step"  # hit its own step limit or the env's force stop (truncated)
STEP_REWARD = "step_reward"  # reward of this step
EPISODE_LENGTH = "episode_length"  # the vehicle's own step count so far
EPISODE_REWARD = "episode_reward"  # the vehicle's return so far
STATE = "state"  # the STATE_DIM local state (centralized critics read it)
ENV_STEP = "env_step"  # the env step the info belongs to (aligns agents of one joint step)
GLOBAL_REWARD = "global_reward"  # mean reward of the agents that acted in this env step

# arena (navigation and parking) outcome keys
SUCCESS = "success"  # parked at the target
COLLIDED = "collided"  # hit a vehicle or an obstacle

DONE_FLAGS = (ARRIVE_DEST, CRASH_VEHICLE, OUT_OF_ROAD, MAX_STEP)  # any of these ends a driving vehicle
