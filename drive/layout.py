"""The scene layout the infractions are judged against, from the sensors' own static scene.

Built from `datagen.sensors.scene.StaticScene` (the mesh the LiDAR and camera see and its `label_map`,
the BEV polygons the labels paint), world frame, metres:

- road: the drivable polygons (BEV class 1: car lanes, junctions) minus the cut-outs painted
  over them (class 0: sidewalks, walking areas);
- kerb: those cut-outs (mounting the sidewalk is a collision with the layout);
- obstacles: the footprints (top faces) of buildings, poles, signal heads and tree trunks.
"""

from __future__ import annotations

import numpy as np

from datagen.sensors.furniture import TRUNK_RGB
from datagen.sensors.mesh import Material
from datagen.sensors.scene import StaticScene


def boxes_overlap(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Separating-axis test of one convex quad a (4, 2) against quads b (N, 4, 2) -> (N,) bool
    (touching edges count as overlap)."""
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4, 2)
    if len(b) == 0:
        return np.zeros(0, bool)
    axes_a = np.diff(np.vstack([a, a[:1]]), axis=0)[:2]  # (2, 2) two edge directions suffice
    axes_b = b[:, [1, 2]] - b[:, [0, 1]]  # (N, 2, 2)
    axes = np.concatenate([np.broadcast_to(axes_a, (len(b), 2, 2)), axes_b], axis=1)  # (N, 4, 2)
    normals = np.stack([-axes[..., 1], axes[..., 0]], -1)  # (N, 4, 2)
    pa = np.einsum("nkd,pd->nkp", normals, a)  # (N, 4 axes, 4 points)
    pb = np.einsum("nkd,npd->nkp", normals, b)
    separated = (pa.max(-1) < pb.min(-1)) | (pb.max(-1) < pa.min(-1))
    return ~separated.any(-1)


class Layout:
    """Road, kerb and obstacle geometry of one town (module docstring).

    Args:
        road, kerb, obstacles: shapely polygons, world frame (see `from_static`).
    """

    def __init__(self, road: list, kerb: list, obstacles: list):
        import shapely

        self._road = shapely.STRtree([shapely.make_valid(p) for p in road])
        self._kerb = shapely.STRtree([shapely.make_valid(p) for p in kerb])
        self._obstacles = shapely.STRtree(obstacles) if len(obstacles) else None

    @staticmethod
    def from_static(static: StaticScene) -> Layout:
        """The layout of the sensors' static scene."""
        import shapely

        labels = static.label_map
        rings = [
            labels.xy_m[labels.start[p] : labels.start[p + 1]].astype(np.float64)
            for p in range(len(labels.class_id))
        ]
        road = [shapely.Polygon(r) for r, c in zip(rings, labels.class_id) if c == 1]
        kerb = [shapely.Polygon(r) for r, c in zip(rings, labels.class_id) if c == 0]
        mat = static.material
        up = static.normals[:, 2] > 0.5
        trunk = (mat == Material.VEGETATION) & np.all(static.colour_rgb == TRUNK_RGB, axis=1)
        solid = np.isin(mat, (Material.BUILDING, Material.POLE, Material.SIGN)) | trunk
        foot = static.triangles_m[up & solid][:, :, :2].astype(np.float64)
        return Layout(road, kerb, list(shapely.polygons(foot)) if len(foot) else [])

    def on_road(self, x_m: float, y_m: float, on_kerb: bool | None = None) -> bool:
        """The point lies on the drivable area (not on a sidewalk or off the network);
        `on_kerb`: `self.on_kerb(x, y)` if the caller has it already."""
        import shapely

        if on_kerb is None:
            on_kerb = self.on_kerb(x_m, y_m)
        p = shapely.Point(x_m, y_m)
        return not on_kerb and len(self._road.query(p, predicate="intersects")) > 0

    def on_kerb(self, x_m: float, y_m: float) -> bool:
        """The point lies on a sidewalk or walking area."""
        import shapely

        return len(self._kerb.query(shapely.Point(x_m, y_m), predicate="intersects")) > 0

    def _points_in(self, tree, xy_m: np.ndarray) -> np.ndarray:
        import shapely

        pts = shapely.points(np.asarray(xy_m, dtype=np.float64).reshape(-1, 2))
        hit = np.zeros(len(pts), bool)
        hit[tree.query(pts, predicate="intersects")[0]] = True
        return hit

    def kerb_points(self, xy_m: np.ndarray) -> np.ndarray:
        """(N,) bool: which of the world points (N, 2) lie on a sidewalk or walking area."""
        return self._points_in(self._kerb, xy_m)

    def road_points(self, xy_m: np.ndarray, on_kerb: np.ndarray | None = None) -> np.ndarray:
        """(N,) bool: which of the world points (N, 2) lie on the drivable area; `on_kerb`:
        `self.kerb_points(xy_m)` if the caller has it already."""
        if on_kerb is None:
            on_kerb = self.kerb_points(xy_m)
        return ~on_kerb & self._points_in(self._road, xy_m)

    def hits_obstacle(self, corners: np.ndarray) -> bool:
        """The box (4, 2) world corners touches a building, pole, sign or tree trunk."""
        if self._obstacles is None:
            return False
        import shapely

        return len(self._obstacles.query(shapely.Polygon(corners), predicate="intersects")) > 0
