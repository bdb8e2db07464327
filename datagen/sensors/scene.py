"""The 3D scene the sensors see: a static mesh per town and the actors of one frame.

World frame throughout (SUMO network coordinates, metres, x east, y north, z up; the network is
flattened to z = 0, elevations are ignored). Every triangle carries a `Material`, a base colour
(RGB, what the camera shades) and, for dynamic triangles, the index of its actor (what the LiDAR
counts returns per box with).

Static mesh (built once per network from sumolib, cached on disk under
`<cache>/scenes/<network sha256>-v<SCENE_VERSION>.npz`):

- road surface: every non-sidewalk lane as a quad strip, junction shapes (earcut);
- lane markings (0.15 m, 2 cm above the road): dashed separators between same-direction lanes,
  solid centre and edge lines, stop lines at signalised and stop-controlled entries, zebra
  stripes on pedestrian crossings;
- sidewalks and walking areas raised 0.12 m, with curbs (their side walls);
- terrain (grass) as one quad per tile under everything, 200 m beyond the network;
- buildings (extruded rectangles of varied size, height and colour) in rows along the roads,
  set back from the sidewalk, never on a road, sidewalk or junction;
- a traffic-light pole with a signal head (three lamps facing the approach) at the near and far
  right corner of every signalised entry, a stop-sign post at every stop-controlled entry
  (the furniture and buildings: datagen/sensors/furniture.py; the polyline and triangle
  helpers: datagen/sensors/polyline.py).

Triangles are sorted into square tiles (TILE_M) by centroid; each tile knows how far its
triangles reach from its centre (what datagen/sensors/raycast.py culls by). The BEV polygons the
labels are painted from are kept beside the mesh as a `LabelMap` (datagen/sensors/labelmap.py).
"""

from __future__ import annotations

import hashlib
import math
import os
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from datagen.sensors import furniture, polyline
from datagen.sensors.labelmap import LabelMap
from datagen.sensors.mesh import Material, MeshBuilder, triangle_normals

SCENE_VERSION = 2  # bump to invalidate every cached static scene after a change here
# 2: each signal head knows its traffic light and the links it shows (head_tls, head_link_*)
TILE_M = 32.0  # culling tile size

SIDEWALK_HEIGHT_M = 0.12
MARKING_Z_M = 0.02  # markings float above the road so they win the depth test
TERRAIN_Z_M = -0.03  # grass just below the road surface
TERRAIN_MARGIN_M = 200.0  # grass beyond the network's bounding box
MARKING_WIDTH_M = 0.15
DASH_M, DASH_GAP_M = 3.0, 6.0  # dashed lane separator: 3 m line, 6 m gap
STOP_LINE_WIDTH_M = 0.4
ZEBRA_STRIPE_M, ZEBRA_PERIOD_M = 0.5, 1.0
MAX_SEGMENT_M = 8.0  # lane strips are cut into pieces no longer than this (cheap culling)


# Street furniture (m).
FURNITURE_SIDE_OFFSET_M = 1.0  # from the rightmost lane's outer edge


_VEHICLE_CLASSES = ("passenger", "bus", "truck", "delivery", "taxi", "coach", "trailer")


# ------------------------------------------------------------------------------------------
# The static scene


