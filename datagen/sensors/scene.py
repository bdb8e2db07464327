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
  right corner of every signalised entry, a stop-sign post at every stop-controlled entry.

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

import mapbox_earcut
import numpy as np

from datagen.sensors.labelmap import LabelMap
from datagen.sensors.mesh import Material, boxes_triangles, triangle_normals

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

# Buildings: rows along the roads, set back from the outer lane boundary.
BUILDING_SETBACK_M = 3.0
BUILDING_FRONTAGE_M = (8.0, 18.0)
BUILDING_DEPTH_M = (8.0, 16.0)
BUILDING_GAP_M = (0.5, 4.0)
BUILDING_CLEARANCE_M = 1.0  # from any road, sidewalk or junction polygon
BUILDING_KEEP = 0.85  # share of the slots that get a building (the rest: a tree or nothing)
TREE_KEEP = 0.5

# Street furniture (m).
POLE_HEIGHT_M = 4.6
POLE_SIDE_M = 0.2
HEAD_SIZE_M = (0.45, 0.45, 1.35)  # depth, width, height of a signal head
HEAD_BOTTOM_M = 3.2
LAMP_SIZE_M = 0.34
SIGN_POST_HEIGHT_M = 2.1
SIGN_SIZE_M = 0.75
FURNITURE_SIDE_OFFSET_M = 1.0  # from the rightmost lane's outer edge


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
FACADES = np.array(
    [
        (196, 180, 150),
        (170, 160, 150),
        (150, 84, 64),
        (210, 205, 195),
        (120, 100, 85),
        (140, 150, 160),
        (185, 160, 120),
        (110, 118, 126),
        (200, 190, 170),
        (165, 110, 80),
    ],
    np.uint8,
)
ROOF_RGB = (95, 92, 90)
TRUNK_RGB = (90, 65, 45)
CANOPY_RGB = (55, 105, 45)

_VEHICLE_CLASSES = ("passenger", "bus", "truck", "delivery", "taxi", "coach", "trailer")


# ------------------------------------------------------------------------------------------
# Geometry helpers (all vectorised over points; z is added last)


def _resample(p: np.ndarray, max_seg_m: float) -> np.ndarray:
    """(n, 2) polyline -> the same polyline with points inserted so that no segment is longer
    than `max_seg_m`."""
    d = np.linalg.norm(np.diff(p, axis=0), axis=1)
    k = np.maximum(1, np.ceil(d / max_seg_m).astype(int))
    if (k == 1).all():
        return p
    out = [p[i] + (p[i + 1] - p[i]) * (np.arange(k[i])[:, None] / k[i]) for i in range(len(d))]
    return np.concatenate([*out, p[-1:]])


def _dedupe(p: np.ndarray) -> np.ndarray:
    keep = np.ones(len(p), bool)
    keep[1:] = np.linalg.norm(np.diff(p, axis=0), axis=1) > 1e-3
    return p[keep]


def _vertex_normals(p: np.ndarray) -> np.ndarray:
    """(n, 2) polyline -> (n, 2) left normals at the vertices, mitred (scaled so that offset
    lines stay parallel to the segments), mitre capped at 2x."""
    seg = np.diff(p, axis=0)
    seg /= np.maximum(np.linalg.norm(seg, axis=1, keepdims=True), 1e-9)
    nseg = np.stack([-seg[:, 1], seg[:, 0]], axis=1)
    n = np.empty_like(p)
    n[0], n[-1] = nseg[0], nseg[-1]
    if len(p) > 2:
        m = nseg[:-1] + nseg[1:]
        m /= np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-9)
        cos = np.clip((m * nseg[1:]).sum(1, keepdims=True), 0.5, 1.0)
        n[1:-1] = m / cos
    return n


def _offset(p: np.ndarray, d_m: float) -> np.ndarray:
    """Polyline offset `d_m` to its left (negative: right)."""
    return p + _vertex_normals(p) * d_m


