"""A fixed agent order in the PPO family's acting and train batches, so that a seed gives one run in every process.

RLlib 2.60 keeps an episode's agent ids in sets, and its connectors lay out the acting batch
(which agent draws which exploration noise) and the train batch by iterating them: runs
followed the process's string hash seed (``PYTHONHASHSEED``). The batched env runner builds
``OrderedMultiAgentEpisode`` chunks and acts on all vehicles in one fixed order itself.
``FixedAgentOrder`` makes RLlib's episodes ordered ones (``coin_app/adapters/episodes.py``): as the
first env-to-module piece (``acting_order``, for RLlib's ``MultiAgentEnvRunner``; it runs on every
step, since RLlib's ``cut`` rebuilds episodes in set order) and as the learner connector's first
piece (``fix_agent_order``).
"""

from __future__ import annotations

from typing import Any

from ray.rllib.connectors.connector_v2 import ConnectorV2

from coin_app.adapters.episodes import order_agents


class FixedAgentOrder(ConnectorV2):
    """Connector piece (env-to-module or learner, first): every multi-agent episode iterates its agents in a fixed order."""

    def __call__(self, *, rl_module: Any, batch: dict[str, Any], episodes: Any, **kwargs: Any) -> dict[str, Any]:
        """Make each plain ``MultiAgentEpisode`` an ``OrderedMultiAgentEpisode`` (agents sorted by id); the batch unchanged."""
        order_agents(episodes)
        return batch


def acting_order(env: Any = None, spaces: Any = None, device: Any = None) -> FixedAgentOrder:
    """The ``env_to_module_connector`` of the PPO family's configs: ``FixedAgentOrder`` before RLlib's default pieces."""
    return FixedAgentOrder()


def fix_agent_order(learner: Any) -> None:
    """Put ``FixedAgentOrder`` first in a built learner's connector pipeline; a ValueError if the learner has none."""
    if learner._learner_connector is None:
        raise ValueError("a PPO learner without a learner connector; allowed: num_aggregator_actors_per_learner=0 (the default)")
    learner._learner_connector.prepend(FixedAgentOrder())
