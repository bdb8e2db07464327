"""What a frame's episode says around it: the ego's own future path (the path labels of
training.pathspeed) and how long it has stood so far (the privileged planner's one input from
the past, issue 45). Both are computed per episode of a shard file, in frame order; in closed
loop, StandClock counts the same seconds at the policy's plans.
"""

from __future__ import annotations

import math

import numpy as np
import pyarrow.parquet as pq

from schemas import FRAME_PERIOD_S
from training import pathspeed

STAND_MPS = 0.5  # below this the ego stands (here and in training.privileged's weights)
STOOD_CAP_S = 20.0  # the input saturates here: longer than most red lights' remaining red


class StandClock:
    """Seconds the ego has stood, at one plan per FRAME_PERIOD_S: 0 at a plan where it moves
    and at the first plan where it stands, FRAME_PERIOD_S more at each plan it goes on
    standing. The training labels (stood_labels) run the same clock over an episode's frames."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self._standing = 0  # consecutive plans standing, this one included

    def tick(self, speed_mps: float) -> float:
        self._standing = self._standing + 1 if speed_mps < STAND_MPS else 0
        return max(self._standing - 1, 0) * FRAME_PERIOD_S


def _episodes(file: str, extra: tuple[str, ...] = ()):
    """The file's rows as pandas, and per episode its row numbers in frame order."""
    names = set(pq.read_schema(file).names)
    cols = ["episode_id", "frame", *extra]
    cols += [c for c in ("rig_shift_m", "rig_yaw_rad") if c in names]
    t = pq.read_table(file, columns=cols).to_pandas()
    groups = [ep.sort_values("frame").index.to_numpy() for _, ep in t.groupby("episode_id")]
    return t, groups


def stood_labels(file: str) -> np.ndarray:
    """(N,) float32 per row of a shard file: StandClock's seconds at that frame of its episode
    (frames are FRAME_PERIOD_S apart), from the recorded ego speeds."""
    t, groups = _episodes(file, ("ego_speed",))
    out = np.zeros(len(t), np.float32)
    speed = t["ego_speed"].to_numpy()
    for rows in groups:
        clock = StandClock()
        for r in rows:
            out[r] = clock.tick(float(speed[r]))
    return out


def path_labels(file: str) -> tuple[np.ndarray, np.ndarray]:
    """Per row of a shard file, pathspeed.future_path of its episode's later frames (the ego's
    own positions, in the frame the row's labels are in: the sensor rig's, `rig_shift_m` to
    the ego's left and turned `rig_yaw_rad`, for a recovery frame) -> (N, P, 2), (N, P)."""
    t, groups = _episodes(file, ("ego_x", "ego_y", "ego_yaw"))
    n = len(t)
    paths = np.zeros((n, pathspeed.PATH_POINTS, 2), np.float32)
    masks = np.zeros((n, pathspeed.PATH_POINTS), bool)
    shift = t["rig_shift_m"].to_numpy(np.float64) if "rig_shift_m" in t else np.zeros(n)
    turn = t["rig_yaw_rad"].to_numpy(np.float64) if "rig_yaw_rad" in t else np.zeros(n)
    xy_all = t[["ego_x", "ego_y"]].to_numpy(np.float64)
    yaw_all = t["ego_yaw"].to_numpy(np.float64)
    for rows in groups:
        xy, yaw = xy_all[rows], yaw_all[rows]
        for k, r in enumerate(rows):
            c, s_ = math.cos(yaw[k]), math.sin(yaw[k])
            origin = xy[k] + shift[r] * np.array([-s_, c])
            a = yaw[k] + turn[r]
            d = xy[k + 1 :] - origin
            ego = np.stack([d[:, 0] * math.cos(a) + d[:, 1] * math.sin(a),
                            -d[:, 0] * math.sin(a) + d[:, 1] * math.cos(a)], 1)  # fmt: skip
            paths[r], masks[r] = pathspeed.future_path(ego)
    return paths, masks
