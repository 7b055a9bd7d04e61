"""Multi-agent episodes whose agents iterate in a fixed order, so that a seed gives one run in every process.

RLlib 2.60's ``MultiAgentEpisode.agent_ids`` and ``get_agents_that_stepped`` are ``set``\\ s of
strings; its connectors build the acting batch and the train batch by iterating them, so rows
(and which agent draws which exploration noise) followed the process's string hash seed
(``PYTHONHASHSEED``). ``OrderedMultiAgentEpisode`` iterates its agents in insertion order; the
batched env runner builds its chunks as such, and ``order_agents`` turns RLlib's episodes into
them with their agents sorted by id.
"""

from __future__ import annotations

from collections.abc import KeysView
from typing import Any

from ray.rllib.env.multi_agent_episode import MultiAgentEpisode


def agent_sort_key(agent_id: Any) -> tuple[int, str]:
    """Sort key of an agent id: shorter ids first, then by text (``agent2`` < ``agent10``)."""
    text = str(agent_id)
    return len(text), text


class AgentIds(KeysView):
    """A set-like, insertion-ordered view of agent ids; ``discard`` is a no-op (RLlib calls it after removing the agent)."""

    def discard(self, agent_id: Any) -> None:
        """Nothing to do: the view follows the episode's ``agent_episodes``, from which RLlib has removed the agent."""


class OrderedMultiAgentEpisode(MultiAgentEpisode):
    """A ``MultiAgentEpisode`` whose agent-id sets iterate in a fixed order (insertion order; stepped agents sorted by id)."""

    __slots__ = ()  # the same layout as RLlib's episode, so that one can become this class in place

    @property
    def agent_ids(self) -> AgentIds:  # type: ignore[override]
        """The episode's agent ids, in insertion order (set-like)."""
        return AgentIds(self.agent_episodes)

    def get_agents_that_stepped(self) -> AgentIds:  # type: ignore[override]
        """The agents with an observation at the last env step, sorted by id (set-like)."""
        return AgentIds(dict.fromkeys(sorted(self.get_observations(-1), key=agent_sort_key)))

    def get_agents_to_act(self) -> AgentIds:  # type: ignore[override]
        """The stepped agents whose episodes are not done, sorted by id (set-like)."""
        return AgentIds({a: None for a in self.get_agents_that_stepped() if not self.agent_episodes[a].is_done})


def order_agents(episodes: Any) -> None:
    """Make every plain ``MultiAgentEpisode`` of ``episodes`` an ``OrderedMultiAgentEpisode``, its agents sorted by id, in place."""
    for episode in episodes:
        if isinstance(episode, MultiAgentEpisode) and not isinstance(episode, OrderedMultiAgentEpisode):
            episode.agent_episodes = dict(sorted(episode.agent_episodes.items(), key=lambda kv: agent_sort_key(kv[0])))
            episode.__class__ = OrderedMultiAgentEpisode
