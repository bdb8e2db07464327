"""Triangles and what they are made of: the vocabulary shared by the static scene
(datagen/sensors/scene.py), the actors (datagen/sensors/actors.py) and the sensors.

World frame throughout (SUMO network coordinates, metres, x east, y north, z up).
"""

from __future__ import annotations

import enum
import zlib

import numpy as np


class Material(enum.IntEnum):
    """Surface class of a triangle (what the camera colours and shades it as)."""

    ROAD = 0
    MARKING = 1
    SIDEWALK = 2
    TERRAIN = 3
    BUILDING = 4
    POLE = 5
    SIGN = 6
    VEHICLE = 7
    PEDESTRIAN = 8
    LAMP = 9  # a traffic-light lamp: lit per frame by the camera (see camera.lit_slots)
    VEGETATION = 10


# Unit box: 12 triangles, faces +x, -x, +y, -y, +z, -z (two triangles each), corners at +-0.5.
_BOX_QUADS = (
    np.array(
        [
            [[1, -1, -1], [1, 1, -1], [1, 1, 1], [1, -1, 1]],
            [[-1, 1, -1], [-1, -1, -1], [-1, -1, 1], [-1, 1, 1]],
            [[1, 1, -1], [-1, 1, -1], [-1, 1, 1], [1, 1, 1]],
            [[-1, -1, -1], [1, -1, -1], [1, -1, 1], [-1, -1, 1]],
            [[-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]],
            [[-1, 1, -1], [1, 1, -1], [1, -1, -1], [-1, -1, -1]],
        ],
        np.float64,
    )
    * 0.5
)
UNIT_BOX = np.concatenate([_BOX_QUADS[:, [0, 1, 2]], _BOX_QUADS[:, [0, 2, 3]]], axis=0)[
    np.array([0, 6, 1, 7, 2, 8, 3, 9, 4, 10, 5, 11])
]  # (12, 3, 3), face f is triangles 2f, 2f+1
BOX_FACE_TOP = np.repeat(  # per UNIT_BOX triangle: on the +z face
    np.array([0, 0, 0, 0, 1, 0]), 2
).astype(bool)


def boxes_triangles(
    centre_xyz: np.ndarray,
    size_xyz: np.ndarray,
    yaw_rad: np.ndarray,
    faces: np.ndarray | None = None,
) -> np.ndarray:
    """Oriented boxes -> (B, F, 3, 3) triangles.

    Args:
        centre_xyz: (B, 3) box centres (not the ground point), m, world frame.
        size_xyz: (B, 3) extents along the box's own x (heading), y, z, m.
        yaw_rad: (B,) heading, counter-clockwise from world +x.
        faces: triangle indices of UNIT_BOX to keep (default all 12; F = len(faces)).
    """
    unit = UNIT_BOX if faces is None else UNIT_BOX[faces]
    local = unit[None] * np.asarray(size_xyz, np.float64)[:, None, None, :]  # (B, F, 3, 3)
    c, s = np.cos(yaw_rad)[:, None, None], np.sin(yaw_rad)[:, None, None]
    x = c * local[..., 0] - s * local[..., 1]
    y = s * local[..., 0] + c * local[..., 1]
    out = np.stack([x, y, local[..., 2]], axis=-1)
    return out + np.asarray(centre_xyz, np.float64)[:, None, None, :]


def triangle_normals(tris: np.ndarray) -> np.ndarray:
    """(T, 3, 3) -> (T, 3) float32 unit normals (orientation arbitrary; the camera flips them to
    face the ray)."""
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    return (n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)).astype(np.float32)


def _stable_index(key: str, n: int) -> int:
    """A deterministic index in [0, n) from a string (Python's hash() is salted per process)."""
    return zlib.crc32(key.encode()) % n


# Base colours (RGB albedo as 0..255) of the static materials.
COLOURS = {
    Material.ROAD: (78, 78, 82),
    Material.MARKING: (228, 228, 222),
    Material.SIDEWALK: (158, 154, 148),
    Material.TERRAIN: (92, 122, 66),
    Material.POLE: (105, 108, 112),
    Material.SIGN: (196, 28, 28),
    Material.LAMP: (40, 40, 40),
}


class MeshBuilder:
    """Accumulates triangles with their material, colour and tag."""

    def __init__(self) -> None:
        self.tris: list[np.ndarray] = []
        self.mat: list[np.ndarray] = []
        self.rgb: list[np.ndarray] = []
        self.tag: list[np.ndarray] = []

    def add(self, tris: np.ndarray, material: Material, rgb=None, tag: int | np.ndarray = -1):
        tris = np.asarray(tris, np.float64).reshape(-1, 3, 3)
        if not len(tris):
            return
        n = len(tris)
        self.tris.append(tris)
        self.mat.append(np.full(n, int(material), np.uint8))
        colour = COLOURS[material] if rgb is None else rgb
        self.rgb.append(np.broadcast_to(np.asarray(colour, np.uint8), (n, 3)).copy())
        self.tag.append(np.broadcast_to(np.asarray(tag, np.int32), (n,)).copy())
