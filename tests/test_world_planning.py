"""The expert plan's path geometry (datagen/world/planning.py): pure, no SUMO."""

import math

import numpy as np

from datagen.world import planning, route


def _straight(length=50.0):
    pts = np.array([[0.0, 0.0], [length, 0.0]])
    return route.Path(pts, np.array([0.0, length]), (), ((0.0, "a_0"),))


def test_centres_along_a_straight_path_lie_half_a_length_behind_the_front():
    c = planning.centres_along(_straight(), [0.0, 5.0, 10.0], 4.0)
    np.testing.assert_allclose(c, [[-2.0, 0.0], [3.0, 0.0], [8.0, 0.0]], atol=1e-9)


def test_centres_along_extend_back_along_the_cars_heading():
    # a car turned 10 degrees from the path: at its front's start its centre is where it is
    yaw = math.radians(10.0)
    c = planning.centres_along(_straight(), [0.0], 4.0, heading_rad=yaw)
    np.testing.assert_allclose(c[0], [-2.0 * math.cos(yaw), -2.0 * math.sin(yaw)], atol=1e-9)


def test_shifted_starts_beside_the_path_and_merges_into_it_within_the_ramp():
    p = planning.shifted(_straight(), 1.5, 10.0)
    np.testing.assert_allclose(p.pts[0], [0.0, 1.5], atol=1e-5)
    y = np.interp([2.0, 5.0, 10.0, 30.0], p.pts[:, 0], p.pts[:, 1])
    assert 1.5 > y[0] > y[1] > 0 and abs(y[2]) < 1e-9 and abs(y[3]) < 1e-9
    straight = _straight()
    assert planning.shifted(straight, 0.0, 10.0) is straight  # nothing to merge
