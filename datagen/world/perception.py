"""What the ego perceives: the obstacles on its path and who holds it back. Pure functions of a
sumo.Snapshot's readings and a route.Path (world frame, metres; distances along the path from
the ego's front bumper)."""

from __future__ import annotations

import bisect
import math
import re
from collections.abc import Callable, Sequence

import numpy as np
import shapely

import datagen.world.expert as expert
from datagen.world.fleet import EGO_DIMS_M, PED_TYPE, dims
from datagen.world.route import Path, RoadNet, first_intersection, project, project_many
from datagen.world.sumo import AgentReading, Leader, centre_xy

_CROSSING = re.compile(r"_c\d+_\d+$")  # internal crossing lane ":<junction>_c<k>_<lane>"
_WALKING_AREA = re.compile(r"_w\d+_\d+$")
CROSSING_HALF_WIDTH_M = 2.0  # SUMO crossings are 4 m wide (netconvert's default)
CORRIDOR_SLACK_M = 1.0  # a person this close to the ego's corridor across a crossing is in it
STEP_ON_M = 2.0  # someone walking to a crossing this close to its end is about to step on
CLEAR_FIRST_S = 1.5  # the ego goes first only if it clears the crossing this long before them
# The car's body sweeps inside its front's path on a turn (SUMO's box is the chord from the
# front back one length along the lane): people standing, even at the kerb, are checked against
# that swept body, sampled every SWEEP_STEP_M of the front's travel up to SWEEP_AHEAD_M, with
# this clearance (measured: three "ego hit p.. (crossing)" with someone standing on the walking
# area at the inside of a right turn, 420 episodes of bench/sim.py).
SWEEP_CLEARANCE_M = 0.3
SWEEP_STEP_M = 0.5
SWEEP_AHEAD_M = 40.0
STOP_FOE_M = 3.0  # a vehicle standing this close to a stop line it must obey is a junction foe
VEHICLE_MARGIN_M = 0.35  # a vehicle's box this close to the ego's corridor is on its path
# band_extent trusts a corner as the extreme only this far from the band's border and from
# every border crossing (GEOS's crossings are exact to ~1e-9 m at the coordinates used here)
BAND_SURE_M = 1e-6


def is_kerb(lane_id: str, allowed: tuple[str, ...] | None) -> bool:
    """A walking area or a pedestrian-only lane (sidewalk, footpath); `allowed` is the lane's
    vClasses (ignored for internal lanes)."""
    if lane_id.startswith(":"):
        return _WALKING_AREA.search(lane_id) is not None
    return lane_id != "" and allowed == ("pedestrian",)


def is_crossing(lane_id: str) -> bool:
    """An internal lane of a pedestrian crossing."""
    return _CROSSING.search(lane_id) is not None


def swept_contact(
    xy: np.ndarray,
    radius_m: np.ndarray,
    path: Path,
    length_m: float,
    half_width_m: float,
    clearance_m: float | np.ndarray = SWEEP_CLEARANCE_M,
) -> np.ndarray:
    """How far the ego's front travels along `path` before its body touches each point `xy`
    (K, 2) with radius `radius_m` (K,), or comes within `clearance_m` of it and closer than it
    is now, m; inf where neither happens within SWEEP_AHEAD_M.

    The body at front distance u is the segment from the path point u - `length_m` to the path
    point u, `half_width_m` wide (behind its start the path goes straight back along its first
    segment). Sampled every SWEEP_STEP_M, the current pose first. "Closer than now": someone
    already beside the car who is left behind as it moves on does not hold it (measured: a
    person waiting at the kerb beside the ego's front, the ego waiting for them and they for the
    ego, until a third walked into it: arterial, build seed 0, episode 9)."""
    pts, s = path.pts, path.s
    u = np.arange(0.0, min(float(s[-1]), SWEEP_AHEAD_M) + 1e-9, SWEEP_STEP_M)
    d0 = pts[1] - pts[0]
    d0 = d0 / max(float(np.hypot(*d0)), 1e-9)

    def at(q: np.ndarray) -> np.ndarray:
        p = np.stack([np.interp(q, s, pts[:, 0]), np.interp(q, s, pts[:, 1])], 1)
        back = q < s[0]
        p[back] = pts[0] + (q[back] - s[0])[:, None] * d0
        return p

    front, rear = at(u), at(u - length_m)  # (U, 2)
    seg = front - rear
    l2 = np.maximum((seg * seg).sum(1), 1e-9)
    rel = xy[:, None, :] - rear[None]  # (K, U, 2)
    t = np.clip((rel * seg[None]).sum(-1) / l2, 0.0, 1.0)
    off = rel - t[..., None] * seg[None]
    dist = np.sqrt((off * off).sum(-1))  # (K, U)
    reach = half_width_m + radius_m[:, None]
    clear = np.broadcast_to(np.asarray(clearance_m, np.float64), (len(xy),))[:, None]
    closer = (dist < reach + clear) & (dist < dist[:, :1] - 0.05)
    touch = (dist < reach) | closer
    first = touch.argmax(1)
    return np.where(touch.any(1), u[first], np.inf)