@dataclass(frozen=True)
class StaticScene:
    """Everything in a town that does not move, world frame, culling tiles and BEV polygons.

    Attributes:
        triangles_m: (T, 3, 3) float32, vertices of each triangle, m, world frame; sorted by tile.
        normals: (T, 3) float32 unit normals.
        colour_rgb: (T, 3) uint8 base colour.
        material: (T,) uint8 `Material`.
        tag: (T,) int32; for LAMP triangles `3 * head + slot` (slot 0 red, 1 yellow, 2 green),
            else -1.
        tile_origin_m: (2,) float64 world (x, y) of the corner of tile (0, 0).
        tile_shape: (2,) int64 number of tiles along x and y.
        tile_start: (nx * ny + 1,) int64, tile k holds triangles tile_start[k]:tile_start[k+1]
            (k = ix * ny + iy).
        tile_reach_m: (nx * ny,) float32, how far any triangle of the tile reaches from the tile's
            centre in the plane, m.
        head_xy_m: (H, 2) float32 signal-head positions, world frame.
        head_yaw_rad: (H,) float32 the direction each head faces (towards its approach).
        head_tls: (H,) str, the SUMO traffic light each head belongs to ("" if unknown).
        head_link_start: (H + 1,) int64, head h shows the links
            head_link_index[head_link_start[h]:head_link_start[h+1]] of its traffic light:
            every link leaving its approach edge's car lanes (indices into the light's state
            string, libsumo trafficlight.getRedYellowGreenState).
        head_link_index: (L,) int32.
        label_map: the BEV polygons the semantic labels are painted from.
        network_sha256: the network this scene was built from.
    """

    triangles_m: np.ndarray
    normals: np.ndarray
    colour_rgb: np.ndarray
    material: np.ndarray
    tag: np.ndarray
    tile_origin_m: np.ndarray
    tile_shape: np.ndarray
    tile_start: np.ndarray
    tile_reach_m: np.ndarray
    head_xy_m: np.ndarray
    head_yaw_rad: np.ndarray
    head_tls: np.ndarray
    head_link_start: np.ndarray
    head_link_index: np.ndarray
    label_map: LabelMap
    network_sha256: str

    @property
    def n_triangles(self) -> int:
        return len(self.triangles_m)

    def tile_centres_m(self) -> np.ndarray:
        """(nx * ny, 2) world centres of the tiles, in tile_start order."""
        nx, ny = (int(v) for v in self.tile_shape)
        ix, iy = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
        c = np.stack([ix.ravel(), iy.ravel()], 1) * TILE_M + TILE_M / 2
        return c + self.tile_origin_m


def _is_sidewalk(perms: set[str]) -> bool:
    return "pedestrian" in perms and not any(c in perms for c in _VEHICLE_CLASSES)


