"""Typed ground-truth state that flows from the simulator (world.py) to sensors and labels.

All positions are in the world frame: SUMO network coordinates, metres, x east, y north.
Yaw is counter-clockwise from +x (east) in radians -- not SUMO's navigational angle (degrees,
0 = north, clockwise), which `world.py` converts once where libsumo is read. Positions are
bounding-box centres on the ground, not SUMO's front-bumper position.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Pose:
    """A planar pose: box centre (x_m, y_m) and yaw_rad, world frame."""

    x_m: float
    y_m: float
    yaw_rad: float

    def ego_from_world(self, xy_world: np.ndarray) -> np.ndarray:
        """(N, 2) world points -> (N, 2) points in this pose's frame (x forward, y left)."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        d = np.asarray(xy_world, dtype=np.float64).reshape(-1, 2) - (self.x_m, self.y_m)
        return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)

    def world_from_ego(self, xy_ego: np.ndarray) -> np.ndarray:
        """(N, 2) points in this pose's frame -> (N, 2) world points."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        p = np.asarray(xy_ego, dtype=np.float64).reshape(-1, 2)
        return np.stack(
            [self.x_m + c * p[:, 0] - s * p[:, 1], self.y_m + s * p[:, 0] + c * p[:, 1]], axis=1
        )

    def relative_yaw(self, yaw_world_rad: float | np.ndarray) -> float | np.ndarray:
        """World yaw -> yaw in this pose's frame, wrapped to [-pi, pi)."""
        return (np.asarray(yaw_world_rad) - self.yaw_rad + math.pi) % (2 * math.pi) - math.pi


@dataclass(frozen=True)
class AgentState:
    """One traffic participant at one instant, world frame.

    Attributes:
        track_id: SUMO id, stable over the episode.
        cls: "vehicle", "pedestrian" or "bicycle" (schemas.BOX_CLASSES).
        pose: box centre on the ground and heading.
        length_m, width_m, height_m: box extents (vType length/width/height).
        speed_mps: speed along the heading, m/s.
    """

    track_id: str
    cls: str
    pose: Pose
    length_m: float
    width_m: float
    height_m: float
    speed_mps: float


@dataclass(frozen=True)
class FrameState:
    """Ground truth at one recorded instant (2 Hz), world frame.

    Attributes:
        time_s: simulation time, s.
        ego: the expert-driven ego car.
        agents: every other vehicle and person within `world.AGENT_RADIUS_M` of the ego.
        command: high-level route command (schemas.COMMANDS).
        target_point_xy_m: the next route goal point, world frame.
        traffic_light: state of the signal governing the ego's next junction on its route if
            its stop line is within 30 m, else "none" (schemas.TRAFFIC_LIGHTS).
        light_distance_m: distance along the route to that stop line, None if "none".
        stop_sign: a stop-controlled entry on the route within 30 m.
        stop_distance_m: distance along the route to its stop line, None if no stop sign.
        expert_reason: the rule binding the expert's speed now (schemas.EXPERT_REASONS).
        signals: (traffic light id, state) of every traffic light in the network, the state a
            string with one SUMO signal character per controlled link (r, y, g, G, ...;
            libsumo trafficlight.getRedYellowGreenState): what the camera lights heads with.
    """

    time_s: float
    ego: AgentState
    agents: tuple[AgentState, ...]
    command: str
    target_point_xy_m: tuple[float, float]
    traffic_light: str
    light_distance_m: float | None
    stop_sign: bool
    stop_distance_m: float | None
    expert_reason: str
    signals: tuple[tuple[str, str], ...] = ()
