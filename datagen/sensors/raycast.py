"""Ray casting with Embree: one frame's scene (a culled static part kept across frames, and
this frame's actors) and the world-frame rays of a sensor.

Culling. datagen/sensors/scene.py sorts the static triangles into square tiles (TILE_M) by centroid;
each tile knows how far its triangles reach from its centre. The town is cut into CELL_M cells;
a cell's static Embree scene holds the tiles within the sensors' reach (the camera's 150 m plus
its mount) of any point of the cell, so the cost per frame does not grow with the town, and it
is committed once per worker process and reused by every episode that drives through the cell.
Measured: one Embree scene of a whole town instead traverses 12% slower on grid_small (51k
triangles) and 27% slower on random_city (221k) than a culled one, for the same hits.

Two Embree scenes per frame, not one. Committing the 13-22k static triangles within reach costs
2-3 ms (15-20 ms through embreex, which copied vertices one Python-level index at a time;
datagen/sensors/embree.py fills the buffers with one copy), too much to pay every frame. So the static
scene is committed once per cell (60 m; ~0.2 ms per frame at 10 m/s while the process cache is
cold), and the agents get their own small scene each frame (~1k triangles, ~0.1 ms). Every
sensor ray is cast into the static scene; only the rays that can hit an agent (LiDAR: its box's
elevation x azimuth window, ~3k of 64k rays; camera: its bounding sphere's projected rectangle)
are cast again into the actor scene, bounded by their static hit, which costs ~0.5 ms a frame.
bench/frame.py measures the result against bare Embree queries for the same rays.

Two ray backends with one interface (`Scene`, `intersect`, `distance`, `occluded`):
datagen/sensors/embree.py, Embree called from numba (the fast path, the default), and
datagen/sensors/trimesh_rays.py, trimesh's own ray API on the same Embree (portable). The fast
path loads Embree out of the embreex wheel by its Linux file name; where it cannot load,
`ray_backend` takes trimesh's with one warning line. `--sensor raycaster=trimesh` forces it.
"""

from __future__ import annotations

import importlib
import math
import os
import sys
import weakref
from collections import OrderedDict
from dataclasses import dataclass
from functools import cached_property

import numba
import numpy as np

from datagen.sensors.actors import ActorMesh, actor_mesh
from datagen.sensors.scene import StaticScene
from datagen.state import AgentState, FrameState, Pose

RAYCASTERS = ("embree", "trimesh")  # SensorConfig.raycaster: the fast path, trimesh.ray
_WARNED = "IIDSU_RAYCASTER_WARNED"  # set once warned, so worker processes do not repeat it
_backends: dict[str, object] = {}


def ray_backend(name: str = "embree"):
    """The ray backend module `name` (RAYCASTERS). "embree" where the fast path cannot load
    (no Embree library at the embreex wheel's Linux file name, numba unable to call it) gives
    trimesh's instead, after one warning line on stderr (once per build: child processes
    inherit the note that it was given)."""
    if name not in RAYCASTERS:
        raise ValueError(f"raycaster must be one of {RAYCASTERS}, got {name!r}")
    if name not in _backends:
        if name == "embree":
            try:
                backend = importlib.import_module("datagen.sensors.embree")
            except Exception as e:  # OSError, ImportError, numba/llvmlite errors: any means no
                if not os.environ.get(_WARNED):
                    print(
                        f"warning: the Embree fast path cannot load here ({type(e).__name__}: "
                        f"{e}); casting rays with trimesh.ray instead (slower, the same hits)",
                        file=sys.stderr,
                    )
                    os.environ[_WARNED] = "1"
                backend = ray_backend("trimesh")
        else:
            backend = importlib.import_module("datagen.sensors.trimesh_rays")
        _backends[name] = backend
    return _backends[name]