def _substring(p: np.ndarray, s0: float, s1: float) -> np.ndarray | None:
    """The part of polyline `p` between arc lengths s0 and s1, or None if empty."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    s0, s1 = max(s0, 0.0), min(s1, s[-1])
    if s1 - s0 < 1e-3:
        return None
    inner = (s > s0) & (s < s1)
    a = np.array([np.interp(s0, s, p[:, 0]), np.interp(s0, s, p[:, 1])])
    b = np.array([np.interp(s1, s, p[:, 0]), np.interp(s1, s, p[:, 1])])
    return np.concatenate([a[None], p[inner], b[None]])


def _length(p: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def _strip(p: np.ndarray, half_w_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Left and right boundary (each (n, 2)) of a strip of half width `half_w_m` along p."""
    n = _vertex_normals(p) * half_w_m
    return p + n, p - n


def _strip_triangles(left: np.ndarray, right: np.ndarray, z_m: float) -> np.ndarray:
    """Quad strip between two (n, 2) boundaries -> (2(n-1), 3, 3) triangles at height z_m."""
    L = np.concatenate([left, np.full((len(left), 1), z_m)], axis=1)
    R = np.concatenate([right, np.full((len(right), 1), z_m)], axis=1)
    t1 = np.stack([R[:-1], R[1:], L[1:]], axis=1)
    t2 = np.stack([R[:-1], L[1:], L[:-1]], axis=1)
    return np.concatenate([t1, t2])


def _walls(ring: np.ndarray, z0_m: float, z1_m: float, closed: bool = True) -> np.ndarray:
    """Vertical quads along a (n, 2) polyline (closed: back to its start) from z0 to z1."""
    a = ring
    b = np.roll(ring, -1, axis=0) if closed else ring[1:]
    a = a if closed else ring[:-1]
    lo0 = np.concatenate([a, np.full((len(a), 1), z0_m)], 1)
    lo1 = np.concatenate([b, np.full((len(b), 1), z0_m)], 1)
    hi0 = np.concatenate([a, np.full((len(a), 1), z1_m)], 1)
    hi1 = np.concatenate([b, np.full((len(b), 1), z1_m)], 1)
    return np.concatenate([np.stack([lo0, lo1, hi1], 1), np.stack([lo0, hi1, hi0], 1)])


