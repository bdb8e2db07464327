"""Infractions of one route, judged geometrically every 0.1 s step from the ground truth the
sensors are made from (datagen.state.FrameState) and the scene layout (drive/layout.py).

Each event is counted once: a collision when the ego's box starts touching an agent's box (a
new contact with the same agent counts again only after they have been apart), a layout
collision when the box starts touching an obstacle footprint or the ego's centre mounts the
kerb, an off-road event when the ego's centre leaves the road. Per type:

- collision_vehicle / collision_pedestrian (people and bicycles): oriented-box overlap of the
  ego with every agent in FrameState.agents (SUMO does not see collisions of a vehicle moved by
  moveToXY, eclipse-sumo/sumo#6327, so SUMO's own collision list is not used).
- collision_layout: see above.
- red_light: the ego's front crosses a signalised stop line of the route while the signal
  governing its lane (datagen.world.EgoTruth's light, or FrameState.traffic_light; read within
  RED_LIGHT_NEAR_M of the line in the step before) is red.
- stop_sign: the ego's front crosses a stop-controlled stop line without having been slower
  than BLOCKED_SPEED_MPS while within STOP_ZONE_M before it (the leaderboard's RunningStopTest).
- off_road: the ego's centre leaves the drivable area; `off_road_share` is the share of the
  distance driven off it, `off_route_share` (the IS factor) the share outside the route's lanes.
- route_deviation (ends the route): the ego's centre farther than DEVIATION_M from the route.
- agent_blocked (ends the route): slower than BLOCKED_SPEED_MPS for BLOCKED_S.
- route_timeout (ends the route): more than score.route_timeout_s(length) simulated.

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
from drive.geometry import RouteGeometry
from drive.layout import Layout, boxes_overlap
from drive.score import (
    BLOCKED_S,
    BLOCKED_SPEED_MPS,
    COMPLETE_PCT,
    DEVIATION_M,
    route_timeout_s,
)
from schemas.dataset import box_corners

RED_LIGHT_NEAR_M = 6.0  # the light seen in the step before a crossing belongs to this line
STOP_ZONE_M = 5.0  # a stop counts within this distance before a stop sign's line
PROGRESS_BACK_M = 10.0  # projection window behind the progress made so far ...
PROGRESS_AHEAD_M = 40.0  # ... and ahead of it (a route may pass near itself)
TTC_HORIZON_S = 5.0
TTC_STEP_S = 0.1
TTC_RANGE_M = 40.0  # agents farther than this are not checked for TTC
NEAR_M = 50.0  # traffic delay counts vehicles within this distance of the ego
END_M = 5.0  # the route is complete once the ego's front is this close to its end (the expert
# stops 0.5 m before it; SUMO ends a route 5 m before its end at standstill)


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
    """

    geometry: RouteGeometry
    layout: Layout
    events: list[Event] = field(default_factory=list)
    ended: str | None = None
    progress_m: float = 0.0
    distance_m: float = 0.0
    off_road_m: float = 0.0
    off_route_m: float = 0.0
    min_ttc_s: float = math.inf
    traffic_delay_s: float = 0.0
    start_time_s: float | None = None
    _start_s: float = 0.0
    _last: FrameState | None = None
    _front_s: float | None = None
    _touching: set = field(default_factory=set)
    _layout_touching: bool = False
    _off_road: bool = False
    _slow_s: float = 0.0
    _zone_min_speed: dict = field(default_factory=dict)
    _top_speed: dict = field(default_factory=dict)
    _light: tuple = ("none", None)

    @property
    def route_completion_pct(self) -> float:
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

    def counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for e in self.events:
            out[e.kind] = out.get(e.kind, 0) + 1
        return out

    def step(self, frame: FrameState, dt_s: float = 0.1, light=None) -> None:
        """Judge one step. `light`: (state, stop-line distance m or None) of the signal of the
        ego's lane at any range (datagen.world.EgoTruth); default: the frame's, within 30 m."""
        if self.ended is not None:
            return
        ego = frame.ego
        p = ego.pose
        g = self.geometry
        if self._last is None:  # the first state: where the route starts for this ego
            s, _ = g.project([[p.x_m, p.y_m]], -1.0, PROGRESS_AHEAD_M)
            self._start_s = self.progress_m = s
            self.start_time_s = frame.time_s
        last = self._last
        moved = (
            0.0
            if last is None
            else math.hypot(p.x_m - last.ego.pose.x_m, p.y_m - last.ego.pose.y_m)
        )
        self.distance_m += moved
        # progress along the route, searched near the progress so far
        s, lateral = g.project(
            [[p.x_m, p.y_m]], self.progress_m - PROGRESS_BACK_M, self.progress_m + PROGRESS_AHEAD_M
        )
        self.progress_m = max(self.progress_m, s)
        front = np.array([p.x_m, p.y_m]) + 0.5 * ego.length_m * np.array(
            [math.cos(p.yaw_rad), math.sin(p.yaw_rad)]
        )
        front_s, front_lat = g.project(
            [front], self.progress_m - PROGRESS_BACK_M, self.progress_m + PROGRESS_AHEAD_M
        )
        self._collisions(frame)
        self._layout(frame, moved)
        if self._front_s is not None and front_lat < DEVIATION_M:
            self._stop_lines(frame, self._front_s, front_s)
        self._front_s = front_s
        self._light = light or (frame.traffic_light, frame.light_distance_m)
        if front_lat < DEVIATION_M and front_s >= g.length_m - END_M:
            self.progress_m = g.length_m
        # beyond the leaderboard
        self.min_ttc_s = min(self.min_ttc_s, time_to_collision(ego, list(frame.agents)))
        self._delay(frame, dt_s)
        # route-ending conditions
        if self.route_completion_pct >= COMPLETE_PCT:
            self.ended = "route_complete"
        elif lateral > DEVIATION_M:  # InRouteTest
            self._add("route_deviation", frame, f"{lateral:.1f} m from the route")
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

    def _collisions(self, frame: FrameState) -> None:
        ego = frame.ego
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
                if a.track_id not in self._touching:
                    kind = "collision_vehicle" if a.cls == "vehicle" else "collision_pedestrian"
                    self._add(kind, frame, a.track_id)
        self._touching = touching

    def _layout(self, frame: FrameState, moved_m: float) -> None:
        ego = frame.ego
        p = ego.pose
        corners = box_corners(p.x_m, p.y_m, p.yaw_rad, ego.length_m, ego.width_m)
        on_kerb = self.layout.on_kerb(p.x_m, p.y_m)
        touching = on_kerb or self.layout.hits_obstacle(corners)
        if touching and not self._layout_touching:
            self._add("collision_layout", frame, "kerb" if on_kerb else "obstacle")
        self._layout_touching = touching
        off = not self.layout.on_road(p.x_m, p.y_m, on_kerb)
        if off and not self._off_road:
            self._add("off_road", frame)
        self._off_road = off
        if off:
            self.off_road_m += moved_m
        if off or not self.geometry.in_lanes(p.x_m, p.y_m):
            self.off_route_m += moved_m

    def _stop_lines(self, frame: FrameState, s0: float, s1: float) -> None:
        speed = frame.ego.speed_mps
        for k, line in enumerate(self.geometry.stop_lines):
            if line.kind == "stop" and line.s_m - STOP_ZONE_M <= s1 <= line.s_m:
                self._zone_min_speed[k] = min(self._zone_min_speed.get(k, math.inf), speed)
            if not (s0 < line.s_m <= s1):
                continue
            if line.kind == "light":
                state, dist = self._light  # still the step before's: the signal before crossing
                red = state == "red" and dist is not None and dist <= RED_LIGHT_NEAR_M
                if red:
                    self._add("red_light", frame, line.junction)
            else:
                if self._zone_min_speed.get(k, math.inf) > BLOCKED_SPEED_MPS:
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
