"""The arena: decentralized navigation and parking of many vehicles among static obstacles (seed-2 paper)."""
