"""Validation-seed selection's rule: the highest validation success wins, a tie goes to the later checkpoint."""

import math

import pytest

from coin_app.evaluation.selection import best_index, select_checkpoints


@pytest.mark.parametrize(
    ("successes", "expected"),
    [
        ([0.2, 0.5, 0.5, 0.1], 2),  # the later of two equal bests
        ([0.9, 0.5, 0.7], 0),  # an early best is kept
        ([0.0, 0.0, 0.0], 2),  # all equal: the final checkpoint
        ([math.nan, 0.3, math.nan], 1),  # a checkpoint that could not be evaluated never wins
        ([math.nan, math.nan], 1),
        ([0.4], 0),
    ],
)
def test_best_index_takes_the_highest_success_and_the_later_of_ties(successes, expected):
    assert best_index(successes) == expected


def test_bad_selection_input_is_refused_by_name():
    with pytest.raises(ValueError, match="no checkpoints to select from"):
        best_index([])
    with pytest.raises(ValueError, match="bad validation episodes 0; allowed: an integer >= 1"):
        select_checkpoints([], 0)
