"""TransFuser++'s output for the privileged planner (training/pathspeed.py): the path label
follows the future at 1 m spacing and masks what the future does not reach, the speed class
is the first second's mean speed, and the timed waypoints made of both stand or move along the
path at the expected speed."""

from __future__ import annotations

import numpy as np
import torch

from training.pathspeed import (
    PATH_POINTS,
    SPEED_CLASSES_MPS,
    future_path,
    speed_class,
    to_waypoints,
)


def test_the_path_follows_the_future_at_one_metre_and_masks_what_it_does_not_reach():
    # 2 Hz future of an ego at 4 m/s turning left onto +y after 4 m
    path, mask = future_path(np.array([[2.0, 0.0], [4.0, 0.0], [4.0, 2.0], [4.0, 4.0]]))
    assert mask.tolist() == [True] * 8 + [False] * (PATH_POINTS - 8)
    np.testing.assert_allclose(
        path[:8], [[1, 0], [2, 0], [3, 0], [4, 0], [4, 1], [4, 2], [4, 3], [4, 4]], atol=1e-6
    )
    assert not path[8:].any()
    _, standing = future_path(np.zeros((6, 2)))  # it never moves: no path to learn
    assert not standing.any()


def test_the_speed_class_is_the_first_seconds_mean_speed():
    t = np.array([0.5, 1.0, 1.5, 2.0])
    wp = np.stack([np.stack([v * t, 0 * t], 1) for v in (0.0, 0.3, 1.2, 7.9, 30.0)])
    assert speed_class(wp).tolist() == [0, 0, 1, 5, len(SPEED_CLASSES_MPS) - 1]


def _out(path: np.ndarray, cls: int) -> dict[str, torch.Tensor]:
    logits = torch.full((1, len(SPEED_CLASSES_MPS)), -10.0)
    logits[0, cls] = 10.0
    return {"path": torch.tensor(path, dtype=torch.float32)[None], "speed_logits": logits}


def test_the_waypoints_stand_or_move_along_the_path_at_the_classes_speed():
    straight = np.stack([np.arange(1.0, PATH_POINTS + 1), np.zeros(PATH_POINTS)], 1)
    assert not to_waypoints(_out(straight, 0)).any()  # "stand": the brake
    k = SPEED_CLASSES_MPS.index(4.0)
    wp = to_waypoints(_out(straight, k))[0].numpy()
    np.testing.assert_allclose(wp, [[2, 0], [4, 0], [6, 0], [8, 0]], atol=1e-4)
    # past the path's end (10 m) it goes on along the last segment: 14 m/s * 2 s = 28 m
    wp = to_waypoints(_out(straight, len(SPEED_CLASSES_MPS) - 1))[0].numpy()
    np.testing.assert_allclose(wp[-1], [28.0, 0.0], atol=1e-3)
    # a left turn: the points lie on the path, 2 m apart at 4 m/s
    arc = np.stack([5 * np.sin(np.arange(1, 11) / 5), 5 - 5 * np.cos(np.arange(1, 11) / 5)], 1)
    wp = to_waypoints(_out(arc, k))[0].numpy()
    radius = np.linalg.norm(wp - [0.0, 5.0], axis=1)
    np.testing.assert_allclose(radius, 5.0, atol=0.05)
    assert np.all(np.diff(wp[:, 1]) > 0)
