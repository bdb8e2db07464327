"""The portable ray backend: trimesh's own ray API (`trimesh.ray.ray_pyembree`, Embree through
embreex), behind the interface of the fast path (datagen/sensors/embree.py): `Scene`,
`intersect`, `distance`, `occluded`, with the same arguments, dtypes and in-place `tfar`.

Used where the fast path cannot load (datagen/sensors/raycast.py `ray_backend`), or when asked
for with `--sensor raycaster=trimesh`. The same Embree library finds the first hit of each ray,
so the hit primitives are the fast path's; the distance is trimesh's hit location (a plane-line
intersection in float64) projected on the ray, equal to Embree's float32 distance to ~1e-5 m,
so a shard can differ from the fast path's in a last bit (tests/test_raycasters.py: on the
grid3 test town an episode's LiDAR BEVs are equal but for one cell in 131k, its images differ
by ~0.01 grey levels on average). Where two coplanar triangles tie, the two may name either
one (both Embree; trimesh shifts the scene to its corner before the float32 cast). trimesh's
first-hit query has no far bound: a hit beyond a ray's `tfar` is dropped afterwards, which is
the same answer (the first hit lies beyond tfar exactly when nothing lies within it). Slower
than the fast path: embreex fills the scene one Python-level index at a time and every query
converts its rays to float64 and back.

Units: metres; every array is float32 world coordinates, as in embree.py.
"""

from __future__ import annotations

import numpy as np
import trimesh
from trimesh.ray.ray_pyembree import RayMeshIntersector

NAME = "trimesh"


class Scene:
    """trimesh's ray intersector of (N, 3, 3) float32 triangles; primitive id = row."""

    def __init__(self, triangles_m: np.ndarray):
        tri = np.ascontiguousarray(triangles_m, np.float32).reshape(-1, 3, 3)
        n = len(tri)
        self.rays = None
        if n:
            # one unshared vertex triple per triangle and no processing, so face i is row i
            mesh = trimesh.Trimesh(
                tri.reshape(3 * n, 3), np.arange(3 * n).reshape(n, 3), process=False
            )
            self.rays = RayMeshIntersector(mesh, scale_to_box=False)


def _first_hits(
    scene: Scene, origins: np.ndarray, directions: np.ndarray, tfar: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(prim (N,) int32, -1 none; dist (N,) float32, inf none) of the first hit of each ray
    within its far bound tfar (N,) float32."""
    n = len(tfar)
    prim = np.full(n, -1, np.int32)
    dist = np.full(n, np.inf, np.float32)
    if scene.rays is None or n == 0:
        return prim, dist
    o = np.broadcast_to(origins, (n, 3))
    d = np.broadcast_to(directions, (n, 3))
    tri, ray, loc = scene.rays.intersects_id(o, d, multiple_hits=False, return_locations=True)
    t = np.einsum("ij,ij->i", loc - o[ray], d[ray]).astype(np.float32)  # along the unit ray
    near = t <= tfar[ray]
    prim[ray[near]] = tri[near]
    dist[ray[near]] = t[near]
    return prim, dist


def _check(origins: np.ndarray, directions: np.ndarray, tfar: np.ndarray) -> None:
    """The fast path's argument contract (embree.py `_inputs`), so both refuse the same calls."""
    if tfar.dtype != np.float32 or tfar.ndim != 1 or not tfar.flags.c_contiguous:
        raise ValueError(f"tfar must be contiguous float32 (N,), got {tfar.dtype} {tfar.shape}")
    for name, a in (("origins", origins), ("directions", directions)):
        if (
            a.dtype != np.float32
            or a.ndim != 2
            or a.shape[1] != 3
            or a.shape[0] not in (1, len(tfar))
        ):
            raise ValueError(f"{name} must be float32 (N, 3) or (1, 3), got {a.dtype} {a.shape}")


def intersect(
    scene: Scene, origins: np.ndarray, directions: np.ndarray, tfar: np.ndarray
) -> np.ndarray:
    """First hits: (N,) int32 primitive ids (-1: no hit within tfar). tfar (N,) float32 holds
    each ray's far bound and is overwritten with the hit distance where there is a hit."""
    _check(origins, directions, tfar)
    prim, dist = _first_hits(scene, origins, directions, tfar)
    hit = prim >= 0
    tfar[hit] = dist[hit]
    return prim


def distance(scene: Scene, origins: np.ndarray, directions: np.ndarray, tfar: np.ndarray) -> None:
    """First-hit distances only: tfar (N,) float32, each ray's far bound, is overwritten with
    the hit distance where there is a hit (unchanged on a miss)."""
    intersect(scene, origins, directions, tfar)


def occluded(
    scene: Scene, origins: np.ndarray, directions: np.ndarray, tfar: np.ndarray
) -> np.ndarray:
    """(N,) bool: does the scene hold anything along each ray within tfar (N,) float32 (m)."""
    _check(origins, directions, tfar)
    return _first_hits(scene, origins, directions, tfar)[0] >= 0
