"""A route's geometry on its network: centreline, the lanes it may use, its stop lines.

Read once per route from the .net.xml with sumolib (no simulation): the same network the world
and the sensors are built from. World frame throughout (SUMO network coordinates, metres).

    geom = route_geometry(net, ("A0A1", "A1B1", "B1B2"))
    geom.length_m, geom.stop_lines        # centreline length; signals and stop signs on it
    s, lateral = geom.project(xy)         # progress along the route, distance from it

Centreline: per route edge the car lane that connects to the next edge (the rightmost such),
then the junction's internal lane(s) of that connection. Lanes: every car lane of a route edge
and every internal lane of a connection between consecutive route edges; `in_lanes` tells
whether a point is on them (the leaderboard's "route lanes"). Stop lines: the end of each route
edge whose connection to the next one is signalised (a traffic light) or stop-controlled (SUMO
link state 's' or 'w'), across all the edge's car lanes, one segment per lane with the signal
links that govern it (so a crossing is judged against the line's own signal, wherever the ego
is: off its lane or off the network too).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class StopLine:
    """A signal or stop sign on the route.

    Attributes:
        kind: "light" or "stop".
        s_m: its position along the route centreline, m.
        junction: SUMO id of the junction it guards.
        xy_m: (2, 2) float64 the line's end points across the approach, world frame: its
            left end, then its right end (seen in the direction of travel).
        lane_xy_m: (K, 2, 2) float64 the line's segment across each of the approach's K car
            lanes (right end, left end; world frame); they tile xy_m.
        direction: (2,) float64 unit vector of travel across the line (the approach's heading
            at its end), world frame; None: xy_m's left-to-right direction turned a quarter
            counter-clockwise (normal to the line).
        tls_id: the traffic light of a "light" line ("" for a stop sign).
        lane_links: per lane, the indices into that light's state string (one character per
            link, sumo getRedYellowGreenState) of the links that govern it: its connection to
            the route's next edge, or all its connections if it has none to it.
    """

    kind: str
    s_m: float
    junction: str
    xy_m: np.ndarray
    lane_xy_m: np.ndarray | None = None
    direction: np.ndarray | None = None
    tls_id: str = ""
    lane_links: tuple[tuple[int, ...], ...] = ()

    def segments(self) -> np.ndarray:
        """(K, 2, 2) the segments a crossing is judged on (per lane, else the whole line)."""
        return self.lane_xy_m if self.lane_xy_m is not None else self.xy_m[None]


@dataclass(frozen=True)
class RouteGeometry:
    """Geometry of one route (module docstring).

    Attributes:
        edges: the route's edge ids.
        centre_xy_m: (N, 2) float64 centreline, world frame, from the start of the first edge.
        centre_s_m: (N,) float64 arc length at each centreline vertex, m.
        stop_lines: signals and stop signs in route order.
        lanes: shapely geometry of the route's lanes (union of lane polygons).
        junctions: junctions with a choice (three or more roads) the route passes.
    """

    edges: tuple[str, ...]
    centre_xy_m: np.ndarray
    centre_s_m: np.ndarray
    stop_lines: tuple[StopLine, ...]
    lanes: object
    junctions: int

    @property
    def length_m(self) -> float:
        return float(self.centre_s_m[-1])

    def project(self, xy_m, s_min: float = -np.inf, s_max: float = np.inf):
        """Closest point of the centreline within [s_min, s_max] to world point xy_m ->
        (s along the route m, distance from the route m)."""
        pts, s = self.centre_xy_m, self.centre_s_m
        lo = max(0, int(np.searchsorted(s, s_min, side="right")) - 1)
        hi = min(len(s) - 1, int(np.searchsorted(s, s_max, side="left")))
        if hi <= lo:
            lo, hi = max(0, min(lo, len(s) - 2)), max(1, min(lo, len(s) - 2) + 1)
        a, b = pts[lo:hi], pts[lo + 1 : hi + 1]
        d = b - a
        l2 = np.maximum((d * d).sum(1), 1e-12)
        p = np.asarray(xy_m, dtype=np.float64)
        t = np.clip(((p - a) * d).sum(1) / l2, 0.0, 1.0)
        foot = a + t[:, None] * d
        dist = np.hypot(*(p - foot).T)
        k = int(np.argmin(dist))
        along = s[lo + k] + t[k] * np.sqrt(l2[k])
        return float(np.clip(along, s_min, s_max)), float(dist[k])

    def point_at(self, s_m: float) -> np.ndarray:
        """(2,) world point of the centreline at arc length s_m (clamped to the route)."""
        s = self.centre_s_m
        return np.array(
            [np.interp(s_m, s, self.centre_xy_m[:, 0]), np.interp(s_m, s, self.centre_xy_m[:, 1])]
        )

    def in_lanes(self, x_m: float, y_m: float) -> bool:
        """True if the world point lies on one of the route's lanes."""
        from shapely import Point

        return bool(self.lanes.contains(Point(x_m, y_m)))


@lru_cache(maxsize=4)
def read_net(net_path: str):
    """sumolib's network object with internal lanes (cached per process)."""
    import sumolib

    return sumolib.net.readNet(str(net_path), withInternal=True)


def _car_lanes(edge) -> list:
    return [lane for lane in edge.getLanes() if lane.allows("passenger")]


def _via_chain(net, via_id: str) -> list:
    """The internal lanes of one junction passage, from its first internal lane."""
    chain, lane = [], net.getLane(via_id)
    while lane is not None and lane.getEdge().getFunction() == "internal" and len(chain) < 4:
        chain.append(lane)
        outs = lane.getOutgoing()
        if not outs:
            break
        nxt = outs[0].getViaLaneID() or outs[0].getToLane().getID()
        lane = net.getLane(nxt)
    return chain


