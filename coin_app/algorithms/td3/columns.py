"""Column names of a TD3-family transition: the replay buffer's sample keys, the learner's batch keys.

One row is one ego agent i at env step t (COIN §4.2, Eqs. 7-12). The ego's columns use RLlib's
``Columns`` values (``Columns.NEXT_OBS == "new_obs"``; ``tests/test_cig_td3_replay.py`` checks they
agree), so this module stays free of Ray. ``TransitionBatch`` fields carry the same names.
"""

from __future__ import annotations

# the ego's transition (RLlib's Columns values)
OBS = "obs"  # o_t, (B, O) float32
ACTIONS = "actions"  # a_t, (B, A) float32
REWARDS = "rewards"  # r_t, (B,) float32
TERMINATEDS = "terminateds"  # (B,) bool
TRUNCATEDS = "truncateds"  # (B,) bool
NEXT_OBS = "new_obs"  # o_{t+1}, (B, O) float32

# the ego's local state and the global reward (COIN Eqs. 9-11)
STATE = "state"  # s_t, (B, S) float32
NEXT_STATE = "new_state"  # s_{t+1}, (B, S) float32
GLOBAL_REWARDS = "global_rewards"  # r^G of env step t (the info of o_{t+1}), (B,) float32

# the other agents that acted at env step t, padded to max_others N
OTHERS_STATE = "others_state"  # s_{-i}, (B, N, S) float32, zero where masked
OTHERS_ACTIONS = "others_actions"  # a_{-i}, (B, N, A) float32, zero where masked
OTHERS_MASK = "others_mask"  # (B, N) bool
OTHERS_REWARDS = "others_rewards"  # r_{-i} of env step t, (B, N) float32, zero where masked (TraCo's domain reward)

# every other agent with an observation at env step t+1, padded to N
NEXT_OTHERS_STATE = "next_others_state"  # s'_{-i}, (B, N, S) float32
NEXT_OTHERS_OBS = "next_others_obs"  # o'_{-i}, (B, N, O) float32
NEXT_OTHERS_MASK = "next_others_mask"  # (B, N) bool

# where the transition comes from
ENV_STEP = "env_step"  # env step t of o_t, (B,) int64
EPISODE = "episode"  # episode key, (B,) int64 (transitions.episode_key)
AGENT = "agent"  # agent key, (B,) int64 (transitions.agent_key)

# what the replay's sample carries to look up the global columns (the learner connector's input, ``connector.py``):
# ring rows of the replay's joint records, int32, -1 where the other agent is masked out
OTHERS_ROWS = "others_rows"  # (B, N) observation-pool row of each other agent acting at t (its state)
OTHERS_TRANSITIONS = "others_transitions"  # (B, N) transition slot of each other agent acting at t (its action, reward)
NEXT_OTHERS_ROWS = "next_others_rows"  # (B, N) observation-pool row of each other agent at t+1 (its state, observation)
TRANSITION = "transition"  # (B,) the ego's transition slot (the global reward of its env step)

EGO = (OBS, STATE, ACTIONS, REWARDS, GLOBAL_REWARDS, TERMINATEDS, TRUNCATEDS, NEXT_OBS, NEXT_STATE)
OTHERS = (OTHERS_STATE, OTHERS_ACTIONS, OTHERS_MASK, OTHERS_REWARDS, NEXT_OTHERS_STATE, NEXT_OTHERS_OBS, NEXT_OTHERS_MASK)
ORIGIN = (ENV_STEP, EPISODE, AGENT)
LOOKUP = (OTHERS_ROWS, OTHERS_TRANSITIONS, NEXT_OTHERS_ROWS, TRANSITION)
SAMPLED = tuple(c for c in EGO if c != GLOBAL_REWARDS) + ORIGIN + LOOKUP  # the replay's sample
GLOBAL = (GLOBAL_REWARDS, *OTHERS)  # what the learner connector injects
