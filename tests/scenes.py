"""Hand-made sensor inputs for tests that need no simulator, and the small SUMO test network.

EGO_POSE, agent_at, frame_at    an ego pose, agents placed in its frame, a FrameState
flat_scene                      a flat square road with optional static boxes
build_test_network              the 3x3 grid (signal, stop signs, sidewalks, crossings)
shared_grid3                    that network and its static scene, built once a session
                                (the `grid3` fixture of tests/conftest.py)
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from datagen.sensors import scene
from datagen.sensors.mesh import Material, MeshBuilder, boxes_triangles
from datagen.state import AgentState, FrameState, Pose

EGO_POSE = Pose(40.0, -20.0, 0.7)  # a non-trivial world pose: tests place things in its frame


def agent_at(
    track_id: str,
    x_m: float,
    y_m: float,
    yaw_rad: float = 0.0,
    cls: str = "vehicle",
    dims: tuple[float, float, float] = (4.5, 1.8, 1.5),
    speed_mps: float = 0.0,
    ego: Pose = EGO_POSE,
) -> AgentState:
    """An agent whose box centre is at (x_m, y_m, yaw_rad) in the frame of `ego`."""
    wx, wy = ego.world_from_ego(np.array([[x_m, y_m]]))[0]
    pose = Pose(float(wx), float(wy), ego.yaw_rad + yaw_rad)
    return AgentState(track_id, cls, pose, *dims, speed_mps)


def frame_at(
    ego: Pose = EGO_POSE,
    agents: tuple[AgentState, ...] = (),
    time_s: float = 0.0,
    speed_mps: float = 0.0,
    traffic_light: str = "none",
    light_distance_m: float | None = None,
) -> FrameState:
    ego_state = AgentState("ego", "vehicle", ego, 4.7, 1.85, 1.5, speed_mps)
    return FrameState(
        time_s=time_s,
        ego=ego_state,
        agents=tuple(agents),
        command="follow",
        target_point_xy_m=(
            ego.x_m + 20 * math.cos(ego.yaw_rad),
            ego.y_m + 20 * math.sin(ego.yaw_rad),
        ),
        traffic_light=traffic_light,
        light_distance_m=light_distance_m,
        stop_sign=False,
        stop_distance_m=None,
        expert_reason="none",
    )


def flat_scene(
    boxes: list[tuple[tuple[float, float, float], tuple[float, float, float], float]] = (),
    road_half_m: float = 150.0,
) -> scene.StaticScene:
    """A square road (z = 0, drivable in the BEV) around EGO_POSE's origin, plus static boxes
    ((x, y, z-centre) world, (sx, sy, sz), yaw) of material POLE."""
    b = MeshBuilder()
    c = np.array([EGO_POSE.x_m, EGO_POSE.y_m])
    ring = c + np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * road_half_m
    v = np.concatenate([ring, np.zeros((4, 1))], 1)
    b.add(np.stack([v[[0, 1, 2]], v[[0, 2, 3]]]), Material.ROAD)
    for centre, size, yaw in boxes:
        tris = boxes_triangles(np.array([centre]), np.array([size]), np.array([yaw]))[0]
        b.add(tris, Material.POLE)
    return scene.assemble_static_scene(b, [ring], [1], terrain=False)


def build_test_network(path: Path) -> Path:
    """A 3x3 grid, 100 m blocks: a signal in the middle, all-way and minor-road stops on the
    west and east, two-lane east-west roads through the middle, sidewalks and crossings."""
    from datagen.world.towns import build_plain_network

    types = {(1, 1): "traffic_light", (0, 1): "allway_stop", (2, 1): "priority_stop"}
    nodes = [
        {"id": f"n{i}{j}", "x": 100 * i, "y": 100 * j, "type": types.get((i, j), "priority")}
        for i in range(3)
        for j in range(3)
    ]
    edges = []
    for i in range(3):
        for j in range(3):
            for di, dj in ((1, 0), (0, 1)):
                a, b = (i, j), (i + di, j + dj)
                if b[0] > 2 or b[1] > 2:
                    continue
                for u, v in ((a, b), (b, a)):
                    edges.append(
                        {
                            "id": f"e{u[0]}{u[1]}_{v[0]}{v[1]}",
                            "from": f"n{u[0]}{u[1]}",
                            "to": f"n{v[0]}{v[1]}",
                            "numLanes": 2 if (j == 1 and dj == 0) else 1,
                            "speed": 13.89,
                            "priority": 3 if dj == 0 else 1,
                        }
                    )
    return build_plain_network(nodes, edges, path)
