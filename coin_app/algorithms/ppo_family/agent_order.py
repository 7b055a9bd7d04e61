"""A fixed agent order in the PPO learners' train batches, so that a seed gives one run in every process.

RLlib 2.60's ``MultiAgentEpisode.agent_ids`` is a ``set`` of strings, and its learner connectors
lay out the train batch by iterating it: the rows' order (and through the minibatches, the run)
followed the process's string hash seed (``PYTHONHASHSEED``). The batched env runner builds
``OrderedMultiAgentEpisode`` chunks, whose agents iterate in the order they were added.
``FixedAgentOrder``, the learner connector's first piece, gives episodes from RLlib's
``MultiAgentEnvRunner`` the same property: it sorts their agents by id (``agent2`` before
``agent10``; RLlib's ``cut`` re-inserts them in set order) and makes them ordered episodes.
"""

from __future__ import annotations

from typing import Any

from ray.rllib.connectors.connector_v2 import ConnectorV2
from ray.rllib.env.multi_agent_episode import MultiAgentEpisode

from coin_app.adapters.batched_runner import OrderedMultiAgentEpisode


def agent_sort_key(agent_id: Any) -> tuple[int, str]:
    """Sort key of an agent id: shorter ids first, then by text (``agent2`` < ``agent10``)."""
    text = str(agent_id)
    return len(text), text


class FixedAgentOrder(ConnectorV2):
    """Learner connector (first piece): every multi-agent episode iterates its agents in a fixed order."""

    def __call__(self, *, rl_module: Any, batch: dict[str, Any], episodes: Any, **kwargs: Any) -> dict[str, Any]:
        """Sort the agents of each episode not already ordered and make it an ``OrderedMultiAgentEpisode``."""
        for episode in episodes:
            if isinstance(episode, MultiAgentEpisode) and not isinstance(episode, OrderedMultiAgentEpisode):
                episode.agent_episodes = dict(sorted(episode.agent_episodes.items(), key=lambda kv: agent_sort_key(kv[0])))
                episode.__class__ = OrderedMultiAgentEpisode  # same fields; only agent_ids differs
        return batch


def fix_agent_order(learner: Any) -> None:
    """Put ``FixedAgentOrder`` first in a built learner's connector pipeline (no-op without one)."""
    if learner._learner_connector is not None:
        learner._learner_connector.prepend(FixedAgentOrder())
