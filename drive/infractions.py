"""Infractions of one route, judged geometrically every 0.1 s step from the ground truth the
sensors are made from (datagen.state.FrameState: the agents' boxes, every signal's state) and
the scene layout (drive/layout.py). Each judge has its thresholds named at the top and cites
its source: carla-simulator/scenario_runner 0.9.10 `atomic_criteria.py`, what leaderboard 1.0
runs (drive/score.py says where this project differs and why). The same judge scores every
policy, the expert included.

Per type:

- collision_vehicle / collision_pedestrian (CollisionTest): the ego's box starts to overlap an
  agent's box (FrameState.agents; SUMO's own collision list misses a vehicle moved by
  moveToXY, eclipse-sumo/sumo#6327). Vehicles and bicycles are vehicles, people are
  pedestrians. As CollisionTest: the same agent again only after COLLISION_ID_S, and nothing
  within COLLISION_AREA_M of an earlier collision's place (forgotten once the ego is
  COLLISION_FORGET_M from it). A collision ends nothing.
- collision_layout: the box starts to touch an obstacle footprint (building, pole, sign, tree
  trunk) or a wheel mounts the kerb (a sidewalk or walking area), same debounce.
- off_road: a wheel leaves the drivable area; `off_road_share` is the share of the distance
  driven so, `off_route_share` (the IS factor) the share with the box centre outside the route's
  lanes (OutsideRouteLanesTest).
- red_light (RunningRedLightTest): the ego's front bumper (either corner or its middle) crosses
  a signalised stop line of the route (gets more than CROSS_M past it), in the direction of
  travel, while the signal links
  governing the lane segment it crosses were red in the step before. The line's own signal is
  read, wherever the ego is (off its lane, off the network).
- stop_sign (RunningStopTest): the front crosses a stop-controlled line without having been
  slower than BLOCKED_SPEED_MPS while within STOP_ZONE_M before it.
- route_deviation (InRouteTest, ends the route): the front farther than DEVIATION_M from the
  route, or more than DEVIATION_SHARE of the route's length progressed while farther than
  DEVIATION_M / 2; or SUMO took the ego out of the simulation away from its route (`end`).
- agent_blocked (ActorSpeedAboveThresholdTest, ends the route): slower than
  BLOCKED_SPEED_MPS for BLOCKED_S.
- route_timeout (ends the route): more than score.route_timeout_s(length) simulated.

Route completion (RouteCompletionTest): progress is the front's projection on the route's
centreline, searched from PROGRESS_BACK_M behind to PROGRESS_AHEAD_M ahead of the progress so
far (the leaderboard checks two waypoints ahead) and growing at most 1.5 times as fast as the
front moves (PROGRESS_GAIN), so a shortcut across a block earns nothing; the route is complete once progress is over
score.COMPLETE_PCT and the front within score.END_DISTANCE_M of the route's end.

Beyond the leaderboard: `min_ttc_s`, the smallest time to collision with any vehicle or person
(both keep their velocity; boxes overlap within TTC_HORIZON_S), and `traffic_delay_s`, the
vehicle-seconds that vehicles within NEAR_M of the ego lose against their own top speed in the
run (sum over steps of dt x (1 - v / v_max)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from datagen.state import AgentState, FrameState
from drive.controller import VehicleConfig
from drive.geometry import RouteGeometry, StopLine
from drive.layout import Layout, boxes_overlap
from drive.score import (
    BLOCKED_S,
    BLOCKED_SPEED_MPS,
    COMPLETE_PCT,
    DEVIATION_M,
    DEVIATION_SHARE,
    END_DISTANCE_M,
    route_timeout_s,
)
from schemas.dataset import box_corners

STOP_ZONE_M = 5.0  # a stop counts within this distance before a stop sign's line
CROSS_M = 0.1  # a line is crossed when the front gets more than this past it: SUMO stops a car
# at the end of its lane with its front exactly on the line (boulevard-long-03 at C5)
RED_STATES = "ru"  # SUMO link states that mean red (red, red-yellow)
PROGRESS_BACK_M = 10.0  # progress is searched this far behind the progress so far ...
PROGRESS_AHEAD_M = 15.0  # ... and this far ahead of it. RouteCompletionTest looks two 1 m
# waypoints ahead; our centreline steps sideways by up to three lanes where the lane a
# junction passage enters is not the lane of the next connection (drive/geometry.py; a 6.4 m
# step on boulevard-long-09 stopped the progress with a 5 m window), and the cap below, not the
# window, keeps a shortcut from earning progress
PROGRESS_GAIN = (1.5, 0.1)  # per step at most 1.5 x the front's movement + 0.1 m (a bend's
# centreline can be longer than the front's path on another lane)
START_SEARCH_M = 40.0  # where the first state's front may be along the route
COLLISION_ID_S = 5.0  # CollisionTest.MAX_ID_TIME: the last agent hit is not counted again so long
COLLISION_AREA_M = 3.0  # CollisionTest.MIN_AREA_OF_COLLISION: no new collision this close ...
COLLISION_FORGET_M = 5.0  # ... to an earlier one's place (MAX_AREA_OF_COLLISION: then forgotten)
WHEEL_INSET_M = 0.15  # wheels' outer edge inside the body's side
TTC_HORIZON_S = 5.0
TTC_STEP_S = 0.1
TTC_RANGE_M = 40.0  # agents farther than this are not checked for TTC
NEAR_M = 50.0  # traffic delay counts vehicles within this distance of the ego


def wheels_xy(ego: AgentState) -> np.ndarray:
    """(4, 2) world points where the ego's wheels touch the ground: the axles at the ends of
    drive.controller.VehicleConfig's wheelbase, WHEEL_INSET_M inside the body's sides."""
    p = ego.pose
    c, s = math.cos(p.yaw_rad), math.sin(p.yaw_rad)
    hx = 0.5 * min(VehicleConfig().wheelbase_m, ego.length_m)
    hy = 0.5 * ego.width_m - WHEEL_INSET_M
    local = np.array([[hx, hy], [-hx, hy], [-hx, -hy], [hx, -hy]])
    return np.stack(
        [p.x_m + c * local[:, 0] - s * local[:, 1], p.y_m + s * local[:, 0] + c * local[:, 1]], 1
    )


def front_xy(ego: AgentState) -> np.ndarray:
    """(3, 2) world points of the ego's front bumper: its left corner, middle, right corner."""
    p = ego.pose
    c, s = math.cos(p.yaw_rad), math.sin(p.yaw_rad)
    hl, hw = 0.5 * ego.length_m, 0.5 * ego.width_m
    local = np.array([[hl, hw], [hl, 0.0], [hl, -hw]])
    return np.stack(
        [p.x_m + c * local[:, 0] - s * local[:, 1], p.y_m + s * local[:, 0] + c * local[:, 1]], 1
    )


