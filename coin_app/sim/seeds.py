"""The three disjoint seed sets: training, validation (checkpoint selection, periodic evaluation) and test (reported results).

Training seeds are below ``MAX_TRAINING_SEED`` (refused otherwise), so with the small offsets
env runners add their envs are seeded below ``VALIDATION_SEED_BASE``; validation seeds are
``VALIDATION_SEED_BASE + k`` and test seeds ``TEST_SEED_BASE + k``. Never select on test seeds.
"""

from __future__ import annotations

VALIDATION_SEED_BASE = 100_000
TEST_SEED_BASE = 200_000
MAX_TRAINING_SEED = VALIDATION_SEED_BASE - 10_000  # env runners add small offsets to the trial seed


def check_training_seed(seed: int) -> int:
    """``seed`` if it is a valid training seed; otherwise a ValueError naming it and the allowed range."""
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < MAX_TRAINING_SEED:
        raise ValueError(
            f"bad seed {seed!r}; allowed: an integer in [0, {MAX_TRAINING_SEED}) (validation seeds start at {VALIDATION_SEED_BASE})"
        )
    return seed


def eval_test_seeds(n: int) -> list[int]:
    """The first ``n`` test seeds (the paper uses 20 per trained model)."""
    return [TEST_SEED_BASE + k for k in range(n)]


def validation_seeds(n: int) -> list[int]:
    """The first ``n`` validation seeds (periodic evaluation during training)."""
    return [VALIDATION_SEED_BASE + k for k in range(n)]
