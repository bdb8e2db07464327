"""The actors of one frame as triangles: oriented boxes per agent (vehicles: wheel band, body,
glass cabin; people: legs, torso, head), coloured per actor from its track id.

World frame (SUMO network coordinates, metres, x east, y north, z up); every triangle carries
the index of its agent (what the LiDAR counts returns per box with).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from datagen.sensors.mesh import (
    BOX_FACE_TOP,
    Material,
    _stable_index,
    boxes_triangles,
    triangle_normals,
)
from datagen.state import AgentState

CAR_PAINTS = np.array(
    [
        (200, 200, 200),
        (30, 30, 34),
        (150, 20, 20),
        (20, 50, 140),
        (230, 230, 225),
        (110, 110, 115),
        (40, 90, 50),
        (200, 160, 30),
        (90, 40, 100),
        (60, 120, 170),
    ],
    np.uint8,
)
CLOTHES = np.array(
    [(180, 40, 40), (40, 70, 160), (220, 200, 60), (40, 140, 80), (230, 230, 230), (200, 100, 30)],
    np.uint8,
)
GLASS_RGB = (38, 48, 60)
TYRE_RGB = (22, 22, 22)
SKIN_RGB = (200, 160, 130)
TROUSERS_RGB = (45, 45, 60)


@dataclass(frozen=True)
class ActorMesh:
    """The dynamic triangles of one frame.

    Attributes:
        triangles_m: (D, 3, 3) float32, world frame.
        normals: (D, 3) float32.
        colour_rgb: (D, 3) uint8.
        material: (D,) uint8 (VEHICLE or PEDESTRIAN).
        actor: (D,) int32 index into the agents the mesh was built from.
    """

    triangles_m: np.ndarray
    normals: np.ndarray
    colour_rgb: np.ndarray
    material: np.ndarray
    actor: np.ndarray


def _parts(agent: AgentState) -> list[tuple]:
    """Boxes of one agent in its own frame (x forward, z up from the ground):
    ((cx, cy, cz), (sx, sy, sz), side rgb, top rgb, material)."""
    L, W, H = agent.length_m, agent.width_m, agent.height_m
    if agent.cls == "pedestrian":
        shirt = tuple(CLOTHES[_stable_index(agent.track_id, len(CLOTHES))])
        m = Material.PEDESTRIAN
        return [
            ((0, 0, 0.24 * H), (0.7 * L, 0.8 * W, 0.48 * H), TROUSERS_RGB, TROUSERS_RGB, m),
            ((0, 0, 0.665 * H), (L, W, 0.37 * H), shirt, shirt, m),
            ((0, 0, 0.925 * H), (0.5 * W, 0.5 * W, 0.15 * H), SKIN_RGB, SKIN_RGB, m),
        ]
    paint = tuple(CAR_PAINTS[_stable_index(agent.track_id, len(CAR_PAINTS))])
    m = Material.VEHICLE
    if agent.cls == "bicycle":
        shirt = tuple(CLOTHES[_stable_index(agent.track_id, len(CLOTHES))])
        return [
            ((0, 0, 0.45), (L, 0.12, 0.9), TYRE_RGB, paint, m),
            ((-0.1 * L, 0, 0.55 * H + 0.05), (0.35, 0.45, 0.45 * H - 0.2), shirt, shirt, m),
            ((-0.1 * L, 0, H - 0.12), (0.22, 0.22, 0.24), SKIN_RGB, SKIN_RGB, m),
        ]
    under = 0.3 if H < 2.2 else 0.45  # a dark band for the wheels and the underbody
    parts = [((0, 0, under / 2), (0.8 * L, 0.94 * W, under), TYRE_RGB, TYRE_RGB, m)]
    if H < 2.2:  # car: body, and a glass cabin with a painted roof
        top = 0.58 * H
        parts += [
            ((0, 0, (under + top) / 2), (L, W, top - under), paint, paint, m),
            ((-0.06 * L, 0, (top + H) / 2), (0.5 * L, 0.9 * W, H - top), GLASS_RGB, paint, m),
        ]
    else:  # van, truck, bus: one tall body with a windscreen
        parts += [
            # the body stops 4 cm short of the front so the windscreen's face is in front of it
            ((-0.02, 0, (under + H) / 2), (L - 0.04, W, H - under), paint, paint, m),
            ((0.5 * L - 0.03, 0, 0.72 * H), (0.06, 0.92 * W, 0.3 * H), GLASS_RGB, GLASS_RGB, m),
        ]
    return parts


def actor_mesh(agents: Sequence[AgentState]) -> ActorMesh:
    """Oriented boxes for every agent (vehicles: wheel band, body, glass cabin; people: legs,
    torso, head), coloured per actor (a stable colour from its track id)."""
    centres, sizes, yaws, side, top, mats, owner = [], [], [], [], [], [], []
    for k, a in enumerate(agents):
        c, s = math.cos(a.pose.yaw_rad), math.sin(a.pose.yaw_rad)
        for (px, py, pz), size, rgb_side, rgb_top, mat in _parts(a):
            centres.append((a.pose.x_m + c * px - s * py, a.pose.y_m + s * px + c * py, pz))
            sizes.append(size)
            yaws.append(a.pose.yaw_rad)
            side.append(rgb_side)
            top.append(rgb_top)
            mats.append(int(mat))
            owner.append(k)
    if not centres:
        z = np.zeros((0, 3), np.float32)
        return ActorMesh(
            np.zeros((0, 3, 3), np.float32),
            z,
            np.zeros((0, 3), np.uint8),
            np.zeros(0, np.uint8),
            np.zeros(0, np.int32),
        )
    tris = boxes_triangles(np.array(centres), np.array(sizes), np.array(yaws))  # (B, 12, 3, 3)
    n = tris.shape[1]
    colour = np.where(
        BOX_FACE_TOP[None, :, None],
        np.array(top, np.uint8)[:, None],
        np.array(side, np.uint8)[:, None],
    )  # (B, 12, 3)
    tris = tris.reshape(-1, 3, 3)
    return ActorMesh(
        triangles_m=tris.astype(np.float32),
        normals=triangle_normals(tris),
        colour_rgb=colour.reshape(-1, 3),
        material=np.repeat(np.array(mats, np.uint8), n),
        actor=np.repeat(np.array(owner, np.int32), n),
    )
