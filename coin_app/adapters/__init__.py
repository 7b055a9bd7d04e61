"""Adapters of the dict-of-agents env to other APIs: RLlib's ``MultiAgentEnv`` and PettingZoo's parallel API."""