def _connection(edge, nxt):
    """The rightmost car lane's connection from `edge` to `nxt` (None if they do not connect)."""
    cons = [c for c in edge.getOutgoing().get(nxt, []) if c.getFromLane().allows("passenger")]
    if not cons:
        return None
    return min(cons, key=lambda c: c.getFromLane().getIndex())


def _dedupe(pts: np.ndarray) -> np.ndarray:
    step = np.hypot(*np.diff(pts, axis=0).T)
    return pts[np.concatenate([[True], step > 1e-3])]


def _stop_line(kind: str, junction: str, lanes: list, con, nxt_edge) -> StopLine:
    """The stop line at the end of an edge's car `lanes` whose route connection `con` leads to
    `nxt_edge` (module docstring); s_m is filled in by the caller."""
    segs, dirs, links = [], [], []
    for ln in lanes:
        p = np.asarray(ln.getShape(), dtype=np.float64)
        u = p[-1] - p[-2]
        u = u / max(np.hypot(*u), 1e-9)
        n = np.array([-u[1], u[0]]) * 0.5 * ln.getWidth()  # to the lane's left
        segs.append([p[-1] - n, p[-1] + n])
        dirs.append(u)
        own = [c for c in ln.getOutgoing() if c.getToLane().getEdge() == nxt_edge]
        idx = {c.getTLLinkIndex() for c in (own or ln.getOutgoing())}
        links.append(tuple(sorted(i for i in idx if i >= 0)))
    segs = np.asarray(segs)  # (K, 2, 2)
    ends = segs.reshape(-1, 2)
    # the two extreme points across the approach: left end, right end
    axis = ends[1] - ends[0]  # to the left
    proj = ends @ axis
    line = np.stack([ends[int(np.argmax(proj))], ends[int(np.argmin(proj))]])
    u = np.mean(dirs, axis=0)
    u = u / max(np.hypot(*u), 1e-9)
    tls = con.getTLSID() if kind == "light" else ""
    return StopLine(
        kind,
        0.0,
        junction,
        line,
        lane_xy_m=segs,
        direction=u,
        tls_id=tls or "",
        lane_links=tuple(links) if kind == "light" else (),
    )


def route_geometry(net_path: str | Path, edges: tuple[str, ...]) -> RouteGeometry:
    """Geometry of the route `edges` on the network (module docstring); ValueError if an edge
    is missing or two consecutive edges do not connect for cars."""
    from shapely import LineString, unary_union

    net = read_net(str(net_path))
    pieces: list[np.ndarray] = []
    polys = []
    stops: list[tuple] = []
    junctions = 0
    s_total = 0.0
    for k, eid in enumerate(edges):
        if not net.hasEdge(eid):
            raise ValueError(f"edge {eid!r} is not in {Path(net_path).name}")
        edge = net.getEdge(eid)
        lanes = _car_lanes(edge)
        if not lanes:
            raise ValueError(f"edge {eid!r} has no lane for cars")
        for lane in lanes:
            polys.append(LineString(lane.getShape()).buffer(0.5 * lane.getWidth(), cap_style=2))
        con = None
        if k + 1 < len(edges):
            if not net.hasEdge(edges[k + 1]):
                raise ValueError(f"edge {edges[k + 1]!r} is not in {Path(net_path).name}")
            nxt_edge = net.getEdge(edges[k + 1])
            con = _connection(edge, nxt_edge)
            if con is None:
                raise ValueError(f"edges {eid!r} and {edges[k + 1]!r} do not connect for cars")
            lane = con.getFromLane()
        else:
            lane = lanes[0]
        shape = np.asarray(lane.getShape(), dtype=np.float64)
        pieces.append(shape)
        s_total += float(np.hypot(*np.diff(shape, axis=0).T).sum())
        if con is None:
            continue
        node = edge.getToNode()
        nbrs = {e.getFromNode().getID() for e in node.getIncoming()}
        nbrs |= {e.getToNode().getID() for e in node.getOutgoing()}
        if len(nbrs) >= 3:
            junctions += 1  # a real junction (three or more roads), not a bend
        jtype = node.getType()
        kind = None
        if jtype.startswith("traffic_light"):
            kind = "light"
        elif con.getState() in ("s", "w"):
            kind = "stop"
        if kind is not None:
            stops.append((s_total, _stop_line(kind, node.getID(), lanes, con, nxt_edge)))
        via = con.getViaLaneID()
        for vl in _via_chain(net, via) if via else []:
            vshape = np.asarray(vl.getShape(), dtype=np.float64)
            pieces.append(vshape)
            s_total += float(np.hypot(*np.diff(vshape, axis=0).T).sum())
            polys.append(LineString(vl.getShape()).buffer(0.5 * vl.getWidth(), cap_style=2))
        # every other internal lane between the two route edges belongs to the route too
        for c in edge.getOutgoing().get(net.getEdge(edges[k + 1]), []):
            if c is not con and c.getViaLaneID() and c.getFromLane().allows("passenger"):
                for vl in _via_chain(net, c.getViaLaneID()):
                    polys.append(LineString(vl.getShape()).buffer(0.5 * vl.getWidth(), cap_style=2))
    pts = _dedupe(np.concatenate(pieces))
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(pts, axis=0).T))])
    # stop-line positions were summed over lane shapes; map them onto the deduped centreline
    scale = s[-1] / max(s_total, 1e-9)
    stop_lines = tuple(replace(line, s_m=sl * scale) for sl, line in stops)
    lanes_geom = unary_union(polys)
    from shapely import prepare

    prepare(lanes_geom)
    return RouteGeometry(tuple(edges), pts, s, stop_lines, lanes_geom, junctions)