def _polygon_triangles(ring: np.ndarray, z_m: float) -> np.ndarray:
    """Simple polygon (n, 2) -> (k, 3, 3) triangles at height z_m (earcut)."""
    ring = _dedupe(np.asarray(ring, np.float64))
    if len(ring) > 3 and np.linalg.norm(ring[0] - ring[-1]) < 1e-3:
        ring = ring[:-1]
    if len(ring) < 3:
        return np.zeros((0, 3, 3))
    idx = mapbox_earcut.triangulate_float64(ring, np.array([len(ring)], np.uint32))
    v = np.concatenate([ring, np.full((len(ring), 1), z_m)], 1)
    return v[np.asarray(idx, np.int64).reshape(-1, 3)]


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
        return _dedupe(np.asarray(lane.getShape(), np.float64)[:, :2])

    for edge in edges:
        fn = edge.getFunction()
        if fn == "walkingarea":
            for lane in edge.getLanes():
                ring = lane_xy(lane)
                if len(ring) < 3:
                    continue
                b.add(_polygon_triangles(ring, SIDEWALK_HEIGHT_M), Material.SIDEWALK)
                b.add(_walls(ring, 0.0, SIDEWALK_HEIGHT_M), Material.SIDEWALK)
                cutouts.append(ring)
                occupied.append(ring)
            continue
        if fn == "crossing":
            for lane in edge.getLanes():
                p = lane_xy(lane)
                if len(p) < 2:
                    continue
                length, w = _length(p), lane.getWidth()
                for s0 in np.arange(0.25, length - ZEBRA_STRIPE_M + 1e-6, ZEBRA_PERIOD_M):
                    piece = _substring(p, s0, s0 + ZEBRA_STRIPE_M)
                    if piece is not None and len(piece) >= 2:
                        # 0.5 m along the walking line, the crossing's width across it.
                        L, R = _strip(piece, 0.5 * (w - 0.4))
                        quad = np.array([L[0], L[-1], R[-1], R[0]])
                        b.add(_polygon_triangles(quad, MARKING_Z_M), Material.MARKING)
            continue
        lanes = edge.getLanes()
        car_lanes = [ln for ln in lanes if "passenger" in ln.getPermissions()]
        for lane in lanes:
            p = lane_xy(lane)
            if len(p) < 2:
                continue
            perms = lane.getPermissions()
            w = lane.getWidth()
            p = _resample(p, MAX_SEGMENT_M)
            L, R = _strip(p, w / 2)
            ring = np.concatenate([L, R[::-1]])
            occupied.append(ring)
            if _is_sidewalk(perms):
                b.add(_strip_triangles(L, R, SIDEWALK_HEIGHT_M), Material.SIDEWALK)
                # the curb: only the road side (SUMO's lane 0, the sidewalk, is the rightmost)
                b.add(_walls(L, 0.0, SIDEWALK_HEIGHT_M, closed=False), Material.SIDEWALK)
                cutouts.append(ring)
                continue
            b.add(_strip_triangles(L, R, 0.0), Material.ROAD)
            if "passenger" in perms:
                bev.append((1, ring))
        if fn != "" or not car_lanes:
            continue
        # Markings of a normal edge with lanes open to cars (SUMO lane 0 is the rightmost).
        car_lanes.sort(key=lambda ln: ln.getIndex())
        for i, lane in enumerate(car_lanes):
            p = _resample(lane_xy(lane), MAX_SEGMENT_M)
            if len(p) < 2:
                continue
            w = lane.getWidth()
            lines = []
            if i + 1 < len(car_lanes) and car_lanes[i + 1].getIndex() == lane.getIndex() + 1:
                sep = _offset(p, w / 2)
                total = _length(sep)
                for s0 in np.arange(0.0, total, DASH_M + DASH_GAP_M):
                    lines.append(_substring(sep, s0 + 1.0, s0 + 1.0 + DASH_M))
            else:  # leftmost: centre line (a double line with the opposite edge's) or edge line
                lines.append(_offset(p, w / 2 - 0.1 - MARKING_WIDTH_M / 2))
            if i == 0:
                lines.append(_offset(p, -(w / 2 - 0.2 - MARKING_WIDTH_M / 2)))
            for line in lines:
                if line is None or len(line) < 2:
                    continue
                L, R = _strip(line, MARKING_WIDTH_M / 2)
                b.add(_strip_triangles(L, R, MARKING_Z_M), Material.MARKING)
                bev.append((2, np.concatenate([L, R[::-1]])))
            # Stop line and furniture at a controlled entry.
            conns = lane.getOutgoing()
            tls = any(c.getTLSID() for c in conns)
            stop = any(c.getState() in ("s", "w") for c in conns)
            if not (tls or stop) or _length(p) < 2 * STOP_LINE_WIDTH_M:
                continue
            total = _length(p)
            piece = _substring(p, total - STOP_LINE_WIDTH_M - 0.1, total - 0.1)
            if piece is not None and len(piece) >= 2:
                L, R = _strip(piece, w / 2 - 0.1)
                b.add(_strip_triangles(L, R, MARKING_Z_M), Material.MARKING)
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
            b.add(_polygon_triangles(ring, 0.0), Material.ROAD)
            bev.append((1, ring))
            occupied.append(ring)

    # Furniture: poles, heads (with lamps facing the approach), stop signs.
    for k, (x, y, yaw) in enumerate(heads):
        _add_signal(b, k, x, y, yaw)
    for x, y, yaw in stop_posts:
        _add_stop_sign(b, x, y, yaw)
    furniture = [
        np.array([[x - 0.5, y - 0.5], [x + 0.5, y - 0.5], [x + 0.5, y + 0.5]])
        for x, y, _ in heads + stop_posts
    ]

    # Buildings and trees in rows along the roads, off every road, sidewalk and junction.
    occ_polys = [Polygon(r) for r in occupied if len(r) >= 3]
    _add_buildings(b, edges, pairs, STRtree(occ_polys), furniture, rng)

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


