"""The shadow steps' exact beam (``ray_box_distance``) by hand-computed geometry."""

import math

import pytest

from coin_app.backends.shadow import ray_box_distance


@pytest.mark.parametrize(
    ("origin", "angle", "center", "heading", "want"),
    [
        ((0.0, 0.0), 0.0, (10.0, 0.0), 0.0, 8.0),  # 4 x 2 box ahead: its near face at x = 8
        ((0.0, 0.0), 0.0, (10.0, 0.0), math.pi / 2, 9.0),  # turned a quarter: its 2 m side faces the ray
        ((0.0, 0.0), math.pi / 4, (5.0, 5.0), 0.0, 4.0 * math.sqrt(2.0)),  # diagonal: enters at (4, 4)
        ((0.0, 0.0), math.pi / 2, (10.0, 0.0), 0.0, math.inf),  # looking away
        ((0.0, 0.0), 0.0, (10.0, 1.01), 0.0, math.inf),  # passes 1 cm beside its edge
        ((0.0, 0.0), 0.0, (10.0, 0.99), 0.0, 8.0),  # 1 cm inside it
        ((10.0, 0.0), 1.0, (10.0, 0.0), 0.0, 0.0),  # from inside the box
        ((0.0, 0.0), math.pi, (10.0, 0.0), 0.0, math.inf),  # the box behind
    ],
)
def test_distance_to_a_4_by_2_box(origin, angle, center, heading, want):
    assert ray_box_distance(origin, angle, center, heading, 4.0, 2.0) == pytest.approx(want, abs=1e-12)
