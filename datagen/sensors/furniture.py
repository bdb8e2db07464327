"""What stands beside the roads of the static scene (datagen/sensors/scene.py): traffic-light
poles with a head of three lamps facing their approach, stop-sign posts with an octagon plate,
and rows of buildings and trees along the roads, off every road, sidewalk, junction and piece of
furniture. World frame, metres; the layout is drawn from the Generator the scene passes in
(seeded by the network's hash), so a network always gets the same town.
"""

from __future__ import annotations

import math

import numpy as np

from datagen.sensors.mesh import Material, MeshBuilder, boxes_triangles
from datagen.sensors.polyline import dedupe, length, substring

# Street furniture (m).
POLE_HEIGHT_M = 4.6
POLE_SIDE_M = 0.2
HEAD_SIZE_M = (0.45, 0.45, 1.35)  # depth, width, height of a signal head
HEAD_BOTTOM_M = 3.2
LAMP_SIZE_M = 0.34
SIGN_POST_HEIGHT_M = 2.1
SIGN_SIZE_M = 0.75

# Buildings: rows along the roads, set back from the outer lane boundary.
BUILDING_SETBACK_M = 3.0
BUILDING_FRONTAGE_M = (8.0, 18.0)
BUILDING_DEPTH_M = (8.0, 16.0)
BUILDING_GAP_M = (0.5, 4.0)
BUILDING_CLEARANCE_M = 1.0  # from any road, sidewalk or junction polygon
BUILDING_KEEP = 0.85  # share of the slots that get a building (the rest: a tree or nothing)
TREE_KEEP = 0.5

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


def add_signal(b: MeshBuilder, k: int, x: float, y: float, facing_rad: float) -> None:
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


def add_stop_sign(b: MeshBuilder, x: float, y: float, facing_rad: float) -> None:
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


def add_buildings(b: MeshBuilder, edges, pairs, occ_tree, furniture, rng) -> None:
    """Buildings (walls and a flat roof, a facade colour each) and trees in rows along the
    normal edges (`edges`: sumolib edges; `pairs`: their (from, to) node ids: a one-way road
    gets rows on both sides, a two-way one on each direction's right), each footprint clear of
    `occ_tree`'s polygons and of
    the `furniture` footprints by BUILDING_CLEARANCE_M and of the other buildings."""
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
            p = dedupe(np.asarray(lane.getShape(), np.float64)[:, :2])
            if len(p) < 2:
                continue
            sign = -1.0 if side == "right" else 1.0
            total = length(p)
            rows = 2 if rng.random() < 0.6 else 1
            depth0 = 0.0
            for _row in range(rows):
                depth = float(rng.uniform(*BUILDING_DEPTH_M))
                off = lane.getWidth() / 2 + BUILDING_SETBACK_M + depth0
                s = float(rng.uniform(0, 4))
                while s < total:
                    front = float(rng.uniform(*BUILDING_FRONTAGE_M))
                    piece = substring(p, s, s + front)
                    s += front + float(rng.uniform(*BUILDING_GAP_M))
                    if piece is None or length(piece) < 0.6 * front:
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