def build_static_scene(net_path: Path | str, network_sha256: str = "") -> StaticScene:
    """Read a SUMO network with sumolib and build its static mesh, tiles and BEV polygons.

    Deterministic: the building layout is drawn from a Generator seeded by the network's hash.
    """
    import sumolib
    from shapely import Polygon, STRtree

    net = sumolib.net.readNet(
        str(net_path), withInternal=True, withPedestrianConnections=True, withPrograms=False
    )
    sha = network_sha256 or hashlib.sha256(Path(net_path).read_bytes()).hexdigest()
    rng = np.random.default_rng(int(sha[:12], 16))
    b = MeshBuilder()
    bev: list[tuple[int, np.ndarray]] = []  # (class, ring)
    cutouts: list[np.ndarray] = []
    occupied: list[np.ndarray] = []  # rings nothing may be built on
    heads: list[tuple[float, float, float]] = []  # x, y, facing yaw
    head_links: list[tuple[str, tuple[int, ...]]] = []  # per head: light id, link indices
    stop_posts: list[tuple[float, float, float]] = []

    edges = net.getEdges(withInternal=True)
    pairs = {
        (e.getFromNode().getID(), e.getToNode().getID()) for e in edges if e.getFunction() == ""
    }

    def lane_xy(lane) -> np.ndarray:
        return polyline.dedupe(np.asarray(lane.getShape(), np.float64)[:, :2])

    for edge in edges:
        fn = edge.getFunction()
        if fn == "walkingarea":
            for lane in edge.getLanes():
                ring = lane_xy(lane)
                if len(ring) < 3:
                    continue
                b.add(polyline.polygon_triangles(ring, SIDEWALK_HEIGHT_M), Material.SIDEWALK)
                b.add(polyline.walls(ring, 0.0, SIDEWALK_HEIGHT_M), Material.SIDEWALK)
                cutouts.append(ring)
                occupied.append(ring)
            continue
        if fn == "crossing":
            for lane in edge.getLanes():
                p = lane_xy(lane)
                if len(p) < 2:
                    continue
                length, w = polyline.length(p), lane.getWidth()
                for s0 in np.arange(0.25, length - ZEBRA_STRIPE_M + 1e-6, ZEBRA_PERIOD_M):
                    piece = polyline.substring(p, s0, s0 + ZEBRA_STRIPE_M)
                    if piece is not None and len(piece) >= 2:
                        # 0.5 m along the walking line, the crossing's width across it.
                        L, R = polyline.strip(piece, 0.5 * (w - 0.4))
                        quad = np.array([L[0], L[-1], R[-1], R[0]])
                        b.add(polyline.polygon_triangles(quad, MARKING_Z_M), Material.MARKING)
            continue
        lanes = edge.getLanes()
        car_lanes = [ln for ln in lanes if "passenger" in ln.getPermissions()]
        for lane in lanes:
            p = lane_xy(lane)
            if len(p) < 2:
                continue
            perms = lane.getPermissions()
            w = lane.getWidth()
            p = polyline.resample(p, MAX_SEGMENT_M)
            L, R = polyline.strip(p, w / 2)
            ring = np.concatenate([L, R[::-1]])
            occupied.append(ring)
            if _is_sidewalk(perms):
                b.add(polyline.strip_triangles(L, R, SIDEWALK_HEIGHT_M), Material.SIDEWALK)
                # the curb: only the road side (SUMO's lane 0, the sidewalk, is the rightmost)
                b.add(polyline.walls(L, 0.0, SIDEWALK_HEIGHT_M, closed=False), Material.SIDEWALK)
                cutouts.append(ring)
                continue
            b.add(polyline.strip_triangles(L, R, 0.0), Material.ROAD)
            if "passenger" in perms:
                bev.append((1, ring))
        if fn != "" or not car_lanes:
            continue
        # Markings of a normal edge with lanes open to cars (SUMO lane 0 is the rightmost).
        car_lanes.sort(key=lambda ln: ln.getIndex())
        for i, lane in enumerate(car_lanes):
            p = polyline.resample(lane_xy(lane), MAX_SEGMENT_M)
            if len(p) < 2:
                continue
            w = lane.getWidth()
            lines = []
            if i + 1 < len(car_lanes) and car_lanes[i + 1].getIndex() == lane.getIndex() + 1:
                sep = polyline.offset(p, w / 2)
                total = polyline.length(sep)
                for s0 in np.arange(0.0, total, DASH_M + DASH_GAP_M):
                    lines.append(polyline.substring(sep, s0 + 1.0, s0 + 1.0 + DASH_M))
            else:  # leftmost: centre line (a double line with the opposite edge's) or edge line
                lines.append(polyline.offset(p, w / 2 - 0.1 - MARKING_WIDTH_M / 2))
            if i == 0:
                lines.append(polyline.offset(p, -(w / 2 - 0.2 - MARKING_WIDTH_M / 2)))
            for line in lines:
                if line is None or len(line) < 2:
                    continue
                L, R = polyline.strip(line, MARKING_WIDTH_M / 2)
                b.add(polyline.strip_triangles(L, R, MARKING_Z_M), Material.MARKING)
                bev.append((2, np.concatenate([L, R[::-1]])))
            # Stop line and furniture at a controlled entry.
            conns = lane.getOutgoing()
            tls = any(c.getTLSID() for c in conns)
            stop = any(c.getState() in ("s", "w") for c in conns)
            if not (tls or stop) or polyline.length(p) < 2 * STOP_LINE_WIDTH_M:
                continue
            total = polyline.length(p)
            piece = polyline.substring(p, total - STOP_LINE_WIDTH_M - 0.1, total - 0.1)
            if piece is not None and len(piece) >= 2:
                L, R = polyline.strip(piece, w / 2 - 0.1)
                b.add(polyline.strip_triangles(L, R, MARKING_Z_M), Material.MARKING)
                bev.append((2, np.concatenate([L, R[::-1]])))
            if i == 0:  # furniture once per edge, beside the rightmost car lane
                end, prev = p[-1], p[-2]
                heading = math.atan2(end[1] - prev[1], end[0] - prev[0])
                right = np.array([math.sin(heading), -math.cos(heading)])
                fwd = np.array([math.cos(heading), math.sin(heading)])
                # distance to the outer edge of the edge's lane 0: on a sidewalk, 0.5 m inside
                # its outer edge; without one, FURNITURE_SIDE_OFFSET_M beyond the road.
                outer = w / 2 + sum(
                    ln.getWidth() for ln in lanes if ln.getIndex() < lane.getIndex()
                )
                if _is_sidewalk(lanes[0].getPermissions()) and lane.getIndex() > 0:
                    side = outer - 0.5
                else:
                    side = outer + FURNITURE_SIDE_OFFSET_M
                near = end + right * side - fwd * 0.5
                if tls:
                    links = [
                        (c.getTLSID(), c.getTLLinkIndex())
                        for ln in car_lanes
                        for c in ln.getOutgoing()
                        if c.getTLSID()
                    ]
                    tls_id = links[0][0] if links else ""
                    shown = (tls_id, tuple(sorted({i for t, i in links if t == tls_id})))
                    heads.append((near[0], near[1], heading + math.pi))
                    head_links.append(shown)
                    node_shape = np.asarray(edge.getToNode().getShape(), np.float64)
                    depth = _junction_depth(end, fwd, node_shape)
                    if depth > 3.0:
                        far = end + fwd * (depth + 2.0) + right * side
                        heads.append((far[0], far[1], heading + math.pi))
                        head_links.append(shown)
                elif stop:
                    stop_posts.append((near[0], near[1], heading + math.pi))

    for node in net.getNodes():
        shape = np.asarray(node.getShape(), np.float64)
        if len(shape) >= 3:
            ring = shape[:, :2]
            b.add(polyline.polygon_triangles(ring, 0.0), Material.ROAD)
            bev.append((1, ring))
            occupied.append(ring)

    # Furniture: poles, heads (with lamps facing the approach), stop signs.
    for k, (x, y, yaw) in enumerate(heads):
        furniture.add_signal(b, k, x, y, yaw)
    for x, y, yaw in stop_posts:
        furniture.add_stop_sign(b, x, y, yaw)
    footprints = [
        np.array([[x - 0.5, y - 0.5], [x + 0.5, y - 0.5], [x + 0.5, y + 0.5]])
        for x, y, _ in heads + stop_posts
    ]

    # Buildings and trees in rows along the roads, off every road, sidewalk and junction.
    occ_polys = [Polygon(r) for r in occupied if len(r) >= 3]
    furniture.add_buildings(b, edges, pairs, STRtree(occ_polys), footprints, rng)

    # BEV polygons in painting order: drivable, cut-outs, markings.
    rings = [r for c, r in bev if c == 1] + cutouts + [r for c, r in bev if c == 2]
    classes = (
        [1] * sum(c == 1 for c, _ in bev) + [0] * len(cutouts) + [2] * sum(c == 2 for c, _ in bev)
    )
    return assemble_static_scene(b, rings, classes, heads, sha, head_links=head_links)