def corridor_span(
    xy: np.ndarray,
    yaw_rad: float,
    length_m: float,
    width_m: float,
    path: Path,
    half_width_m: float,
    projection: tuple[float, float, float] | None = None,
) -> tuple[float, float] | None:
    """Along-path extent (from, to), m from the ego's front, of the part of a box (centre `xy`
    (2,), heading `yaw_rad`, world frame) within `half_width_m` of `path`; None if no part is.

    The box is placed in the path's frame at the projection of its centre (the path taken as
    straight over the box's length), then cut to the corridor with shapely. `projection`:
    `route.project`'s (along, unsigned lateral, heading) of `xy`, where the caller has it."""
    if projection is None:
        along, lat, head = project(xy[None], path.pts, path.s)
        projection = (float(along[0]), float(lat[0]), float(head[0]))
    along0, lat, h = projection
    rel = yaw_rad - h
    half_l, half_w = 0.5 * length_m, 0.5 * width_m

    def box(lat0: float) -> list[tuple[float, float]]:
        return path_box(along0, lat0, rel, half_l, half_w)

    side = _side(xy, along0, h, path)
    if abs(side) <= BAND_SURE_M:
        # a vehicle on the lane line (most in the ego's lane): if either side gives the same
        # extent, the sign does not matter; else take numpy's exact sign
        sure, span = band_extent(box(lat), half_width_m)
        if sure and band_extent(box(-lat), half_width_m) == (True, span):
            return span
        side = _exact_side(xy, along0, h, path)
    corners = box(math.copysign(lat, side))
    sure, span = band_extent(corners, half_width_m)
    if sure:
        return span
    inside = shapely.Polygon(corners).intersection(
        shapely.box(-1e6, -half_width_m, 1e6, half_width_m)
    )
    if inside.is_empty:
        return None
    lo, _, hi, _ = inside.bounds
    return float(lo), float(hi)


def path_box(
    along_m: float, lat_m: float, rel_rad: float, half_l_m: float, half_w_m: float
) -> list[tuple[float, float]]:
    """Corners (along, lateral) of a box in a path's frame: centre `along_m` along the path and
    `lat_m` left of it, heading `rel_rad` relative to the path, half extents in m; front-left,
    front-right, rear-right, rear-left."""
    c, sn = math.cos(rel_rad), math.sin(rel_rad)
    return [
        (along_m + dx * c - dy * sn, lat_m + dx * sn + dy * c)
        for dx, dy in (
            (half_l_m, half_w_m),
            (half_l_m, -half_w_m),
            (-half_l_m, -half_w_m),
            (-half_l_m, half_w_m),
        )
    ]


def _side(xy: np.ndarray, along0: float, h: float, path: Path) -> float:
    """Which side of `path` the point `xy` (2,) lies on, as a number whose sign says it (left
    > 0): (xy - the path point at `along0`) . the left normal at heading `h`, m.

    Scalar arithmetic: the sign is that of `_exact_side` (numpy's, as corridor_span always
    took it) wherever the result is more than BAND_SURE_M from 0."""
    s, pts = path.s, path.pts
    j = min(max(bisect.bisect_left(s, along0), 1), len(s) - 1)
    x0, y0, x1, y1 = pts[j - 1, 0], pts[j - 1, 1], pts[j, 0], pts[j, 1]
    f = min(max((along0 - s[j - 1]) / max(s[j] - s[j - 1], 1e-9), 0.0), 1.0)
    nx, ny = -math.sin(h), math.cos(h)
    return float((xy[0] - (x0 + f * (x1 - x0))) * nx + (xy[1] - (y0 + f * (y1 - y0))) * ny)


