"""What the expert reads of the world and where it plans to drive, from the ego's state now,
whoever drives it.

`Planner.expert_input()` gathers the expert's input (expert.ExpertInput) from the latest
snapshot: the speed limits and curvature of the path ahead, the obstacles on it and the people
about to cross it (perception.py), the next signal and stop-controlled entry, the junction ahead
and its foes, the end of the route. The expert's step (world.py) decides on it every step;
`Planner.plan()` rolls the expert out on it (expert.rollout) along the route's lanes: the
privileged plan a policy is labelled with and compared to (World.expert_plan), as box
centres along the route's lanes (`centres_along`), merging from beside the lane (`shifted`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

import datagen.world.expert as expert
import datagen.world.perception as perception
import datagen.world.route as route
from datagen.world.behaviour import EGO_DECEL_SLACK
from datagen.world.fleet import EGO_DIMS_M
from datagen.world.route import PATH_LOOKAHEAD_M
from datagen.world.rules import stop_foes
from datagen.world.simulation import Simulation

# The expert reads the green left within this of a signalled junction, plus its comfortable
# stopping distance (read at 30 m only, a car coming at 17 m/s was past stopping: arterial,
# build seed 0, episode 20)
GREEN_CHECK_M = 30.0
STOP_FOE_CHECK_M = 10.0  # within this of a stop line the expert reads its junction's foes
LANE_CHANGE_S = 2.0  # the expert's plan changes lanes as SUMO does for it (sumo.py)


def centres_along(
    path: route.Path, front_s_m: Sequence[float], length_m: float, heading_rad: float | None = None
) -> np.ndarray:
    """(K, 2) world box centres of a car of `length_m` whose front is `front_s_m[k]` along `path`
    (from its first point) and whose rear follows the path: the centre lies half a length back
    from the front towards the point one length back along the path, as SUMO places a vehicle
    from its front and back positions on its lanes. Before the path's first point the path is
    extended straight back along `heading_rad` (the car's heading, world, rad: a car whose front
    is at the path's start then has its centre where it is) or, without it, along the path's
    first segment."""
    seg = path.segments
    u = seg.u if heading_rad is None else np.array([math.cos(heading_rad), math.sin(heading_rad)])
    back = path.pts[0] - u * (length_m + 1.0)
    pts = np.vstack([back, path.pts])
    s = np.concatenate([[-(length_m + 1.0)], path.s])
    out = np.empty((len(front_s_m), 2))
    for k, f in enumerate(front_s_m):
        front = np.array(route.point_along(pts, s - s[0], f - s[0]))
        rear = np.array(route.point_along(pts, s - s[0], f - length_m - s[0]))
        d = front - rear
        n = float(np.hypot(d[0], d[1]))
        out[k] = front - 0.5 * length_m * (d / n if n > 1e-6 else u)
    return out


def shifted(path: route.Path, offset_m: float, ramp_m: float, step_m: float = 1.0) -> route.Path:
    """`path` moved `offset_m` to its left at its start, the offset fading out smoothly (a smooth
    step) within `ramp_m` along it: the way from beside a lane, or from the lane before a
    lane change, onto `path`'s lane. link_dist and seg_lanes are `path`'s."""
    if abs(offset_m) < 1e-3:
        return path
    end = min(path.s[-1], ramp_m)
    s = np.arange(0.0, end + 1e-9, step_m)
    if len(s) < 2:
        return path
    pts = np.array([route.point_along(path.pts, path.s, max(d, 1e-6)) for d in s])
    head = np.diff(pts, axis=0)
    head = np.vstack([head, head[-1:]])
    head /= np.maximum(np.hypot(head[:, 0], head[:, 1]), 1e-9)[:, None]
    normal = np.stack([-head[:, 1], head[:, 0]], axis=1)
    u = np.clip(s / max(ramp_m, 1e-6), 0.0, 1.0)
    fade = 1.0 - u * u * (3.0 - 2.0 * u)
    pts = np.vstack([pts + normal * (offset_m * fade)[:, None], path.pts[path.s > end + 1e-6]])
    step = np.hypot(*np.diff(pts, axis=0).T)
    pts = pts[np.concatenate([[True], step > 1e-6])]
    ss = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(pts, axis=0).T))])
    return route.Path(pts, ss, path.link_dist, path.seg_lanes)


class Planner:
    """The expert's input and plan from the ego's state in `sim` now."""

    def __init__(self, sim: Simulation):
        self._sim = sim
        self._last_lane = ""  # the last lane outside a junction the plan saw

    def expert_input(self) -> expert.ExpertInput:
        """The expert's input from the latest snapshot, path and signals (world frame, m)."""
        sim = self._sim
        snap, net, path = sim.snap, sim.net, sim.path
        ego = snap.ego
        limit, limits_ahead = route.speed_limits(net, ego.lane_id, path)
        curv = route.curvature_ahead(path, expert.MIN_CURVATURE_1PM)
        sig = sim.signals
        # the end of the route binds only when it will not be extended (any more)
        remaining = sim.remaining_route()
        route_end = (
            remaining
            if remaining < (PATH_LOOKAHEAD_M if not sim.config.reroute else 100.0)
            else None
        )
        leader = sim.sumo.leader(snap, PATH_LOOKAHEAD_M)
        obstacles = perception.obstacles(
            snap.agents, sim.is_kerb, ego.lane_id.startswith(":"), path, leader
        )
        obstacles += perception.crossing_obstacles(
            snap.agents,
            net,
            sim.is_kerb,
            path,
            ego.speed_mps,
            ego.lane_id.startswith(":"),
        )
        junction = route.junction_ahead(ego.lane_id, path, snap.links)
        waits_inside, foe_eta = False, None
        if junction is not None and route.waits_inside(net, snap.links[0]):
            waits_inside = True
            foe_eta = perception.foe_eta_s(
                snap.agents,
                net,
                route.junction_of(snap.links[0].via_lane_id),
                ego.road_id,
                net.stop_controlled,
            )
        stop_foe = None
        stop_d = sig.stop_distance_m
        if stop_d is not None and sig.stop_junction and stop_d < STOP_FOE_CHECK_M:
            stop_foe = perception.foe_eta_s(
                snap.agents, net, sig.stop_junction, ego.road_id, foes=stop_foes(net, snap.links)
            )
        green_left = None
        b = sim.profile.ego_comfort_decel_mps2  # from where it can still stop comfortably
        near = junction is not None and junction[0] < GREEN_CHECK_M + ego.speed_mps**2 / (2 * b)
        if near and sig.light == "green" and abs(sig.light_distance_m - junction[0]) < 3.0:
            green_left = sim.sumo.switch_in_s(snap.next_signals[0].tls_id)
        return expert.ExpertInput(
            speed_mps=ego.speed_mps,
            speed_limit_mps=float(limit),
            limits_ahead=limits_ahead,
            curvature_ahead=curv,
            obstacles=tuple(obstacles),
            light=sig.light,
            light_distance_m=sig.light_distance_m,
            stop_distance_m=sig.stop_distance_m,
            stop_done=sig.stop_distance_m is not None and sim.rules.stop_done_lane == ego.lane_id,
            route_end_m=route_end,
            junction_entry_m=junction[0] if junction else None,
            junction_exit_m=junction[1] if junction else None,
            waits_inside=waits_inside,
            foe_eta_s=foe_eta,
            green_left_s=green_left,
            stop_foe_eta_s=stop_foe,
        )

    def plan(self, times_s: tuple[float, ...]) -> tuple[np.ndarray, expert.Decision] | None:
        """Where the expert would put the ego's box centre at each of `times_s`
        ((len(times_s), 2), world frame, m) and its decision now; None off the network (see
        World.expert_plan)."""
        sim = self._sim
        if not sim.snap.ego.lane_id:
            return None
        p = sim.profile
        dists, dec = expert.rollout(
            self.expert_input(), p, times_s, EGO_DECEL_SLACK * p.ego_comfort_decel_mps2
        )
        path = self._path()
        yaw = sim.snap.ego.yaw_rad
        return centres_along(path, dists, EGO_DIMS_M[0], yaw), dec

    def _path(self) -> route.Path:
        """The path the expert's plan follows, from where the ego's front is: along the route's
        lanes (inside a junction: the route's own passage, whatever internal lane SUMO maps a
        placed ego to where passages overlap), along the next lane over where the ego's lane
        does not lead along its route (what SUMO's strategic lane changing reads,
        getBestLanes), starting beside that lane's centre line as far as the ego is and
        merging into it within LANE_CHANGE_S of driving (SUMO's lane changes in the data take
        as long: sumo.py --lanechange.duration)."""
        sim = self._sim
        net = sim.net
        ego = sim.snap.ego
        front = np.array([ego.front_xy_m])
        ahead = sim.route[sim.route_index() + 1 :]
        target = None
        if ego.lane_id.startswith(":"):
            passage = self._passage(ahead)
            if passage and ego.lane_id not in passage:
                target = min(passage, key=lambda lid: self._lane_gap(lid, front)[1])
        else:
            self._last_lane = ego.lane_id
            offset = sim.sumo.ego_lane_offset()
            edge, idx = ego.lane_id.rsplit("_", 1)
            k = int(idx) + (1 if offset > 0 else -1)
            if offset != 0 and 0 <= k < net.lane_count(edge):
                target = f"{edge}_{k}"
        path = sim.path
        if target is not None:
            pos = self._lane_gap(target, front)[0]
            if target.startswith(":"):  # path_ahead walks out of the junction by itself
                exit_lane = route.exit_chain(net, target)[-1:]
                links = route.route_links(net, exit_lane[0], ahead[1:], 4) if exit_lane else ()
            else:
                links = route.route_links(net, target, ahead, 4)
            path = route.path_ahead(net, target, pos, links, ego.front_xy_m, ego.yaw_rad)
        beside = float((front[0] - path.pts[0]) @ path.segments.normal)  # m left of its start
        return shifted(path, beside, LANE_CHANGE_S * max(ego.speed_mps, 3.0))

    def _passage(self, ahead: tuple[str, ...]) -> list[str]:
        """The internal lanes of the junction passage from the last lane the ego was on before
        it to the route's next edge ([] if none)."""
        if not ahead or not self._last_lane:
            return []
        links = route.route_links(self._sim.net, self._last_lane, ahead, 1)
        if not links or not links[0].via_lane_id:
            return []
        return route.via_chain(self._sim.net, links[0].via_lane_id)

    def _lane_gap(self, lane_id: str, xy: np.ndarray) -> tuple[float, float]:
        """(position along lane `lane_id` in lane-length units, distance from it, m) of the
        point (1, 2) `xy`."""
        lane = self._sim.net.lane(lane_id)
        s, d, _ = route.project(xy, lane.pts, lane.cum_m, lane.segments)
        return float(s[0]) * lane.length_m / max(float(lane.cum_m[-1]), 1e-9), float(d[0])
