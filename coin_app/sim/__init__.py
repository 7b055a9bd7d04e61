"""The native simulator core: scenario config, vectorized vehicle simulation, the dict-of-agents env and the arena.

Nothing here imports Ray; every layer above (backends, adapters, algorithms) builds on it.
"""