def _exact_side(xy: np.ndarray, along0: float, h: float, path: Path) -> float:
    """`_side` with numpy (np.interp, a dot product): the sign corridor_span has always used."""
    s, pts = path.s, path.pts
    at = np.array([np.interp(along0, s, pts[:, 0]), np.interp(along0, s, pts[:, 1])])
    return float((xy - at) @ np.array([-math.sin(h), math.cos(h)]))


def band_extent(
    corners: Sequence[tuple[float, float]], half_width_m: float
) -> tuple[bool, tuple[float, float] | None]:
    """(sure, span): the x extent (lo, hi) of the part of a convex polygon (corners (x, y), m)
    within |y| <= `half_width_m`, or None if no part is, where that follows without computing
    where an edge crosses the band's border; sure is False otherwise.

    Exactly what shapely's intersection with the band and its bounds give (`corridor_span`'s
    slow path): the extent is then a corner's own x. The polygon's vertices inside the band are
    its corners there plus the border crossings; a crossing only has to be approximate here to
    tell that it is not an extreme, as GEOS computes it to far better than BAND_SURE_M."""
    inside = []
    above = below = False
    for x, y in corners:
        if abs(y) < half_width_m - BAND_SURE_M:
            inside.append(x)
        elif y > half_width_m + BAND_SURE_M:
            above = True
        elif y < -half_width_m - BAND_SURE_M:
            below = True
        else:
            return False, None  # a corner on (or too near) the border
    if not inside:
        return (True, None) if not (above and below) else (False, None)
    lo, hi = min(inside), max(inside)
    if len(inside) < len(corners):
        n = len(corners)
        for k in range(n):
            (x0, y0), (x1, y1) = corners[k], corners[(k + 1) % n]
            for border in (half_width_m, -half_width_m):
                if (y0 - border) * (y1 - border) < 0.0:
                    x = x0 + (border - y0) * (x1 - x0) / (y1 - y0)
                    if not lo + BAND_SURE_M < x < hi - BAND_SURE_M:
                        return False, None  # a crossing is (or may be) the extreme
    return True, (float(lo), float(hi))


