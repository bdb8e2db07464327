"""The ego's route ahead as pure geometry: path polyline, turn command, target point, signals.

Everything here is a pure function of lane geometry (world frame: x east, y north, metres) and
SUMO's link tuples; lane lookups go through a `RoadNet` (sumo.Network in the world, a dict-backed
stand-in in tests). Distances "along the path" are measured from the ego's front bumper.

Internal lanes (inside a junction) have ids ":<junction>_<index>_<lane>"; a link's `via_lane_id`
is the first internal lane of that passage ("" for a link without one).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple, Protocol

import numpy as np

SIGNAL_RANGE_M = 30.0  # FrameState.traffic_light / stop_sign look this far along the route
PATH_LOOKAHEAD_M = 100.0  # the expert plans over this much of its route
COMMAND_RANGE_M = 40.0  # a turn command is given from this distance before the junction
TARGET_AHEAD_M = 30.0  # target point on plain road: this far ahead along the route
EXIT_INTO_M = 5.0  # target point at a junction: this far into its exit lane
# The sparse route plan (the paper's / TransFuser's target point): the road's centre at every
# junction entry and exit of the route and every ROUTE_SPACING_M between them; the target is the
# next plan point more than ROUTE_REACHED_M ahead (TransFuser's route planner: 50 m, 7.5 m).
ROUTE_SPACING_M = 50.0
ROUTE_REACHED_M = 7.5
TARGET_FORMS = ("sparse", "dense")

LIGHT_STATES = {"r": "red", "u": "red", "y": "yellow", "Y": "yellow", "G": "green", "g": "green"}
COMMANDS_BY_DIRECTION = {
    "s": "straight",
    "l": "left",
    "L": "left",
    "t": "left",
    "r": "right",
    "R": "right",
}
# link states of a right-of-way junction entry (no signal, no stop): a stop entry behind them
# still governs the ego
_UNSIGNALLED = ("M", "m", "=", "O", "o")


@dataclass(frozen=True)
class Lane:
    """Static geometry of one lane (world frame, metres).

    Attributes:
        pts: (N, 2) float64 shape points.
        length_m: SUMO lane length (may differ slightly from the shape's).
        speed_mps: speed limit.
    """

    pts: np.ndarray
    length_m: float
    speed_mps: float

    @cached_property
    def cum_m(self) -> np.ndarray:
        """(N,) distance of each shape point from the first along the shape, m (computed once
        per lane: the network is static)."""
        seg = np.diff(self.pts, axis=0)
        return np.concatenate([[0.0], np.cumsum(np.hypot(seg[:, 0], seg[:, 1]))])

    @cached_property
    def segments(self) -> Segments:
        """The shape's segments for `project` (computed once per lane; N >= 2 points)."""
        return segments(self.pts)


class Link(NamedTuple):
    """One link from a lane to the next (a libsumo link tuple, named).

    Attributes:
        lane_id: the lane it leads to.
        via_lane_id: its first internal lane inside the junction, "" if none.
        state: right-of-way / signal state now ("G", "r", "s" stop, "w" all-way stop, "M"...);
            "" in the network's static links (Network.links).
        direction: "s", "l", "L", "r", "R", "t" (SUMO's link direction).
    """

    lane_id: str
    via_lane_id: str
    state: str
    direction: str


class RoadNet(Protocol):
    """Static lane lookups the geometry needs (sumo.Network)."""

    def lane(self, lane_id: str) -> Lane: ...

    def links(self, lane_id: str) -> tuple[Link, ...]: ...

    def allowed(self, lane_id: str) -> tuple[str, ...]: ...

    def lane_count(self, edge_id: str) -> int: ...

    def to_junction(self, edge_id: str) -> str: ...


@dataclass(frozen=True)
class Path:
    """The ego's path ahead (world frame) from its front bumper along lanes and next links.

    Attributes:
        pts: (N, 2) float64 polyline, m, N >= 2.
        s: (N,) float64 distance along it from pts[0], m.
        link_dist: distance from the ego's front to each next link's start (the end of the lane
            before it), m, one per link walked.
        seg_lanes: (distance where it starts, lane id) of each lane on the path, the ego's first.
    """

    pts: np.ndarray
    s: np.ndarray
    link_dist: tuple[float, ...]
    seg_lanes: tuple[tuple[float, str], ...]

    @cached_property
    def segments(self) -> Segments:
        """The polyline's segments for `project` (computed once per path)."""
        return segments(self.pts)


@dataclass(frozen=True)
class Signals:
    """The next signal and stop-controlled entry ahead on the route (unlimited range).

    Attributes:
        light: "none", "red", "yellow" or "green" of the next traffic light.
        light_distance_m: distance to its stop line, None without a light.
        stop_distance_m: distance to the next stop-controlled entry's line, None without one.
        stop_junction: that entry's junction id, None if none or it has no internal lane.
    """

    light: str
    light_distance_m: float | None
    stop_distance_m: float | None
    stop_junction: str | None


def cut(lane: Lane, pos_m: float) -> np.ndarray:
    """The lane's shape from `pos_m` (lane-length units) to its end: (K, 2)."""
    pts = lane.pts
    cum = lane.cum_m
    target = pos_m * (cum[-1] / lane.length_m if lane.length_m > 0 else 1.0)
    i = int(np.searchsorted(cum, target, side="right"))
    if i >= len(pts):
        return pts[-1:]
    i = max(i, 1)
    f = (target - cum[i - 1]) / max(cum[i] - cum[i - 1], 1e-9)
    out = pts[i - 1 :].copy()
    out[0] = pts[i - 1] + f * (pts[i] - pts[i - 1])
    return out


class Segments(NamedTuple):
    """A polyline's M segments, as `project` needs them (world frame, m).

    Attributes:
        a: (M, 2) start points; d: (M, 2) vectors to the end points; seg_len: (M,) lengths;
        l2: (M,) squared lengths, at least 1e-9; u: (2,) unit vector of the first segment;
        normal: (2,) its left normal.
    """

    a: np.ndarray
    d: np.ndarray
    seg_len: np.ndarray
    l2: np.ndarray
    u: np.ndarray
    normal: np.ndarray


def segments(pts: np.ndarray) -> Segments:
    """The segments of a (N, 2) polyline, N >= 2, for `project`."""
    a = pts[:-1]
    d = pts[1:] - a
    dx, dy = d[:, 0], d[:, 1]
    seg_len = np.sqrt(dx * dx + dy * dy)
    l2 = np.maximum(seg_len * seg_len, 1e-9)
    u = d[0] / max(seg_len[0], 1e-9)
    return Segments(a, d, seg_len, l2, u, np.array([-u[1], u[0]]))


def project(
    xy: np.ndarray, pts: np.ndarray, s: np.ndarray, segs: Segments | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project (K, 2) points onto a polyline: along-path s (K,), unsigned lateral distance (K,)
    and the path heading at the projection (K,), radians. `segs`: `segments(pts)`, where the
    caller has it (Path.segments)."""
    return project_many([xy], pts, s, segs)


def project_many(
    xys: Sequence[np.ndarray], pts: np.ndarray, s: np.ndarray, segs: Segments | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`project` of several (K_i, 2) point sets in one pass, rows in the order of the sets:
    the same results, bit for bit, as one call per set (the products for points behind the
    start are taken per set, as a matrix product's last bits depend on its shape).

    x and y are kept in separate (K, M) arrays: the same products and sums as with (K, M, 2)
    arrays summed over their last axis, at a fraction of numpy's cost for that reduction."""
    a, d, seg_len, l2, u, normal = segs if segs is not None else segments(pts)
    dx, dy = d[:, 0], d[:, 1]
    xy = np.concatenate(xys) if len(xys) > 1 else xys[0]
    rel_x = xy[:, :1] - a[:, 0]  # (K, M)
    rel_y = xy[:, 1:] - a[:, 1]
    t = (rel_x * dx + rel_y * dy) / l2
    # clip to [0, 1] (np.clip's values; at a fraction of its call cost)
    np.maximum(t, 0.0, out=t)
    np.minimum(t, 1.0, out=t)
    off_x = rel_x - t * dx
    off_y = rel_y - t * dy
    dist = np.sqrt(off_x * off_x + off_y * off_y)  # (K, M)
    idx = dist.argmin(1)
    k = np.arange(len(xy))
    t_at = t[k, idx]
    along = s[idx] + t_at * seg_len[idx]
    lat = dist[k, idx]
    heading = np.arctan2(dy[idx], dx[idx])
    # points beyond the ends: extend the first/last segment so "behind" gives negative s
    first = (idx == 0) & (t_at <= 0.0)
    if first.any():
        first_l = first.tolist()
        lo = 0
        for g in xys:
            hi = lo + len(g)
            if True in first_l[lo:hi]:
                f = first[lo:hi]
                behind = g[f] - a[0]
                along[lo:hi][f] = s[0] + (behind @ u)
                lat[lo:hi][f] = np.abs(behind @ normal)
            lo = hi
    return along, lat, heading


def first_intersection(
    pts: np.ndarray, s: np.ndarray, other: np.ndarray
) -> tuple[float, float] | None:
    """Where polyline `other` (M, 2) first crosses polyline `pts` (N, 2) with arc lengths `s`:
    (distance along pts, distance along other), or None if they do not cross."""
    a, da = pts[:-1], np.diff(pts, axis=0)  # (N-1, 2)
    b, db = other[:-1], np.diff(other, axis=0)  # (M-1, 2)
    cross = da[:, None, 0] * db[None, :, 1] - da[:, None, 1] * db[None, :, 0]  # (N-1, M-1)
    rel = b[None] - a[:, None]  # (N-1, M-1, 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (rel[..., 0] * db[None, :, 1] - rel[..., 1] * db[None, :, 0]) / cross
        u = (rel[..., 0] * da[:, None, 1] - rel[..., 1] * da[:, None, 0]) / cross
    ok = (np.abs(cross) > 1e-12) & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1)
    if not ok.any():
        return None
    i, j = np.argwhere(ok)[0]  # rows are path segments in order: the first one along pts
    seg_b = np.hypot(db[:, 0], db[:, 1])
    s_b = np.concatenate([[0.0], np.cumsum(seg_b)])
    return float(s[i] + t[i, j] * (s[i + 1] - s[i])), float(s_b[j] + u[i, j] * seg_b[j])


def via_chain(net: RoadNet, internal: str) -> list[str]:
    """The internal lane(s) of one junction passage starting at `internal` (an internal
    junction splits a turn into two lanes)."""
    chain, lid = [internal], internal
    while len(chain) < 4:
        links = net.links(lid)
        if not links or not links[0].via_lane_id:
            break
        lid = links[0].via_lane_id
        chain.append(lid)
    return chain


def exit_chain(net: RoadNet, internal: str) -> list[str]:
    """From inside a junction: the remaining internal lanes and the exit lane."""
    chain, lid = [], internal
    while len(chain) < 4:
        links = net.links(lid)
        if not links:
            break
        lid = links[0].via_lane_id or links[0].lane_id
        chain.append(lid)
        if not lid.startswith(":"):
            break
    return chain


def junction_has_choice(net: RoadNet, from_lane: str) -> bool:
    """True if the edge of `from_lane` leads to two or more drivable edges (a real
    intersection, where a turn command means something)."""
    edge = from_lane.rsplit("_", 1)[0]
    outs = set()
    for k in range(net.lane_count(edge)):
        for link in net.links(f"{edge}_{k}"):
            if link.direction != "t" and "passenger" in net.allowed(link.lane_id):
                outs.add(link.lane_id.rsplit("_", 1)[0])
    return len(outs) >= 2


def path_ahead(
    net: RoadNet,
    lane_id: str,
    lane_pos_m: float,
    links: tuple[Link, ...],
    front_xy_m: tuple[float, float],
    yaw_rad: float,
) -> Path:
    """The path polyline from the ego's front along its current lane and next links, up to
    PATH_LOOKAHEAD_M (plus the lane that crosses it); a 1 m stub along the heading if the
    lanes give fewer than two points."""
    lane = net.lane(lane_id)
    pieces = [cut(lane, lane_pos_m)]
    seg_lanes = [(0.0, lane_id)]
    dist = lane.length_m - lane_pos_m
    if lane_id.startswith(":"):
        # inside a junction getNextLinks starts after the exit lane: walk out first
        for nxt in exit_chain(net, lane_id):
            seg_lanes.append((dist, nxt))
            pieces.append(net.lane(nxt).pts)
            dist += net.lane(nxt).length_m
    link_dist = []
    for link in links:
        link_dist.append(dist)
        if dist > PATH_LOOKAHEAD_M:
            break
        chain = via_chain(net, link.via_lane_id) if link.via_lane_id else []
        for via in chain:
            pieces.append(net.lane(via).pts)
            dist += net.lane(via).length_m
        seg_lanes.append((dist, link.lane_id))
        dist += net.lane(link.lane_id).length_m
        pieces.append(net.lane(link.lane_id).pts)
    pts = np.concatenate(pieces)
    step = pts[1:] - pts[:-1]
    step_len = np.hypot(step[:, 0], step[:, 1])
    keep = step_len > 0.2
    if not keep.all():  # drop points within 0.2 m of the one before (where pieces join)
        pts = pts[np.concatenate([[True], keep])]
        step = pts[1:] - pts[:-1]
        step_len = np.hypot(step[:, 0], step[:, 1])
    if len(pts) < 2:
        x, y = front_xy_m
        pts = np.array([[x, y], [x + math.cos(yaw_rad), y + math.sin(yaw_rad)]])
        step = pts[1:] - pts[:-1]
        step_len = np.hypot(step[:, 0], step[:, 1])
    s = np.concatenate([[0.0], np.cumsum(step_len)])
    return Path(pts, s, tuple(link_dist), tuple(seg_lanes))


def signals(next_signals, links: tuple[Link, ...], link_dist: tuple[float, ...]) -> Signals:
    """The next light (from `next_signals`, sumo.NextSignal tuples nearest first) and the next
    stop-controlled entry along `links` (a signal met first governs instead)."""
    light, light_d = "none", None
    for _tls, _idx, d, state in next_signals[:1]:
        light, light_d = LIGHT_STATES.get(state, "none"), float(d)
        if light == "none":
            light_d = None
    stop_d = None
    stop_junction = None
    for link, d in zip(links, link_dist):
        if link.state in ("s", "w"):
            stop_d = float(d)
            if link.via_lane_id:  # internal lane ":<junction>_<index>_<lane>"
                stop_junction = link.via_lane_id[1:].rsplit("_", 2)[0]
            break
        if link.state not in _UNSIGNALLED:  # a signal first: it governs
            break
    return Signals(light, light_d, stop_d, stop_junction)


def exit_point(net: RoadNet, lane_id: str) -> tuple[float, float]:
    """The point EXIT_INTO_M into a junction's exit lane (at most half its length), world m."""
    lane = net.lane(lane_id)
    pts = cut(lane, min(EXIT_INTO_M, 0.5 * lane.length_m))
    return float(pts[0, 0]), float(pts[0, 1])


# (junction id, command, exit lane) of the junction passage a command was given for: kept while
# the ego is inside that junction
Sticky = tuple[str, str, str]


def command_and_target(
    net: RoadNet,
    lane_id: str,
    path: Path,
    links: tuple[Link, ...],
    sticky: Sticky | None,
) -> tuple[str, tuple[float, float], Sticky | None]:
    """(command, target point, sticky) from the route ahead.

    Within COMMAND_RANGE_M of a junction with a choice the command is the link's turn and the
    target point lies EXIT_INTO_M into the exit lane; both stay (sticky) while the ego is inside
    that junction. Elsewhere the command is "follow" and the target lies TARGET_AHEAD_M along
    the path. `sticky` is the value returned for the previous frame (None at the start).
    """
    pts, s = path.pts, path.s
    if lane_id.startswith(":"):
        if sticky is not None:
            _j, cmd, exit_lane = sticky
            return cmd, exit_point(net, exit_lane), sticky
    else:
        sticky = None
        from_lane = lane_id
        for link, d in zip(links, path.link_dist):
            if d > COMMAND_RANGE_M:
                break
            if not link.via_lane_id:  # no internal lane: not a junction we drive through
                from_lane = link.lane_id
                continue
            if junction_has_choice(net, from_lane):
                cmd = COMMANDS_BY_DIRECTION.get(link.direction, "straight")
                junction = link.via_lane_id[1:].rsplit("_", 2)[0]
                sticky = (junction, cmd, link.lane_id)
                return cmd, exit_point(net, link.lane_id), sticky
            from_lane = link.lane_id
    return "follow", point_along(pts, s, TARGET_AHEAD_M), sticky


class PlanPoint(NamedTuple):
    """A point of the sparse route plan: world x, y (m), the index of its route edge and its
    distance along that edge's lanes (m, lane-length units)."""

    x_m: float
    y_m: float
    edge_index: int
    pos_m: float


def sparse_plan(net: RoadNet, edges: Sequence[str]) -> tuple[PlanPoint, ...]:
    """The route as sparse points: per edge its start (a junction exit), every ROUTE_SPACING_M
    and its end (a junction entry), each the mean over the edge's car lanes, so that the point
    says where the route goes, not which lane the car takes."""
    out = []
    for i, edge in enumerate(edges):
        lanes = [
            net.lane(f"{edge}_{k}")
            for k in range(net.lane_count(edge))
            if "passenger" in net.allowed(f"{edge}_{k}")
        ]
        if not lanes:
            continue
        length = min(lane.length_m for lane in lanes)
        n = max(1, int(round(length / ROUTE_SPACING_M)))
        for pos in np.linspace(0.0, length, n + 1):
            xy = np.mean([cut(lane, float(pos))[0] for lane in lanes], axis=0)
            out.append(PlanPoint(float(xy[0]), float(xy[1]), i, float(pos)))
    return tuple(out)


def next_plan_point(
    plan: Sequence[PlanPoint],
    k: int,
    route_index: int,
    lane_pos_m: float | None,
    front_xy_m: tuple[float, float],
) -> int:
    """Index of the target in `plan`, from the previous one `k`: points of edges behind the
    ego's (`route_index`), points on its edge less than ROUTE_REACHED_M ahead of `lane_pos_m`
    (None inside a junction) and points within ROUTE_REACHED_M of its front are reached; the
    last point is kept."""
    while k < len(plan) - 1:
        p = plan[k]
        reached = p.edge_index < route_index or (
            math.hypot(p.x_m - front_xy_m[0], p.y_m - front_xy_m[1]) < ROUTE_REACHED_M
        )
        if lane_pos_m is not None and p.edge_index == route_index:
            reached = reached or p.pos_m < lane_pos_m + ROUTE_REACHED_M
        if not reached:
            break
        k += 1
    return k


def point_along(pts: np.ndarray, s: np.ndarray, dist_m: float) -> tuple[float, float]:
    """The point `dist_m` along a polyline (its end if shorter), world m."""
    i = int(np.searchsorted(s, dist_m))
    if i >= len(s):
        tp = pts[-1]
    else:
        f = (dist_m - s[i - 1]) / max(s[i] - s[i - 1], 1e-9)
        tp = pts[i - 1] + f * (pts[i] - pts[i - 1])
    return float(tp[0]), float(tp[1])


def curvature_ahead(path: Path, min_curvature_1pm: float) -> tuple[tuple[float, float], ...]:
    """(distance_m, curvature_1pm) at path vertices where it exceeds `min_curvature_1pm`:
    turning angle / local segment length (segments shorter than 1.5 m count as 1.5 m)."""
    pts, s = path.pts, path.s
    if len(pts) < 3:
        return ()
    seg = np.diff(pts, axis=0)
    head = np.arctan2(seg[:, 1], seg[:, 0])
    seg_len = np.hypot(seg[:, 0], seg[:, 1])
    dth = np.abs((np.diff(head) + np.pi) % (2 * np.pi) - np.pi)
    k = dth / np.maximum(1.5, 0.5 * (seg_len[:-1] + seg_len[1:]))
    sel = np.flatnonzero(k > min_curvature_1pm)
    return tuple((float(s[i + 1]), float(k[i])) for i in sel)


def speed_limits(
    net: RoadNet, lane_id: str, path: Path
) -> tuple[float, tuple[tuple[float, float], ...]]:
    """(limit now, lower limits ahead as (distance_m, limit_mps)) along the path's lanes;
    inside a junction the exit lane's limit is the one that counts now."""
    limit = net.lane(lane_id).speed_mps
    limits_ahead = []
    is_internal = lane_id.startswith(":")
    for d, lid in path.seg_lanes[1:]:
        if lid.startswith(":"):
            continue
        v = net.lane(lid).speed_mps
        if is_internal:
            limit, is_internal = v, False
        elif v < limit:
            limits_ahead.append((d, v))
    return limit, tuple(limits_ahead)


def junction_ahead(lane_id: str, path: Path, links: tuple[Link, ...]) -> tuple[float, float] | None:
    """(entry, exit) distances of the next junction the path drives through, while the ego is
    before it: entry = where its first internal lane starts (the stop line), exit = where the
    lane after it starts. None inside a junction or without internal lanes ahead."""
    if lane_id.startswith(":") or not links or not path.link_dist or len(path.seg_lanes) < 2:
        return None
    if not links[0].via_lane_id:
        return None
    return path.link_dist[0], path.seg_lanes[1][0]


def junction_of(internal_lane_id: str) -> str:
    """The junction id of an internal lane ":<junction>_<index>_<lane>"."""
    return internal_lane_id[1:].rsplit("_", 2)[0]


def waits_inside(net: RoadNet, link: Link) -> bool:
    """The ego would give way inside the junction on this link: a minor link ("m", or "g"
    at a light) whose passage has an internal waiting point (two or more internal lanes)."""
    return (
        link.state in ("m", "g")
        and bool(link.via_lane_id)
        and len(via_chain(net, link.via_lane_id)) >= 2
    )


def route_suffix_m(net: RoadNet, route: tuple[str, ...]) -> np.ndarray:
    """(len(route) + 1,) length of each suffix of the route (lane-0 lengths), m; last 0."""
    lengths = np.array([net.lane(f"{e}_0").length_m for e in route])
    return np.concatenate([np.cumsum(lengths[::-1])[::-1], [0.0]])


def remaining_route_m(
    net: RoadNet, suffix_m: np.ndarray, lane_id: str, lane_pos_m: float, route_index: int
) -> float:
    """Distance from the ego's front to the end of its route, m."""
    rest = net.lane(lane_id).length_m - lane_pos_m
    return float(rest + suffix_m[min(route_index + 1, len(suffix_m) - 1)])


def route_links(net: RoadNet, lane_id: str, route_ahead: Sequence[str], n: int) -> tuple[Link, ...]:
    """Up to `n` consecutive links from `lane_id` along the route's next edges `route_ahead`
    (each the first static link into the next edge; the walk stops where none leads on)."""
    out: list[Link] = []
    lane = lane_id
    for edge in route_ahead[:n]:
        link = next((k for k in net.links(lane) if k.lane_id.rsplit("_", 1)[0] == edge), None)
        if link is None:
            break
        out.append(link)
        lane = link.lane_id
    return tuple(out)