def _add_signal(b: MeshBuilder, k: int, x: float, y: float, facing_rad: float) -> None:
    """Pole, head and three lamps (red on top) facing `facing_rad`; lamp tags 3k..3k+2."""
    pole = boxes_triangles(
        np.array([[x, y, POLE_HEIGHT_M / 2]]),
        np.array([[POLE_SIDE_M, POLE_SIDE_M, POLE_HEIGHT_M]]),
        np.array([facing_rad]),
    )[0]
    b.add(pole, Material.POLE)
    d, w, h = HEAD_SIZE_M
    f = np.array([math.cos(facing_rad), math.sin(facing_rad)])
    hx, hy = np.array([x, y]) + f * (POLE_SIDE_M / 2 + d / 2)
    head = boxes_triangles(
        np.array([[hx, hy, HEAD_BOTTOM_M + h / 2]]), np.array([[d, w, h]]), np.array([facing_rad])
    )[0]
    b.add(head, Material.POLE, rgb=(32, 32, 34))
    for slot in range(3):
        z = HEAD_BOTTOM_M + h * (5 - 2 * slot) / 6
        c = np.array([hx, hy]) + f * (d / 2 + 0.01)
        lamp = boxes_triangles(
            np.array([[c[0], c[1], z]]),
            np.array([[0.02, LAMP_SIZE_M, LAMP_SIZE_M]]),
            np.array([facing_rad]),
            faces=np.array([0, 1]),
        )[0]
        b.add(lamp, Material.LAMP, tag=3 * k + slot)


def _add_stop_sign(b: MeshBuilder, x: float, y: float, facing_rad: float) -> None:
    post = boxes_triangles(
        np.array([[x, y, SIGN_POST_HEIGHT_M / 2]]),
        np.array([[0.08, 0.08, SIGN_POST_HEIGHT_M]]),
        np.array([facing_rad]),
    )[0]
    b.add(post, Material.POLE)
    f = np.array([math.cos(facing_rad), math.sin(facing_rad)])
    c = np.array([x, y]) + f * 0.06
    # An octagon plate (two triangles per side) facing the approach.
    ang = np.deg2rad(22.5 + 45 * np.arange(8))
    r = SIGN_SIZE_M / 2 / math.cos(math.radians(22.5))
    side = np.array([-f[1], f[0]])
    zc = SIGN_POST_HEIGHT_M + SIGN_SIZE_M / 2 - 0.1
    ring = np.array([[*(c + side * r * math.cos(a)), zc + r * math.sin(a)] for a in ang])
    centre = np.array([*c, zc])
    plate = np.stack([np.repeat(centre[None], 8, 0), ring, np.roll(ring, -1, 0)], 1)
    b.add(plate, Material.SIGN)