def obstacles(
    agents: Sequence[AgentReading],
    kerb: Callable[[str], bool],
    ego_in_junction: bool,
    path: Path,
    leader: Leader | None,
) -> list[expert.Obstacle]:
    """Vehicles and people on (or entering) the ego's path, and the lane leader.

    A box is on the path when its extent across the path comes within the ego's half width plus
    a margin (0.35 m vehicles, 0.8 m people on the road, 0 at the kerb); a vehicle, by the part
    of its box inside that corridor ahead of the front (`corridor_span`). People are also taken
    where they will be in 1 s and 2 s at their speed. `kerb(lane_id)` says whether a lane is a
    sidewalk or walking area; the leader's gap gets back the ego vType's 1 m minGap.
    """
    pts, s = path.pts, path.s
    ids, xy, yaw, spd, length, width, is_ped, kerb_l = [], [], [], [], [], [], [], []
    for a in agents:
        d = dims(a.type_id)
        ped = d[3] == "pedestrian"
        ids.append(a.agent_id)
        xy.append(centre_xy(a.front_xy_m, a.yaw_rad, d[0]))
        yaw.append(a.yaw_rad)
        spd.append(a.speed_mps)
        length.append(d[0])
        width.append(d[1])
        is_ped.append(ped)
        kerb_l.append(ped and kerb(a.lane_id))
    out = []
    half_w = 0.5 * EGO_DIMS_M[1]
    if ids:
        xy_a = np.asarray(xy)
        yaw_a = np.asarray(yaw)
        spd_a = np.asarray(spd)
        length = np.array(length)
        width = np.array(width)
        is_ped = np.array(is_ped)
        # People on a sidewalk or walking area count only where they will be (entering the
        # road), or where the car's swept body would touch them (below), not where they
        # stand: someone waiting at the kerb is not on the path, and yielding to them would
        # deadlock with SUMO, where they wait for the car.
        kerb_a = np.asarray(kerb_l)
        near = np.hypot(*(xy_a - pts[0]).T) < s[-1] + 15.0
        if near.any():
            k = np.flatnonzero(near)
            # Now, and for pedestrians also where they will be in 1 s and 2 s (horizons); the
            # sets are projected onto the path in one pass, with the people checked against
            # the swept body below.
            sels, pos = [], []
            now = k[~kerb_a[k]]
            if len(now):
                sels.append(now)
                pos.append(xy_a[now])  # at horizon 0 s: where they are
            walking = is_ped[k] & (spd_a[k] > 0.2)
            if ego_in_junction:
                # Inside a junction, never brake for someone still on the kerb: SUMO
                # granted our passage, and stopping in it invites a crossing car into
                # our side (one of the three ego collisions in a 160-episode run).
                walking &= ~kerb_a[k]
            moving = k[walking]
            if len(moving):
                heading = np.empty((len(moving), 2))  # unit vectors, (n, 2)
                heading[:, 0] = np.cos(yaw_a[moving])
                heading[:, 1] = np.sin(yaw_a[moving])
                xy_m, spd_m = xy_a[moving], spd_a[moving, None]
                for h in (1.0, 2.0):
                    sels.append(moving)
                    pos.append(xy_m + h * spd_m * heading)
            n_hit = sum(len(p) for p in pos)
            peds = k[is_ped[k]]  # standing or walking, kerb included: for the swept body
            if len(peds):
                pos.append(xy_a[peds])
            if pos:
                along_all, lat_all, head_all = project_many(pos, pts, s, path.segments)
            if n_hit:
                sel = np.concatenate(sels) if len(sels) > 1 else sels[0]
                p = np.concatenate(pos[: len(sels)]) if len(sels) > 1 else pos[0]
                along, lat, head = along_all[:n_hit], lat_all[:n_hit], head_all[:n_hit]
                rel = yaw_a[sel] - head
                c, sn = np.abs(np.cos(rel)), np.abs(np.sin(rel))
                half_l, half_wd = 0.5 * length[sel], 0.5 * width[sel]
                across = half_l * sn + half_wd * c
                ahead = half_l * c + half_wd * sn
                margin = np.where(is_ped[sel], np.where(kerb_a[sel], 0.0, 0.8), VEHICLE_MARGIN_M)
                hit = (lat - across < half_w + margin) & (along + ahead > 0.0)
                hit &= along - ahead < s[-1]
                for j in np.flatnonzero(hit):
                    i = sel[j]
                    if is_ped[i]:
                        gap = float(along[j] - ahead[j])
                        out.append(expert.Obstacle(gap, 0.0, "pedestrian", ids[i]))
                        continue
                    # The extents above bound a skewed box by a rectangle along the path, which
                    # joins a corner in the corridor beside the ego to a far end ahead of it
                    # beside the lane (a 12 m bus 3 degrees off the opposite direction): a
                    # vehicle counts by the part of its box in the corridor, if that is ahead.
                    span = corridor_span(
                        p[j],
                        yaw_a[i],
                        length[i],
                        width[i],
                        path,
                        half_w + VEHICLE_MARGIN_M,
                        (float(along[j]), float(lat[j]), float(head[j])),
                    )
                    if span is None or span[1] <= 0.0 or span[0] >= s[-1]:
                        continue
                    v_along = max(0.0, float(spd_a[i] * np.cos(rel[j])))
                    out.append(expert.Obstacle(span[0], v_along, "vehicle", ids[i]))
            # people standing or walking, kerb included, against the body swept on turns
            if len(peds):
                along, lat = along_all[n_hit:], lat_all[n_hit:]
                ok = (lat < half_w + 2.0) & (along > -EGO_DIMS_M[0]) & (along < SWEEP_AHEAD_M)
                cand = peds[ok]
                if len(cand):
                    # someone standing at the kerb holds the car only where its body would
                    # cover where they stand (their centre): a margin there deadlocks with
                    # SUMO's walkers, who wait for the car (arterial, build seed 0, episode 9)
                    standing = kerb_a[cand] & (spd_a[cand] < 0.2)
                    radius = np.where(standing, 0.0, 0.5 * np.maximum(length[cand], width[cand]))
                    clear = np.where(standing, 0.0, SWEEP_CLEARANCE_M)
                    reach = swept_contact(
                        xy_a[cand], radius, path, EGO_DIMS_M[0], half_w, clearance_m=clear
                    )
                    for i, u in zip(cand, reach):
                        if np.isfinite(u):
                            out.append(expert.Obstacle(float(u), 0.0, "pedestrian", ids[i]))
    if leader is not None:
        # SUMO's gap leaves out the ego vType's minGap (1 m); "lead:" marks the lane leader
        out.append(
            expert.Obstacle(
                leader.gap_m + 1.0, leader.speed_mps, "vehicle", "lead:" + leader.agent_id
            )
        )
    return out


