"""The labels of one recorded frame (paper Sec. III-A), from the simulator's ground truth.

Pure functions of `FrameState`s (the frame at t and its recorded future at 2 Hz) and the town's
label map (datagen/sensors/labelmap.py); every position is in the ego frame at t (x forward, y left, m; yaw counter-clockwise).

- `bev_semantic`: the network's drivable area, cut by sidewalks, with lane markings on top,
  rasterised on the BEV grid with OpenCV `fillPoly` (1/8-pixel vertex precision). Polygons are
  culled by their bounding boxes and painted one call each in LabelMap.class_id order: one
  call for all of them would use the even-odd rule and punch holes where lanes overlap.
- `boxes`: agents inside the BEV area at t, t+0.5 s and t+1.0 s, each in the ego frame at t,
  with their LiDAR returns at t.
- recovery frames (datagen/episode.py) are sensed from a rig shifted beside the ego and turned
  (`rig_pose`): their labels are in that rig's frame, so the waypoints lead back to where the
  expert drove (TransFuser++'s shifted-camera augmentation, Jaeger et al. 2023).
- `waypoints`: the ego's own box centre at t+0.5..2.0 s; `target_point` and the rest as the
  simulator reports them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import cv2
import numpy as np

from datagen.sensors.labelmap import LabelMap
from datagen.state import FrameState, Pose
from schemas import (
    BEV_AHEAD_M,
    BEV_SIDE_M,
    BEV_SIZE_PX,
    BOX_TIMESTEPS,
    FRAME_PERIOD_S,
    WAYPOINT_TIMES_S,
    ego_to_bev_px,
)

FUTURE_FRAMES = round(max(WAYPOINT_TIMES_S) / FRAME_PERIOD_S)  # 4: waypoints reach +2.0 s
_SUBPIXEL_BITS = 3  # fillPoly vertex precision: 1/8 px


def bev_area_corners(pose: Pose) -> np.ndarray:
    """(4, 2) world corners of the BEV area of the ego at `pose`."""
    ego = np.array(
        [
            [0.0, BEV_SIDE_M],
            [BEV_AHEAD_M, BEV_SIDE_M],
            [BEV_AHEAD_M, -BEV_SIDE_M],
            [0.0, -BEV_SIDE_M],
        ]
    )
    return pose.world_from_ego(ego)


def bev_semantic(label_map: LabelMap, pose: Pose) -> np.ndarray:
    """(256, 256) uint8 class ids on the BEV grid of the ego at `pose`: 0 other, 1 drivable,
    2 lane marking (the town's `label_map`, e.g. StaticScene.label_map)."""
    img = np.zeros((BEV_SIZE_PX, BEV_SIZE_PX), np.uint8)
    corners = bev_area_corners(pose)
    lo, hi = corners.min(0), corners.max(0)
    bb = label_map.bbox_m
    sel = np.flatnonzero(
        (bb[:, 0] <= hi[0]) & (bb[:, 2] >= lo[0]) & (bb[:, 1] <= hi[1]) & (bb[:, 3] >= lo[1])
    )
    if not len(sel):
        return img
    starts, ends = label_map.start[sel], label_map.start[sel + 1]
    lens = ends - starts
    idx = np.repeat(starts - np.concatenate([[0], np.cumsum(lens)[:-1]]), lens) + np.arange(
        lens.sum()
    )
    ego = pose.ego_from_world(label_map.xy_m[idx])
    row, col = ego_to_bev_px(ego[:, 0], ego[:, 1])
    # OpenCV puts pixel i's centre at i; ours (schemas.bev) at i + 0.5.
    scale = 1 << _SUBPIXEL_BITS
    pts = np.stack([(col - 0.5) * scale, (row - 0.5) * scale], 1).round().astype(np.int32)
    offs = np.concatenate([[0], np.cumsum(lens)])
    for k, p in enumerate(sel):
        cv2.fillPoly(
            img,
            [pts[offs[k] : offs[k + 1]]],
            int(label_map.class_id[p]),
            cv2.LINE_8,
            _SUBPIXEL_BITS,
        )
    return img


def in_bev_area(x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
    """Bool mask of ego-frame points that fall on the BEV grid."""
    row, col = ego_to_bev_px(x_m, y_m)
    return (row >= 0) & (row < BEV_SIZE_PX) & (col >= 0) & (col < BEV_SIZE_PX)


def boxes(
    frame: FrameState, future: Sequence[FrameState], lidar_hits: dict[str, int] | None = None
) -> list[dict]:
    """`boxes` column entries: agents inside the BEV area at t (frame), t+0.5 s and t+1.0 s
    (future[0], future[1]), all in the ego frame at t.

    Args:
        lidar_hits: LiDAR returns at t per track id (lidar.Sweep.actor_hits); missing: 0.
    """
    pose = frame.ego.pose
    out: list[dict] = []
    states = [frame, *future[: len(BOX_TIMESTEPS) - 1]]
    for t, state in zip(BOX_TIMESTEPS, states):
        agents = state.agents
        if not agents:
            continue
        xy = pose.ego_from_world(np.array([(a.pose.x_m, a.pose.y_m) for a in agents]))
        inside = in_bev_area(xy[:, 0], xy[:, 1])
        for k in np.flatnonzero(inside):
            a = agents[k]
            hits = int(lidar_hits.get(a.track_id, 0)) if (t == 0 and lidar_hits) else 0
            out.append(
                {
                    "track_id": a.track_id,
                    "cls": a.cls,
                    "t": t,
                    "x": float(xy[k, 0]),
                    "y": float(xy[k, 1]),
                    "yaw": float(pose.relative_yaw(a.pose.yaw_rad)),
                    "length": float(a.length_m),
                    "width": float(a.width_m),
                    "speed": float(a.speed_mps),
                    "lidar_points": hits,
                }
            )
    return out


def waypoints(frame: FrameState, future: Sequence[FrameState]) -> list[float]:
    """The ego's positions at +0.5, +1.0, +1.5, +2.0 s (future[0..3]) in the ego frame at t,
    flattened x0, y0, x1, y1, ..."""
    if len(future) < FUTURE_FRAMES:
        raise ValueError(f"waypoints need {FUTURE_FRAMES} future frames, got {len(future)}")
    xy = np.array([(f.ego.pose.x_m, f.ego.pose.y_m) for f in future[:FUTURE_FRAMES]])
    return frame.ego.pose.ego_from_world(xy).ravel().tolist()


def rig_pose(ego: Pose, shift_m: float, yaw_rad: float) -> Pose:
    """The sensor rig's pose when it is shifted `shift_m` to the ego's left (m, negative: right)
    and turned `yaw_rad` (counter-clockwise) from the ego's box centre and heading."""
    x, y = ego.world_from_ego(np.array([[0.0, shift_m]]))[0]
    return Pose(float(x), float(y), ego.yaw_rad + yaw_rad)


def frame_labels(
    frame: FrameState,
    future: Sequence[FrameState],
    lidar_hits: dict[str, int] | None = None,
    rig: tuple[float, float] = (0.0, 0.0),
    waypoints_ego: Sequence[float] | None = None,
) -> dict:
    """Every non-sensor column of one row (schemas.FIELDS) except the episode's identity
    (episode_id, frame, town, weather, behaviour) and the binary sensor columns.

    `rig`: (shift_m, yaw_rad) of the sensor rig from the ego (`rig_pose`; recovery frames,
    datagen/episode.py): every column in the ego frame is then in the rig's frame, as if the
    ego stood there, while ego_x/ego_y/ego_yaw stay the ego's own pose. `waypoints_ego` (8
    floats, the ego frame at t) replaces the recorded future's waypoints: on-policy frames are
    labelled with the expert's plan from where the policy put the ego (drive/collect.py), and
    then `future` need only hold the boxes' two future states."""
    pose = frame.ego.pose
    seen = frame
    if rig != (0.0, 0.0):
        seen = replace(frame, ego=replace(frame.ego, pose=rig_pose(pose, *rig)))
    tp = seen.ego.pose.ego_from_world(np.array([frame.target_point_xy_m]))[0]
    return {
        "time_s": float(frame.time_s),
        "ego_x": float(pose.x_m),
        "ego_y": float(pose.y_m),
        "ego_yaw": float(math.remainder(pose.yaw_rad, 2 * math.pi)),
        "ego_speed": float(frame.ego.speed_mps),
        "rig_shift_m": float(rig[0]),
        "rig_yaw_rad": float(rig[1]),
        "command": frame.command,
        "target_point": [float(tp[0]), float(tp[1])],
        "waypoints": (
            waypoints(seen, future) if waypoints_ego is None else [float(v) for v in waypoints_ego]
        ),
        "traffic_light": frame.traffic_light,
        "light_distance_m": frame.light_distance_m,
        "stop_sign": bool(frame.stop_sign),
        "stop_distance_m": frame.stop_distance_m,
        "expert_reason": frame.expert_reason,
        "boxes": boxes(seen, future, lidar_hits),
    }