def crossed(p0: np.ndarray, p1: np.ndarray, seg: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """(K,) bool: which of the segments `seg` (K, 2, 2) any of the moves p0 -> p1 (P, 2) crosses
    in `direction` (2,) (from the side it points away from to the side it points to; ending
    on a segment counts, starting on one does not)."""
    p0 = np.asarray(p0, np.float64)[:, None]  # (P, 1, 2)
    p1 = np.asarray(p1, np.float64)[:, None]
    a, b = seg[None, :, 0], seg[None, :, 1]  # (1, K, 2)

    def side(o, q, r):  # z of (q - o) x (r - o)
        return (q[..., 0] - o[..., 0]) * (r[..., 1] - o[..., 1]) - (q[..., 1] - o[..., 1]) * (
            r[..., 0] - o[..., 0]
        )

    before = ((p0 - a) * direction).sum(-1)  # signed distance past the line's point a
    after = ((p1 - a) * direction).sum(-1)
    forward = (before < 0.0) & (after >= 0.0)
    d1, d2 = side(a, b, p0), side(a, b, p1)
    d3, d4 = side(p0, p1, a), side(p0, p1, b)
    straddle = (d1 * d2 <= 0.0) & (d3 * d4 <= 0.0)
    return (forward & straddle).any(0)


def link_red(signals: dict[str, str], tls_id: str, links: tuple[int, ...]) -> bool:
    """Every link `links` of traffic light `tls_id` is red in `signals` ({id: state string});
    False when the light or its links are unknown."""
    state = signals.get(tls_id)
    if not state or not links or max(links) >= len(state):
        return False
    return all(state[i] in RED_STATES for i in links)


@dataclass(frozen=True)
class Event:
    """One infraction: its type (score.INFRACTION_TYPES), simulation time s, world position of
    the ego's centre m, and what it was about (an agent id, a junction id)."""

    kind: str
    time_s: float
    x_m: float
    y_m: float
    detail: str = ""

    def to_dict(self) -> dict:
        return {
            "kind": self.kind,
            "time_s": round(self.time_s, 2),
            "x_m": round(self.x_m, 2),
            "y_m": round(self.y_m, 2),
            "detail": self.detail,
        }


def time_to_collision(ego: AgentState, agents: list[AgentState]) -> float:
    """Smallest time (s, multiples of TTC_STEP_S up to TTC_HORIZON_S, inf if none) at which the
    ego's box overlaps an agent's box with both keeping their velocity."""
    ev = ego.speed_mps * np.array([math.cos(ego.pose.yaw_rad), math.sin(ego.pose.yaw_rad)])
    r_ego = 0.5 * math.hypot(ego.length_m, ego.width_m)
    near, va = [], []
    for a in agents:
        v = a.speed_mps * np.array([math.cos(a.pose.yaw_rad), math.sin(a.pose.yaw_rad)])
        d = math.hypot(a.pose.x_m - ego.pose.x_m, a.pose.y_m - ego.pose.y_m)
        # only agents the relative motion can bring within reach of the ego in the horizon
        reach = float(np.hypot(*(v - ev))) * TTC_HORIZON_S + r_ego
        if d < TTC_RANGE_M and d < reach + 0.5 * math.hypot(a.length_m, a.width_m):
            near.append(a)
            va.append(v)
    if not near:
        return math.inf
    va = np.array(va)  # (A, 2) m/s
    ts = np.arange(0.0, TTC_HORIZON_S + 1e-9, TTC_STEP_S)
    base = np.stack(
        [box_corners(a.pose.x_m, a.pose.y_m, a.pose.yaw_rad, a.length_m, a.width_m) for a in near]
    )  # (A, 4, 2)
    e0 = box_corners(ego.pose.x_m, ego.pose.y_m, ego.pose.yaw_rad, ego.length_m, ego.width_m)
    # relative motion: move the agents by (v_a - v_ego) t, keep the ego where it is
    moved = base[None] + ((va - ev)[None] * ts[:, None, None])[:, :, None, :]  # (T, A, 4, 2)
    hit = boxes_overlap(e0, moved.reshape(-1, 4, 2)).reshape(len(ts), len(near)).any(1)
    if hit.any():
        return float(ts[int(np.argmax(hit))])
    return math.inf


@dataclass
class InfractionTracker:
    """Watches one route step by step; `step(frame)` after every SUMO step.

    Attributes:
        geometry, layout: the route and the town.
        events: the infractions so far, in time order.
        ended: None while the route runs, else "route_complete" or the ending infraction.
        complete: the route was completed (RouteCompletionTest, module docstring).
        progress_m: the front's progress along the route's centreline, m.
    """

    geometry: RouteGeometry
    layout: Layout
    events: list[Event] = field(default_factory=list)
    ended: str | None = None
    complete: bool = False
    progress_m: float = 0.0
    distance_m: float = 0.0
    off_road_m: float = 0.0
    off_route_m: float = 0.0
    far_m: float = 0.0  # progress made farther than DEVIATION_M / 2 from the route
    min_ttc_s: float = math.inf
    traffic_delay_s: float = 0.0
    start_time_s: float | None = None
    _start_s: float = 0.0
    _last: FrameState | None = None
    _front: np.ndarray | None = None  # (3, 2) the last step's front bumper points
    _signals: dict = field(default_factory=dict)  # the last step's signal states
    _touching: set = field(default_factory=set)
    _layout_touching: bool = False
    _off_road: bool = False
    _slow_s: float = 0.0
    _zone_min_speed: dict = field(default_factory=dict)
    _lines_done: set = field(default_factory=set)
    _hit_places: list = field(default_factory=list)  # (x, y) of collisions still remembered
    _last_hit: tuple = ("", -math.inf)  # (agent id, time s) of the last agent collision
    _top_speed: dict = field(default_factory=dict)

    @property
    def route_completion_pct(self) -> float:
        if self.complete:
            return 100.0
        span = self.geometry.length_m - self._start_s
        return 100.0 * min(1.0, max(0.0, (self.progress_m - self._start_s) / max(span, 1e-6)))

    def _add(self, kind: str, frame: FrameState, detail: str = "") -> None:
        p = frame.ego.pose
        self.events.append(Event(kind, frame.time_s, p.x_m, p.y_m, detail))

    @property
    def standing_s(self) -> float:
        """How long the ego has been slower than BLOCKED_SPEED_MPS, s."""
        return self._slow_s

    def end(self, kind: str, frame: FrameState, detail: str = "") -> None:
        """End the route by an infraction found outside the tracker (e.g. the world's own)."""
        if self.ended is None:
            self._add(kind, frame, detail)
            self.ended = kind

    def route_distance_m(self, frame: FrameState) -> float:
        """Distance from the ego's front to the route near the progress so far, m."""
        front = front_xy(frame.ego)[1]
        lo, hi = self.progress_m - PROGRESS_BACK_M, self.progress_m + PROGRESS_AHEAD_M
        return self.geometry.project([front], lo, hi)[1]

    def counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for e in self.events:
            out[e.kind] = out.get(e.kind, 0) + 1
        return out

    def step(self, frame: FrameState, dt_s: float = 0.1) -> None:
        """Judge one step (module docstring)."""
        if self.ended is not None:
            return
        ego = frame.ego
        p = ego.pose
        g = self.geometry
        front = front_xy(ego)  # (3, 2) left corner, middle, right corner
        if self._last is None:  # the first state: where the route starts for this ego
            s, _ = g.project(front[1:2], -1.0, START_SEARCH_M)
            self._start_s = self.progress_m = s
            self.start_time_s = frame.time_s
        last = self._last
        moved = (
            0.0
            if last is None
            else math.hypot(p.x_m - last.ego.pose.x_m, p.y_m - last.ego.pose.y_m)
        )
        self.distance_m += moved
        # progress along the route, searched near the progress so far, no faster than the front
        before = self.progress_m
        front_moved = 0.0 if self._front is None else float(np.hypot(*(front[1] - self._front[1])))
        s, lateral = g.project(front[1:2], before - PROGRESS_BACK_M, before + PROGRESS_AHEAD_M)
        gain, slack = PROGRESS_GAIN
        self.progress_m = max(before, min(s, before + gain * front_moved + slack))
        if lateral > 0.5 * DEVIATION_M:
            self.far_m += self.progress_m - before
        self._collisions(frame)
        self._layout(frame, moved)
        if self._front is not None:
            self._stop_lines(frame, self._front, front)
        self._front = front
        self._signals = dict(frame.signals)
        end_dist = float(np.hypot(*(front[1] - g.centre_xy_m[-1])))
        if self.route_completion_pct > COMPLETE_PCT and end_dist < END_DISTANCE_M:
            self.complete = True  # RouteCompletionTest
        # beyond the leaderboard
        self.min_ttc_s = min(self.min_ttc_s, time_to_collision(ego, list(frame.agents)))
        self._delay(frame, dt_s)
        # route-ending conditions
        if self.complete:
            self.ended = "route_complete"
        elif lateral > DEVIATION_M:  # InRouteTest
            self._add("route_deviation", frame, f"{lateral:.1f} m from the route")
            self.ended = "route_deviation"
        elif self.far_m > DEVIATION_SHARE * g.length_m:
            far = f"{self.far_m:.0f} m of the route driven over {0.5 * DEVIATION_M:.0f} m off it"
            self._add("route_deviation", frame, far)
            self.ended = "route_deviation"
        else:
            self._slow_s = self._slow_s + dt_s if ego.speed_mps < BLOCKED_SPEED_MPS else 0.0
            if self._slow_s >= BLOCKED_S:
                self._add("agent_blocked", frame, f"stood {BLOCKED_S:.0f} s")
                self.ended = "agent_blocked"
            elif frame.time_s - self.start_time_s > route_timeout_s(g.length_m - self._start_s):
                self._add("route_timeout", frame)
                self.ended = "route_timeout"
        self._last = frame

    def _debounced(self, frame: FrameState, agent_id: str) -> bool:
        """CollisionTest's debounce (module docstring): True if this contact is not counted;
        else remember it."""
        ego = frame.ego.pose
        if agent_id and self._last_hit[0] == agent_id:
            if frame.time_s - self._last_hit[1] <= COLLISION_ID_S:
                return True
        for x, y in self._hit_places:
            if math.hypot(ego.x_m - x, ego.y_m - y) <= COLLISION_AREA_M:
                return True
        self._hit_places.append((ego.x_m, ego.y_m))
        if agent_id:  # layout contacts have no id (CARLA's static objects: id 0)
            self._last_hit = (agent_id, frame.time_s)
        return False

    def _collisions(self, frame: FrameState) -> None:
        ego = frame.ego
        self._hit_places = [
            (x, y)
            for x, y in self._hit_places
            if math.hypot(ego.pose.x_m - x, ego.pose.y_m - y) <= COLLISION_FORGET_M
        ]
        e = box_corners(ego.pose.x_m, ego.pose.y_m, ego.pose.yaw_rad, ego.length_m, ego.width_m)
        agents = [
            a
            for a in frame.agents
            if math.hypot(a.pose.x_m - ego.pose.x_m, a.pose.y_m - ego.pose.y_m)
            < 0.5 * (a.length_m + ego.length_m) + 1.0
        ]
        touching = set()
        if agents:
            boxes = np.stack(
                [
                    box_corners(a.pose.x_m, a.pose.y_m, a.pose.yaw_rad, a.length_m, a.width_m)
                    for a in agents
                ]
            )
            hit = boxes_overlap(e, boxes)
            for a, h in zip(agents, hit):
                if not h:
                    continue
                touching.add(a.track_id)
                if a.track_id not in self._touching and not self._debounced(frame, a.track_id):
                    kind = "collision_pedestrian" if a.cls == "pedestrian" else "collision_vehicle"
                    self._add(kind, frame, f"{a.track_id} ({a.cls})")
        self._touching = touching

    def _layout(self, frame: FrameState, moved_m: float) -> None:
        ego = frame.ego
        p = ego.pose
        corners = box_corners(p.x_m, p.y_m, p.yaw_rad, ego.length_m, ego.width_m)
        wheels = wheels_xy(ego)
        kerb = self.layout.kerb_points(wheels)
        on_kerb = bool(kerb.any())
        touching = on_kerb or self.layout.hits_obstacle(corners)
        if touching and not self._layout_touching and not self._debounced(frame, ""):
            self._add("collision_layout", frame, "kerb" if on_kerb else "obstacle")
        self._layout_touching = touching
        off = not bool(self.layout.road_points(wheels, kerb).all())
        if off and not self._off_road:
            self._add("off_road", frame)
        self._off_road = off
        if off:
            self.off_road_m += moved_m
        if not self.layout.on_road(p.x_m, p.y_m) or not self.geometry.in_lanes(p.x_m, p.y_m):
            self.off_route_m += moved_m

    def _stop_lines(self, frame: FrameState, front0: np.ndarray, front1: np.ndarray) -> None:
        speed = frame.ego.speed_mps
        mid = front1[1]
        for k, line in enumerate(self.geometry.stop_lines):
            if k in self._lines_done:
                continue
            if line.kind == "stop" and _in_zone(line, mid):
                self._zone_min_speed[k] = min(self._zone_min_speed.get(k, math.inf), speed)
            u = line.direction if line.direction is not None else _across(line)
            hit = crossed(front0, front1, line.segments() + CROSS_M * u, u)
            if not hit.any():
                continue
            self._lines_done.add(k)
            if line.kind == "light":
                # the signal the ego saw before crossing: the step before's state
                lanes = np.flatnonzero(hit)
                links = line.lane_links
                red = any(
                    link_red(self._signals, line.tls_id, links[i] if i < len(links) else ())
                    for i in lanes
                )
                if red:
                    self._add("red_light", frame, line.junction)
            elif self._zone_min_speed.get(k, math.inf) > BLOCKED_SPEED_MPS:
                self._add("stop_sign", frame, line.junction)

    def _delay(self, frame: FrameState, dt_s: float) -> None:
        ego = frame.ego.pose
        for a in frame.agents:
            if a.cls != "vehicle":
                continue
            top = max(self._top_speed.get(a.track_id, 0.0), a.speed_mps)
            self._top_speed[a.track_id] = top
            if top < 1.0:
                continue
            if math.hypot(a.pose.x_m - ego.x_m, a.pose.y_m - ego.y_m) < NEAR_M:
                self.traffic_delay_s += dt_s * (1.0 - a.speed_mps / top)

    @property
    def off_road_share(self) -> float:
        return self.off_road_m / self.distance_m if self.distance_m > 0 else 0.0

    @property
    def off_route_share(self) -> float:
        return self.off_route_m / self.distance_m if self.distance_m > 0 else 0.0


def _across(line: StopLine) -> np.ndarray:
    """A line's direction of travel when it has none stored: xy_m runs from the approach's
    left end to its right end, so travel is that direction turned a quarter to the left."""
    d = line.xy_m[1] - line.xy_m[0]
    n = np.array([-d[1], d[0]])
    return n / max(float(np.hypot(*n)), 1e-9)


def _in_zone(line: StopLine, xy: np.ndarray) -> bool:
    """The world point lies within STOP_ZONE_M before the line, across its width."""
    u = line.direction if line.direction is not None else _across(line)
    a, b = line.xy_m
    ahead = float((a - xy) @ u)  # distance still to go to the line
    d = b - a
    t = float((xy - a) @ d) / max(float(d @ d), 1e-9)
    return -0.5 <= ahead <= STOP_ZONE_M and -0.1 <= t <= 1.1
