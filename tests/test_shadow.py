"""The shadow steps' exact beam (``ray_box_distance``) and its clearance with a box, by hand-computed geometry."""

import math

import numpy as np
import pytest

from coin_app.backends.shadow import outline_distance, ray_box_clearance, ray_box_distance


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


@pytest.mark.parametrize(
    ("origin", "angle", "center", "want"),
    [
        ((0.0, 0.0), 0.0, (10.0, 0.0), 4.0),  # straight through the 4 m length
        ((0.0, 0.0), 0.0, (10.0, 0.99), 4.0),  # 1 cm inside its edge: still the whole length
        ((0.0, 0.0), math.pi / 4, (5.0, 5.0), 2.0 * math.sqrt(2.0)),  # diagonal: (4, 4) to (6, 6)
        ((0.0, 0.0), 0.0, (10.0, 1.01), -0.01),  # 1 cm beside its edge
        ((0.0, 0.0), 0.0, (10.0, 3.0), -2.0),  # 2 m beside it: the corners at y = 2
        ((0.0, 0.0), math.pi, (10.0, 0.0), -8.0),  # the box behind: the origin 8 m from its near face
    ],
)
def test_clearance_with_a_4_by_2_box(origin, angle, center, want):
    assert ray_box_clearance(origin, angle, center, 0.0, 4.0, 2.0) == pytest.approx(want, abs=1e-9)


def test_outline_distance_to_4_by_2_boxes():
    # one box at the origin, heading 0 (x in [-2, 2], y in [-1, 1]); the same turned by 90 deg about (10, 0)
    boxes = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, math.pi / 2]])
    cases = [
        ((3.0, 0.0), [1.0, 6.0]),  # beyond the front face; 6 m short of the turned box's side face (x = 9)
        ((0.0, 0.5), [-0.5, 9.0]),  # inside the first: 0.5 m from its nearest face (negative); 9 m from the other
        ((5.0, 4.0), [math.hypot(3.0, 3.0), math.hypot(4.0, 2.0)]),  # beyond a corner of each: (2, 1) and (9, 2)
    ]
    for point, want in cases:
        np.testing.assert_allclose(outline_distance(np.array(point), boxes, 4.0, 2.0), want, atol=1e-12)