def crossing_obstacles(
    agents: Sequence[AgentReading],
    net: RoadNet,
    kerb: Callable[[str], bool],
    path: Path,
    ego_speed_mps: float,
    ego_in_junction: bool = False,
) -> list[expert.Obstacle]:
    """People on, or about to step onto, a crossing that the ego's path crosses ahead.

    A person counts while on the crossing and not yet past the ego's corridor (its half width
    + CORRIDOR_SLACK_M around where the path crosses), or, while the ego is not yet inside the
    junction, while walking on the kerb towards a crossing (their next edge) within STEP_ON_M
    of it. Inside a junction the ego does not stop for someone still on the kerb: standing
    there its body can cover the crossing behind it, and SUMO's walkers then walk into it
    (measured: "ego hit p146 (crossing)", downtown seed 129). Someone still outside the corridor is
    let go first only when the ego, at its speed (2 m/s at least), clears the crossing
    CLEAR_FIRST_S before they reach the corridor. The obstacle is the crossing's near edge.
    """
    out = []
    band = 0.5 * EGO_DIMS_M[1] + CORRIDOR_SLACK_M
    for a in agents:
        if a.type_id != PED_TYPE:
            continue
        if is_crossing(a.lane_id):
            lane, on = a.lane_id, True
        elif (
            not ego_in_junction
            and a.speed_mps > 0.2
            and is_crossing(a.next_edge + "_0")
            and kerb(a.lane_id)
        ):
            lane, on = a.next_edge + "_0", False
        else:
            continue
        crossing = net.lane(lane)
        c = crossing.pts
        if len(c) < 2:
            continue
        hit = first_intersection(path.pts, path.s, c)
        if hit is None or hit[0] < 0.0:
            continue
        s_x, u_x = hit
        c_s = crossing.cum_m
        u_p, lat, head = project(
            np.asarray([a.front_xy_m], dtype=np.float64), c, c_s, crossing.segments
        )
        u_p = float(u_p[0])
        if on:
            if a.speed_mps < 0.2:
                direction = 0.0  # standing on the crossing: only in the corridor counts
            else:
                direction = 1.0 if np.cos(a.yaw_rad - head[0]) >= 0.0 else -1.0
        else:
            to_start, to_end = abs(u_p), abs(c_s[-1] - u_p)
            if min(to_start, to_end) > STEP_ON_M + float(lat[0]):
                continue
            direction = 1.0 if to_start <= to_end else -1.0  # onto it from the nearer end
        ahead = (u_x - u_p) * direction  # how far the person still walks to the path
        if abs(u_x - u_p) > band:
            if direction == 0.0 or ahead < 0.0:
                continue  # standing off the corridor, or already past it
            t_person = (ahead - band) / max(a.speed_mps, 0.5)
            t_ego = (s_x + CROSSING_HALF_WIDTH_M + EGO_DIMS_M[0]) / max(ego_speed_mps, 2.0)
            if t_ego + CLEAR_FIRST_S < t_person:
                continue
        out.append(expert.Obstacle(s_x - CROSSING_HALF_WIDTH_M, 0.0, "pedestrian", a.agent_id))
    return out