def _add_buildings(b, edges, pairs, occ_tree, furniture, rng) -> None:
    from shapely import STRtree, polygons

    cand: list[np.ndarray] = []
    heights: list[float] = []
    for edge in edges:
        if edge.getFunction() != "":
            continue
        lanes = edge.getLanes()
        if not lanes:
            continue
        sides = [("right", lanes[0])]
        if (edge.getToNode().getID(), edge.getFromNode().getID()) not in pairs:
            sides.append(("left", lanes[-1]))
        for side, lane in sides:
            p = _dedupe(np.asarray(lane.getShape(), np.float64)[:, :2])
            if len(p) < 2:
                continue
            sign = -1.0 if side == "right" else 1.0
            total = _length(p)
            rows = 2 if rng.random() < 0.6 else 1
            depth0 = 0.0
            for _row in range(rows):
                depth = float(rng.uniform(*BUILDING_DEPTH_M))
                off = lane.getWidth() / 2 + BUILDING_SETBACK_M + depth0
                s = float(rng.uniform(0, 4))
                while s < total:
                    front = float(rng.uniform(*BUILDING_FRONTAGE_M))
                    piece = _substring(p, s, s + front)
                    s += front + float(rng.uniform(*BUILDING_GAP_M))
                    if piece is None or _length(piece) < 0.6 * front:
                        continue
                    a, c = piece[0], piece[-1]
                    t = (c - a) / max(np.linalg.norm(c - a), 1e-9)
                    n = np.array([-t[1], t[0]]) * sign  # away from the road
                    o0 = a + n * off
                    o1 = c + n * off
                    cand.append(np.array([o0, o1, o1 + n * depth, o0 + n * depth]))
                    u = rng.random()
                    h = (
                        rng.uniform(5, 12)
                        if u < 0.6
                        else rng.uniform(12, 28)
                        if u < 0.95
                        else rng.uniform(28, 50)
                    )
                    heights.append(float(h))
                depth0 += depth + float(rng.uniform(2.0, 6.0))
    if not cand:
        return
    polys = polygons(np.array(cand))
    # Reject footprints on roads/sidewalks/junctions/furniture (with clearance), then overlaps.
    clear = [p.buffer(BUILDING_CLEARANCE_M, join_style="mitre") for p in polys]
    hit = occ_tree.query(clear, predicate="intersects")
    bad = np.zeros(len(polys), bool)
    bad[hit[0]] = True
    if furniture:
        ft = STRtree(polygons(np.array(furniture)))
        bad[ft.query(clear, predicate="intersects")[0]] = True
    own = STRtree(polys)
    i, j = own.query(polys, predicate="intersects")
    neighbours: dict[int, list[int]] = {}
    for a, c in zip(i, j):
        if a != c:
            neighbours.setdefault(int(a), []).append(int(c))
    accepted = np.zeros(len(polys), bool)
    keep = rng.random(len(polys))
    trees = []
    for k in range(len(polys)):
        if bad[k] or any(accepted[m] for m in neighbours.get(k, ())):
            continue
        if keep[k] < BUILDING_KEEP:
            accepted[k] = True
        elif keep[k] < BUILDING_KEEP + (1 - BUILDING_KEEP) * TREE_KEEP:
            trees.append(cand[k].mean(0))
    idx = np.flatnonzero(accepted)
    if len(idx):
        fp = np.array([cand[k] for k in idx])  # (B, 4, 2)
        h = np.array([heights[k] for k in idx])
        facade = FACADES[rng.integers(len(FACADES), size=len(idx))]
        shade = rng.uniform(0.85, 1.1, size=(len(idx), 1))
        facade = np.clip(facade * shade, 0, 255).astype(np.uint8)
        z0 = np.zeros((len(idx), 4, 1))
        lo = np.concatenate([fp, z0], 2)
        hi = np.concatenate([fp, z0 + h[:, None, None]], 2)
        walls = []
        for e in range(4):
            f = (e + 1) % 4
            walls.append(np.stack([lo[:, e], lo[:, f], hi[:, f]], 1))
            walls.append(np.stack([lo[:, e], hi[:, f], hi[:, e]], 1))
        walls = np.stack(walls, 1)  # (B, 8, 3, 3)
        roof = np.stack(
            [
                np.stack([hi[:, 0], hi[:, 1], hi[:, 2]], 1),
                np.stack([hi[:, 0], hi[:, 2], hi[:, 3]], 1),
            ],
            1,
        )
        b.add(walls.reshape(-1, 3, 3), Material.BUILDING, rgb=np.repeat(facade, 8, 0))
        b.add(roof.reshape(-1, 3, 3), Material.BUILDING, rgb=ROOF_RGB)
    if trees:
        t = np.array(trees)
        n = len(t)
        trunk = boxes_triangles(
            np.concatenate([t, np.full((n, 1), 1.25)], 1),
            np.tile([0.35, 0.35, 2.5], (n, 1)),
            rng.uniform(0, np.pi, n),
        )
        size = rng.uniform(2.5, 4.5, n)
        canopy = boxes_triangles(
            np.concatenate([t, (2.3 + size / 2)[:, None]], 1),
            np.stack([size, size, size * 0.9], 1),
            rng.uniform(0, np.pi, n),
        )
        b.add(trunk.reshape(-1, 3, 3), Material.VEGETATION, rgb=TRUNK_RGB)
        green = np.clip(np.array(CANOPY_RGB) * rng.uniform(0.8, 1.2, (n, 1)), 0, 255).astype(
            np.uint8
        )
        b.add(canopy.reshape(-1, 3, 3), Material.VEGETATION, rgb=np.repeat(green, 12, 0))


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
