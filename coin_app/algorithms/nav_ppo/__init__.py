"""Decentralized navigation-and-parking PPO (seed-2 paper): a long-range and a short-range policy on the arena."""
