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

`frame_labels` gathers them in a `FrameLabels` (boxes as `BoxLabel`s); the writer turns that
into the row's columns (`FrameLabels.row()`) where it builds the Parquet row.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

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


@dataclass(frozen=True)
class BoxLabel:
    """One agent's box at one of the labelled instants (schemas.BOX_TYPE), ego frame at t.

    Attributes:
        track_id: SUMO id of the vehicle or person.
        cls: schemas.BOX_CLASSES.
        t: timestep index (schemas.BOX_TIMESTEPS): 0 = t, 1 = t+0.5 s, 2 = t+1.0 s.
        x_m, y_m: box centre, m.
        yaw_rad: heading, counter-clockwise from the ego's +x.
        length_m, width_m: extents along and across the heading, m.
        speed_mps: speed along the heading, m/s.
        lidar_points: LiDAR returns on the agent at t; 0 for t > 0.
    """

    track_id: str
    cls: str
    t: int
    x_m: float
    y_m: float
    yaw_rad: float
    length_m: float
    width_m: float
    speed_mps: float
    lidar_points: int

    def row(self) -> dict:
        """The `boxes` column's struct entry."""
        return {
            "track_id": self.track_id,
            "cls": self.cls,
            "t": self.t,
            "x": self.x_m,
            "y": self.y_m,
            "yaw": self.yaw_rad,
            "length": self.length_m,
            "width": self.width_m,
            "speed": self.speed_mps,
            "lidar_points": self.lidar_points,
        }


def boxes(
    frame: FrameState, future: Sequence[FrameState], lidar_hits: dict[str, int] | None = None
) -> tuple[BoxLabel, ...]:
    """The agents inside the BEV area at t (frame), t+0.5 s and t+1.0 s (future[0],
    future[1]), all in the ego frame at t.

    Args:
        lidar_hits: LiDAR returns at t per track id (lidar.Sweep.actor_hits); missing: 0.
    """
    pose = frame.ego.pose
    out: list[BoxLabel] = []
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
                BoxLabel(
                    track_id=a.track_id,
                    cls=a.cls,
                    t=t,
                    x_m=float(xy[k, 0]),
                    y_m=float(xy[k, 1]),
                    yaw_rad=float(pose.relative_yaw(a.pose.yaw_rad)),
                    length_m=float(a.length_m),
                    width_m=float(a.width_m),
                    speed_mps=float(a.speed_mps),
                    lidar_points=hits,
                )
            )
    return tuple(out)


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


@dataclass(frozen=True)
class FrameLabels:
    """The labels of one frame: every non-sensor column of its row (schemas.FIELDS) but the
    episode's identity (episode_id, frame, town, weather, behaviour); `row()` names them as
    the columns do.

    Attributes:
        time_s: simulation time, s.
        ego_x_m, ego_y_m, ego_yaw_rad: the ego's own box centre and heading (world frame, m;
            yaw counter-clockwise from east, wrapped to [-pi, pi]), a recovery frame's too.
        ego_speed_mps: its speed, m/s.
        rig_shift_m, rig_yaw_rad: the sensor rig's shift to the ego's left and turn
            (`rig_pose`; 0, 0 but for recovery frames).
        command: the route command (schemas.COMMANDS).
        target_point_xy_m: the next route goal, the rig's frame at t, m.
        waypoints_xy_m: 8 floats x0, y0, ..., x3, y3: the ego's box centre at t+0.5..2.0 s,
            the rig's frame at t, m.
        traffic_light, light_distance_m, stop_sign, stop_distance_m: the signal ahead and
            the stop-controlled entry as FrameState gives them (m; None where there is none).
        expert_reason: the rule binding the expert's speed (schemas.EXPERT_REASONS).
        boxes: the agents in the BEV area at t, t+0.5 s and t+1.0 s, the rig's frame at t.
    """

    time_s: float
    ego_x_m: float
    ego_y_m: float
    ego_yaw_rad: float
    ego_speed_mps: float
    rig_shift_m: float
    rig_yaw_rad: float
    command: str
    target_point_xy_m: tuple[float, float]
    waypoints_xy_m: tuple[float, ...]
    traffic_light: str
    light_distance_m: float | None
    stop_sign: bool
    stop_distance_m: float | None
    expert_reason: str
    boxes: tuple[BoxLabel, ...]

    def row(self) -> dict:
        """These labels as the row's columns (schemas.FIELDS), for the writer to complete with
        the episode's identity and the sensor columns."""
        return {
            "time_s": self.time_s,
            "ego_x": self.ego_x_m,
            "ego_y": self.ego_y_m,
            "ego_yaw": self.ego_yaw_rad,
            "ego_speed": self.ego_speed_mps,
            "rig_shift_m": self.rig_shift_m,
            "rig_yaw_rad": self.rig_yaw_rad,
            "command": self.command,
            "target_point": list(self.target_point_xy_m),
            "waypoints": list(self.waypoints_xy_m),
            "traffic_light": self.traffic_light,
            "light_distance_m": self.light_distance_m,
            "stop_sign": self.stop_sign,
            "stop_distance_m": self.stop_distance_m,
            "expert_reason": self.expert_reason,
            "boxes": [b.row() for b in self.boxes],
        }


def frame_labels(
    frame: FrameState,
    future: Sequence[FrameState],
    lidar_hits: dict[str, int] | None = None,
    rig: tuple[float, float] = (0.0, 0.0),
    waypoints_ego: Sequence[float] | None = None,
) -> FrameLabels:
    """The labels of one frame from its state at t (`frame`) and its recorded future.

    `rig`: (shift_m, yaw_rad) of the sensor rig from the ego (`rig_pose`; recovery frames,
    datagen/episode.py): every label in the ego frame is then in the rig's frame, as if the
    ego stood there, while ego_x/ego_y/ego_yaw stay the ego's own pose. `waypoints_ego` (8
    floats, the ego frame at t) replaces the recorded future's waypoints: on-policy frames are
    labelled with the expert's plan from where the policy put the ego (drive/collect.py), and
    then `future` need only hold the boxes' two future states."""
    pose = frame.ego.pose
    seen = frame
    if rig != (0.0, 0.0):
        seen = replace(frame, ego=replace(frame.ego, pose=rig_pose(pose, *rig)))
    tp = seen.ego.pose.ego_from_world(np.array([frame.target_point_xy_m]))[0]
    return FrameLabels(
        time_s=float(frame.time_s),
        ego_x_m=float(pose.x_m),
        ego_y_m=float(pose.y_m),
        ego_yaw_rad=float(math.remainder(pose.yaw_rad, 2 * math.pi)),
        ego_speed_mps=float(frame.ego.speed_mps),
        rig_shift_m=float(rig[0]),
        rig_yaw_rad=float(rig[1]),
        command=frame.command,
        target_point_xy_m=(float(tp[0]), float(tp[1])),
        waypoints_xy_m=tuple(
            waypoints(seen, future) if waypoints_ego is None else [float(v) for v in waypoints_ego]
        ),
        traffic_light=frame.traffic_light,
        light_distance_m=frame.light_distance_m,
        stop_sign=bool(frame.stop_sign),
        stop_distance_m=frame.stop_distance_m,
        expert_reason=frame.expert_reason,
        boxes=boxes(seen, future, lidar_hits),
    )