@dataclass
class FrameScene:
    """The scene of one frame: a static ray scene (the tiles within reach of the ego's cell,
    committed once per process) and an actor scene (this frame's agents), cast in turn.

    Primitive ids are unified: 0..n_static-1 are static triangles, n_static.. actor triangles;
    `actor_of(prim)` (and the camera's shading) read their attributes without concatenating
    the static arrays with the actors' every frame.

    Attributes:
        backend: the ray backend module (`ray_backend`) both scenes belong to.
        static_embree, actor_embree: its committed `Scene`s (actor_embree None: no agents).
        static_normals: (S, 3) float32; static_colour_rgb: (S, 3) uint8; static_material: (S,)
            uint8; static_tag: (S,) int32 lamp tags (-1 elsewhere): the static primitives'.
        actors: this frame's actor triangles (ActorMesh; its `actor` is the agent index).
        n_static: the first n_static primitives are static (S).
        agents: the agents in the actor scene, in actor-index order.
        actor_boxes: (A, 6) float64 the agents' boxes: x, y (centre, m), yaw (rad), length,
            width, height (m); `actor_centres_m` and `actor_radii_m` derive their bounding
            spheres.
        ray_log: if a list, every ray query appends (query, scene, origins, directions,
            tfar) to it (bench/frame.py replays them as bare backend calls).
    """

    backend: object
    static_embree: object
    actor_embree: object | None
    static_normals: np.ndarray
    static_colour_rgb: np.ndarray
    static_material: np.ndarray
    static_tag: np.ndarray
    actors: ActorMesh
    n_static: int
    agents: tuple[AgentState, ...]
    actor_boxes: np.ndarray
    ray_log: list | None = None

    @cached_property
    def actor_centres_m(self) -> np.ndarray:
        """(A, 3) float64 world centres of the agents' bounding spheres (half their height)."""
        b = self.actor_boxes
        return np.stack([b[:, 0], b[:, 1], b[:, 5] / 2], 1)

    @cached_property
    def actor_radii_m(self) -> np.ndarray:
        """(A,) float64 radii of the agents' bounding spheres (half the box diagonal), m."""
        b = self.actor_boxes
        return 0.5 * np.sqrt(b[:, 3] ** 2 + b[:, 4] ** 2 + b[:, 5] ** 2)

    def actor_of(self, prim: np.ndarray) -> np.ndarray:
        """(n,) int32 index into `agents` of each primitive's agent; -1 static or no hit."""
        out = np.full(len(prim), -1, np.int32)
        dyn = np.flatnonzero(prim >= self.n_static)
        out[dyn] = self.actors.actor[prim[dyn] - self.n_static]
        return out

    def _run(self, query: str, scene, origins, directions, tfar):
        """One ray query of the backend (intersect, distance or occluded); tfar is overwritten
        with hit distances."""
        if self.ray_log is not None:
            self.ray_log.append((query, scene, origins, directions, tfar.copy()))
        return getattr(self.backend, query)(scene, origins, directions, tfar)

    def cast(
        self,
        origins: np.ndarray,
        directions: np.ndarray,
        max_dist_m: float,
        actor_rays: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """First hits of rays: (N, 3) float32 origins and unit directions, world frame.

        Args:
            actor_rays: indices of the rays that may hit an agent (the sensor knows from the
                agents' boxes or bounding spheres); None: all. Only these are cast into the
                actor scene, bounded by their static hit.
        Returns:
            dist_m (N,) float32 (inf: no hit within max_dist_m), prim (N,) int32 (-1: none).
        """
        dist = np.full(len(origins), max_dist_m, np.float32)
        prim = self._run("intersect", self.static_embree, origins, directions, dist)
        rays, actor_prim, actor_dist = self._actor_hits(origins, directions, dist, actor_rays)
        prim[rays] = actor_prim + self.n_static
        dist[rays] = actor_dist
        dist[prim < 0] = np.inf
        return dist, prim

    def _actor_hits(
        self,
        origins: np.ndarray,
        directions: np.ndarray,
        dist: np.ndarray,
        actor_rays: np.ndarray | None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cast the rays `actor_rays` (all if None) against the actors, each only up to its
        static hit `dist`: (indices of the rays that hit an actor first (K,), the actor
        primitive each hit (K,), the hit distances (K,) m)."""
        none = np.zeros(0, np.int64)
        if self.actor_embree is None:
            return none, none, np.zeros(0, np.float32)
        idx = np.arange(len(origins)) if actor_rays is None else actor_rays
        if not len(idx):
            return none, none, np.zeros(0, np.float32)
        bound = dist[idx]
        dirs = np.take(directions, idx, axis=0)
        prim = self._run("intersect", self.actor_embree, take_rows(origins, idx), dirs, bound)
        hit = prim >= 0
        return idx[hit], prim[hit], bound[hit]

    def distances(
        self,
        origins: np.ndarray,
        directions: np.ndarray,
        max_dist_m: float,
        actor_rays: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Like `cast` but without the static primitive (a cheaper Embree query, what the
        LiDAR needs): returns dist_m (N,) float32 (inf: no hit) and actor (N,) int32, the index
        into `agents` of the agent hit first, -1 for static hits and misses."""
        n = len(origins)
        dist = np.full(n, max_dist_m, np.float32)
        self._run("distance", self.static_embree, origins, directions, dist)
        actor = np.full(n, -1, np.int32)
        rays, actor_prim, actor_dist = self._actor_hits(origins, directions, dist, actor_rays)
        actor[rays] = self.actors.actor[actor_prim]
        dist[rays] = actor_dist
        dist[dist >= max_dist_m] = np.inf
        return dist, actor

    def occluded(
        self,
        origins: np.ndarray,
        directions: np.ndarray,
        max_dist_m: float,
        actor_rays: np.ndarray | None = None,
    ) -> np.ndarray:
        """(N,) bool: does anything lie along each ray within max_dist_m (shadow rays).

        Args:
            directions: (N, 3) float32, or (1, 3) for one direction shared by all rays.
            actor_rays: indices of the rays that may pass an agent; None: all.
        """
        bound = np.full(len(origins), max_dist_m, np.float32)
        hit = self._run("occluded", self.static_embree, origins, directions, bound)
        if self.actor_embree is not None:
            idx = np.flatnonzero(~hit) if actor_rays is None else actor_rays[~hit[actor_rays]]
            if len(idx):
                d = np.full(len(idx), max_dist_m, np.float32)
                dirs = directions if len(directions) == 1 else np.take(directions, idx, axis=0)
                a = self._run("occluded", self.actor_embree, take_rows(origins, idx), dirs, d)
                hit[idx[a]] = True
        return hit


CELL_M = 60.0
"""The town is cut into square cells of this side; the static Embree scene of a cell holds every
tile within the sensors' reach of any point in it, so it serves the ego anywhere in the cell."""
CELL_CACHE_SIZE = 64  # committed cell scenes kept per process (LRU): ~3 MB each

_cells: OrderedDict[tuple, tuple] = OrderedDict()
cell_commits = 0  # how many cell scenes this process has committed (tests, bench)


def _cell_scene(
    static: StaticScene, cell: tuple[int, int], radius_m: float, tiles_fn, backend
) -> tuple:
    """(ray scene, normals, colour, material, tag) of the static tiles within `radius_m` of
    cell `cell`'s centre, built by `backend` on first use and kept per process (LRU), so every
    episode in a worker that drives through the cell reuses it."""
    global cell_commits
    key = (id(static), cell, radius_m, backend.NAME)
    hit = _cells.get(key)
    if hit is not None and hit[0]() is static:
        _cells.move_to_end(key)
        return hit[1]
    st = static
    centre = (np.asarray(cell, np.float64) + 0.5) * CELL_M
    tiles = tiles_fn(centre, radius_m)
    starts, ends = st.tile_start[tiles], st.tile_start[tiles + 1]
    lens = ends - starts
    idx = np.repeat(starts - np.concatenate([[0], np.cumsum(lens)[:-1]]), lens)
    idx += np.arange(int(lens.sum()))
    part = (
        backend.Scene(st.triangles_m[idx]),
        st.normals[idx],
        st.colour_rgb[idx],
        st.material[idx],
        st.tag[idx],
    )
    cell_commits += 1
    _cells[key] = (weakref.ref(static), part)
    while len(_cells) > CELL_CACHE_SIZE:
        _cells.popitem(last=False)
    return part


class SceneBuilder:
    """Builds each frame's `FrameScene` from a static scene.

    Static part: the Embree scene of the CELL_M cell the ego is in, holding every tile within
    `reach_m` (the longer of the LiDAR and camera ranges, plus the mounts' offset) of any point
    of the cell, so the sensors' reach is always covered; cell scenes are committed once per
    process and reused by later frames and episodes (`_cell_scene`). The actor scene is built
    every frame from the agents within reach (never the ego). `raycaster`: RAYCASTERS.
    """

    def __init__(self, static: StaticScene, reach_m: float, raycaster: str = "embree"):
        self.static = static
        self.reach_m = reach_m
        self.backend = ray_backend(raycaster)
        self._centres = static.tile_centres_m()
        self._nonempty = np.diff(static.tile_start) > 0
        self._cell: tuple[int, int] | None = None
        self._static = None
        self.rebuilds = 0  # cell changes (a cached cell costs no commit: see cell_commits)

    def visible_tiles(self, xy_m: np.ndarray, radius_m: float) -> np.ndarray:
        """Indices of the non-empty tiles holding a triangle within radius_m of xy_m."""
        d = self._centres - xy_m
        r = np.hypot(d[:, 0], d[:, 1])
        return np.flatnonzero((r <= radius_m + self.static.tile_reach_m) & self._nonempty)

    def _static_part(self, pose: Pose):
        cell = (math.floor(pose.x_m / CELL_M), math.floor(pose.y_m / CELL_M))
        if cell != self._cell:
            radius = self.reach_m + CELL_M / math.sqrt(2.0) + 1e-3  # centre to corner
            self._static = _cell_scene(self.static, cell, radius, self.visible_tiles, self.backend)
            self._cell = cell
            self.rebuilds += 1
        return self._static

    def build(self, frame: FrameState) -> FrameScene:
        static_scene, normals, colour, material, tag = self._static_part(frame.ego.pose)
        ex, ey = frame.ego.pose.x_m, frame.ego.pose.y_m
        agents = tuple(
            a
            for a in frame.agents
            if math.hypot(a.pose.x_m - ex, a.pose.y_m - ey) <= self.reach_m + a.length_m
        )
        actors = actor_mesh(agents)
        boxes = np.array(
            [
                (a.pose.x_m, a.pose.y_m, a.pose.yaw_rad, a.length_m, a.width_m, a.height_m)
                for a in agents
            ],
            np.float64,
        ).reshape(-1, 6)
        return FrameScene(
            backend=self.backend,
            static_embree=static_scene,
            actor_embree=(
                self.backend.Scene(actors.triangles_m) if len(actors.triangles_m) else None
            ),
            static_normals=normals,
            static_colour_rgb=colour,
            static_material=material,
            static_tag=tag,
            actors=actors,
            n_static=len(normals),
            agents=agents,
            actor_boxes=boxes,
        )


class SensorRays:
    """A sensor's fixed fan of rays, mounted at (mount_x_m, 0, mount_z_m) in the ego frame.

    The ego-frame directions are kept as three contiguous float32 columns, and one compiled
    pass (`_rotate`) turns them into the world frame each frame (0.05 ms for 64k rays against
    0.13 ms for the six numpy passes it replaced). Identical values: the same float32
    operations, elementwise, without fused multiply-adds.
    """

    def __init__(self, directions_ego: np.ndarray, mount_x_m: float, mount_z_m: float):
        d = np.asarray(directions_ego, np.float32)
        self.x, self.y, self.z = (np.ascontiguousarray(d[:, k]) for k in range(3))
        self.mount_x_m, self.mount_z_m = mount_x_m, mount_z_m

    def __len__(self) -> int:
        return len(self.x)

    def world(self, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        """World-frame (origins, directions) of the rays for the ego at `pose`, each (N, 3)
        float32. The origins are one point repeated by a zero stride (no copy): read them,
        never write into them."""
        c, s = np.float32(math.cos(pose.yaw_rad)), np.float32(math.sin(pose.yaw_rad))
        dirs = np.empty((len(self.x), 3), np.float32)
        _rotate(self.x, self.y, self.z, c, s, dirs)
        ox, oy = pose.world_from_ego(np.array([[self.mount_x_m, 0.0]]))[0]
        origin = np.array([ox, oy, self.mount_z_m], np.float32)
        return repeat_rows(origin, len(dirs)), dirs


@numba.njit(cache=True, nogil=True)
def _rotate(x, y, z, c, s, out):
    """out (N, 3) float32 = the ego-frame directions (x, y, z columns) turned by the yaw whose
    cosine and sine are the float32 c, s: (x c - y s, x s + y c, z)."""
    for i in range(x.shape[0]):
        out[i, 0] = x[i] * c - y[i] * s
        out[i, 1] = x[i] * s + y[i] * c
        out[i, 2] = z[i]


def take_rows(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Rows `idx` of (N, 3) `a`; a zero-stride `a` (one repeated origin) stays one."""
    if a.strides[0] == 0:
        return repeat_rows(a[0], len(idx))
    return np.take(a, idx, axis=0)  # ~4x faster than fancy indexing for rows


def repeat_rows(row: np.ndarray, n: int) -> np.ndarray:
    """(3,) float32 -> an (n, 3) view of it repeated by a zero stride (read-only use; the Embree
    queries read it as one shared origin, and it saves a 0.3 ms copy per 64k rays)."""
    return np.lib.stride_tricks.as_strided(row, (n, 3), (0, row.strides[0]))