def foe_eta_s(
    agents: Sequence[AgentReading],
    net: RoadNet,
    junction: str,
    own_edge: str,
    stop_controlled: Callable[[str], bool] | None = None,
    foes: frozenset[str] | None = None,
) -> float | None:
    """Soonest time (s) any vehicle moving faster than 1 m/s on another lane into `junction`
    reaches it (straight-line distance from its front to its lane's end over its speed), 0 for
    one already inside it; None if none. People are left to the crossing rule.

    With `stop_controlled` (lane id -> its entry has a stop sign), a vehicle standing within
    STOP_FOE_M of the end of such a lane also counts, with 0: once its stop is done it may start
    at any moment, and SUMO's right-of-way model let one start into the ego's left turn from
    a minor link (arterial seed 172, "v30 hit ego").

    With `foes` (Network.internal_foes of the ego's passage), only vehicles whose passage can
    conflict with the ego's count: inside the junction on one of those lanes, or on a lane with
    a link through one. Counting every vehicle, a stop sign on a busy road never saw a 5 s gap
    and the ego stood until SUMO took it away (boulevard-short-04, -long-05, issue 38)."""
    best = None
    prefix = f":{junction}_"
    for a in agents:
        if a.type_id == PED_TYPE or not a.lane_id:
            continue
        moving = a.speed_mps > 1.0
        if a.lane_id.startswith(prefix):
            if not moving or is_crossing(a.lane_id) or _WALKING_AREA.search(a.lane_id):
                continue
            if foes is not None and a.lane_id not in foes:
                continue
            eta = 0.0
        elif a.lane_id.startswith(":"):
            continue
        else:
            edge = a.lane_id.rsplit("_", 1)[0]
            if edge == own_edge or net.to_junction(edge) != junction:
                continue
            if foes is not None and not any(k.via_lane_id in foes for k in net.links(a.lane_id)):
                continue
            end = net.lane(a.lane_id).pts[-1]
            dist = float(np.hypot(end[0] - a.front_xy_m[0], end[1] - a.front_xy_m[1]))
            if moving:
                eta = dist / a.speed_mps
            elif stop_controlled and dist < STOP_FOE_M and stop_controlled(a.lane_id):
                eta = 0.0
            else:
                continue
        best = eta if best is None else min(best, eta)
    return best


def junction_clear(
    agents: Sequence[AgentReading],
    junction: str | None,
    kerb: Callable[[str], bool],
    foes: frozenset[str] | None = None,
) -> bool:
    """No other vehicle is inside `junction` (on its internal lanes; with `foes`, on one of
    those: Network.internal_foes of the ego's passage); people on its crossings and walking
    areas are left to the pedestrian rule and SUMO. True without a junction."""
    if junction is None:
        return True
    prefix = f":{junction}_"
    for a in agents:
        lane = a.lane_id
        if lane.startswith(prefix) and not kerb(lane) and not is_crossing(lane):
            if foes is None or lane in foes:
                return False
    return True


def attribute_hold(
    stop_distance_m: float | None,
    path: Path,
    agents: Sequence[AgentReading],
    ego_in_junction: bool,
    link_dist: tuple[float, ...],
) -> str:
    """Name what SUMO's safety model yields to when it holds the ego below the command:
    "stop_sign", "pedestrian" (someone within 5 m of the path, 2 m behind to 50 m ahead),
    "junction" (in one or within 50 m of the next link) or else "vehicle"."""
    if stop_distance_m is not None and stop_distance_m < 10.0:
        return "stop_sign"
    peds = [a.front_xy_m for a in agents if a.agent_id.startswith("p")]
    if peds:
        along, lat, _ = project(np.asarray(peds, dtype=np.float64), path.pts, path.s)
        if np.any((lat < 5.0) & (along > -2.0) & (along < 50.0)):
            return "pedestrian"
    if ego_in_junction or (link_dist and link_dist[0] < 50.0):
        return "junction"
    return "vehicle"