def assemble_static_scene(
    b: MeshBuilder,
    bev_rings: Sequence[np.ndarray] = (),
    bev_classes: Sequence[int] = (),
    heads: Sequence[tuple[float, float, float]] = (),
    network_sha256: str = "",
    terrain: bool = True,
    head_links: Sequence[tuple[str, Sequence[int]]] = (),
) -> StaticScene:
    """Finish a static scene from accumulated triangles: grass terrain under everything (one
    quad per tile, TERRAIN_MARGIN_M beyond), tiles, normals and the BEV polygons (painted in
    the given order). `head_links`: per head, its traffic light's id and the link indices it
    shows (default: none). Also how tests build small hand-made scenes."""
    tris = np.concatenate(b.tris)
    lo = tris[..., :2].reshape(-1, 2).min(0) - TERRAIN_MARGIN_M
    hi = tris[..., :2].reshape(-1, 2).max(0) + TERRAIN_MARGIN_M
    origin = np.floor(lo / TILE_M) * TILE_M
    shape = np.ceil((hi - origin) / TILE_M).astype(np.int64)
    if terrain:
        ix, iy = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
        x0 = origin[0] + ix.ravel() * TILE_M
        y0 = origin[1] + iy.ravel() * TILE_M
        quads = np.stack(
            [
                np.stack([x0, y0], 1),
                np.stack([x0 + TILE_M, y0], 1),
                np.stack([x0 + TILE_M, y0 + TILE_M], 1),
                np.stack([x0, y0 + TILE_M], 1),
            ],
            1,
        )
        q = np.concatenate([quads, np.full(quads.shape[:2] + (1,), TERRAIN_Z_M)], 2)
        b.add(np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]]), Material.TERRAIN)

    tris = np.concatenate(b.tris)
    material = np.concatenate(b.mat)
    colour = np.concatenate(b.rgb)
    tag = np.concatenate(b.tag)

    # Tiles: sort by the tile of the centroid; reach = farthest vertex from the tile's centre.
    cen = tris[..., :2].mean(1)
    tix = np.clip(((cen - origin) // TILE_M).astype(np.int64), 0, shape - 1)
    tid = tix[:, 0] * shape[1] + tix[:, 1]
    order = np.argsort(tid, kind="stable")
    tris, material, colour, tag, tid = (
        tris[order],
        material[order],
        colour[order],
        tag[order],
        tid[order],
    )
    n_tiles = int(shape[0] * shape[1])
    tile_start = np.searchsorted(tid, np.arange(n_tiles + 1)).astype(np.int64)
    centres = origin + (np.stack([tid // shape[1], tid % shape[1]], 1) + 0.5) * TILE_M
    reach_tri = np.linalg.norm(tris[..., :2] - centres[:, None, :], axis=2).max(1)
    reach = np.zeros(n_tiles, np.float32)
    np.maximum.at(reach, tid, reach_tri.astype(np.float32))

    head_arr = np.array(heads, np.float64).reshape(-1, 3)
    links = list(head_links) or [("", ())] * len(head_arr)
    link_start = np.concatenate([[0], np.cumsum([len(i) for _, i in links])]).astype(np.int64)
    link_index = np.array([i for _, idx in links for i in idx], np.int32)
    return StaticScene(
        triangles_m=tris.astype(np.float32),
        normals=triangle_normals(tris),
        colour_rgb=colour,
        material=material,
        tag=tag,
        tile_origin_m=origin.astype(np.float64),
        tile_shape=shape.astype(np.int64),
        tile_start=tile_start,
        tile_reach_m=reach,
        head_xy_m=head_arr[:, :2].astype(np.float32),
        head_yaw_rad=head_arr[:, 2].astype(np.float32),
        head_tls=np.array([t for t, _ in links], dtype=str).reshape(-1),
        head_link_start=link_start,
        head_link_index=link_index,
        label_map=LabelMap.from_rings(bev_rings, bev_classes),
        network_sha256=network_sha256,
    )


def _junction_depth(start: np.ndarray, fwd: np.ndarray, shape: np.ndarray) -> float:
    """How far a ray from `start` along `fwd` runs inside the junction polygon `shape`."""
    if len(shape) < 3:
        return 0.0
    from shapely import LineString, Polygon

    poly = Polygon(shape[:, :2])
    if not poly.is_valid:
        poly = poly.buffer(0)
    ray = LineString([start - fwd * 0.5, start + fwd * 80.0])
    inter = poly.intersection(ray)
    return float(inter.length) if not inter.is_empty else 0.0


# ------------------------------------------------------------------------------------------
# Disk and process cache


def scene_cache_dir() -> Path:
    """<cache>/scenes: `$IIDSU_CACHE/scenes` if set, else ~/.cache/iidsu/scenes."""
    base = os.environ.get("IIDSU_CACHE")
    return (Path(base) if base else Path.home() / ".cache" / "iidsu") / "scenes"


# The cache file's keys: the mesh fields by name, the label map's as before the split.
_LABEL_MAP_KEYS = {
    "xy_m": "bev_xy_m",
    "start": "bev_start",
    "class_id": "bev_class",
    "bbox_m": "bev_bbox_m",
}
_MESH_FIELDS = tuple(
    f.name for f in fields(StaticScene) if f.name not in ("label_map", "network_sha256")
)


def _to_arrays(scene: StaticScene) -> dict[str, np.ndarray]:
    out = {name: getattr(scene, name) for name in _MESH_FIELDS}
    out.update({k: getattr(scene.label_map, f) for f, k in _LABEL_MAP_KEYS.items()})
    return out


def _from_arrays(z, sha: str) -> StaticScene:
    label_map = LabelMap(**{f: z[k] for f, k in _LABEL_MAP_KEYS.items()})
    return StaticScene(
        **{name: z[name] for name in _MESH_FIELDS}, label_map=label_map, network_sha256=sha
    )


_loaded: OrderedDict[str, StaticScene] = OrderedDict()
LOADED_TOWNS = 8  # static scenes kept per process (LRU; all built-in towns: ~100 MB at most)


def load_static_scene(net_path: Path | str, cache_dir: Path | None = None) -> StaticScene:
    """The static scene of a network: from this process's memory, else the disk cache, else
    built (and cached atomically, so parallel workers may race to build it)."""
    from datagen.world.towns import network_sha256

    sha = network_sha256(Path(net_path))
    key = f"{sha}-v{SCENE_VERSION}"
    if key in _loaded:
        _loaded.move_to_end(key)
        return _loaded[key]
    cache = Path(cache_dir) if cache_dir is not None else scene_cache_dir()
    path = cache / f"{key}.npz"
    scene = None
    if path.exists():
        try:
            with np.load(path, allow_pickle=False) as z:
                scene = _from_arrays(z, sha)
        except (OSError, ValueError, KeyError):
            scene = None  # a damaged cache entry is rebuilt
    if scene is None:
        scene = build_static_scene(net_path, sha)
        cache.mkdir(parents=True, exist_ok=True)
        part = path.with_name(f".{path.stem}.{os.getpid()}.part.npz")
        np.savez(part, **_to_arrays(scene))
        os.replace(part, path)
    _loaded[key] = scene  # kept, so that raycast reuses its cell scenes across episodes
    while len(_loaded) > LOADED_TOWNS:
        _loaded.popitem(last=False)
    return scene
