"""The step loop: libsumo stepped in-process, background traffic and pedestrians around an
expert-driven ego car.

    with World(WorldConfig(net_path=town_net_path("grid_small"), seed=1, weather="sunny",
                           behaviour="normal")) as world:
        for frame in record(world, n_frames=100):   # FrameState at 2 Hz
            ...

How the ego is driven. Each 0.1 s step `World` reads a sumo.Snapshot (the ego, everything within
AGENT_RADIUS_M, its next links and signals), builds the route ahead (route.py) and what is on it
(perception.py) into an `expert.ExpertInput` and sets the expert's target speed. The ego keeps
SUMO's default speed mode 31, so SUMO remains the safety net under the expert: it still caps the
commanded speed by its safe speed behind the leader (bit 0), by the vType's acceleration and
deceleration (bits 1, 2), by right of way at junctions, pedestrians on crossings included
(bit 3), and brakes hard rather than pass a red light (bit 4). The ego vType's decel, the cap on
commanded braking, is EGO_DECEL_SLACK x the comfortable deceleration the expert plans with. Only
two things brake harder (up to emergencyDecel), both only to avoid a collision (counted in
`stats["hard_brakes"]`): SUMO's safety checks, and the expert's emergency brake
(`Decision.brake_mps2`, for a car cutting in close ahead or a person stepping out), applied as
a speed for the step with bit 2 off (speed mode 27). When SUMO holds the ego below the expert's
target, the step's reason names what it yields to (`junction`, `stop_sign`, `pedestrian`,
`vehicle`). Lane choice and lane changes stay with SUMO's lane-change model.

On top of SUMO's checks the expert yields to people on, or about to step onto, a crossing its
path crosses (perception.crossing_obstacles: their next edge is the crossing; once inside a
junction only to people already on one, since standing there its body can cover the crossing
behind it), and keeps
junctions clear (expert.junction_rule): it does not enter one whose exit is blocked, nor begin a
turn that would give way at a waiting point inside it while a foe vehicle is near (waiting
there, the car's front can reach into the foe's lane).

What the dataset keeps of an episode that still ends in an ego collision: `record` holds every
state back COLLISION_DROP_S (5 s) and drops the held states when the collision comes, so no
frame shows the expert driving into it (World.dropped_frames, stats["dropped_frames"]).

The ego drives a random route that is extended with a new random destination before it ends
(`WorldConfig.reroute`); traffic lives in a bubble around it (traffic.py).

Who drives the ego: one seam. `WorldConfig.ego_driver="expert"` (the default, above) or
"external": a controller (the closed-loop evaluator) computes the ego's next pose and speed with
its own kinematic model and hands them over every 0.1 s step as an `EgoCommand`; the world puts
the ego there (moveToXY with keepRoute=2: anywhere, off its lane or the road too), sets its speed
(speed mode 0, so other drivers see the speed it really has), keeps its SUMO route on the planned
route so other vehicles give way to it at junctions (sumo#6140), and moves the traffic bubble
with it. `state()` gives the FrameState the sensors need; `truth()` gives what infractions need
beyond the agents' boxes in `state().agents`: lane, signal of the ego's lane and its distance
(any range), entering a junction on red, route progress, SUMO's own ego collisions (incomplete
for a placed vehicle, sumo#6327: check boxes too). Nothing ends an externally driven episode but
SUMO removing the ego; collisions and red lights are the caller's to score.

    cfg = WorldConfig(net, seed=3, weather="rainy", behaviour="cautious",
                      ego_route=route_edges, reroute=False, ego_driver="external")
    with World(cfg) as world:
        ego = world.state().ego                        # the start: box centre, yaw, speed 0
        for k in range(n_steps):
            pose, v = controller.next(ego, world.truth())   # the caller's kinematics, 0.1 s
            world.step(EgoCommand(pose, v))
            frame = world.state()                      # sensors at 2 Hz: every 5th step
            ego = frame.ego

Poses are converted once, where libsumo is read (sumo.py): FrameState poses are box centres
with yaw counter-clockwise from east in radians.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from datagen.errors import UserError
from datagen.state import AgentState, FrameState, Pose
from datagen.world import expert, perception, route
from datagen.world.behaviour import EGO_DECEL_SLACK, PROFILES, Profile
from datagen.world.config import EGO_DRIVERS, WorldConfig
from datagen.world.fleet import EGO_DIMS_M, EGO_ID, dims
from datagen.world.route import PATH_LOOKAHEAD_M, SIGNAL_RANGE_M
from datagen.world.rules import RuleBook, stop_foes
from datagen.world.sumo import Collision, Snapshot, StepEvents, Sumo, box_centre
from datagen.world.traffic import Traffic
from schemas import FRAME_PERIOD_S, WAYPOINT_TIMES_S, WEATHERS

AGENT_RADIUS_M = 100.0  # agents within this distance of the ego are in FrameState.agents
BLOCKED_S = 80.0  # ego standing this long (not at a red light) ends the episode ("blocked")
# The expert reads the green left within this of a signalled junction, plus its comfortable
# stopping distance (read at 30 m only, a car coming at 17 m/s was past stopping: arterial,
# build seed 0, episode 20)
GREEN_CHECK_M = 30.0
STOP_FOE_CHECK_M = 10.0  # within this of a stop line the expert reads its junction's foes
# record() drops the frames of the last 5 s before an ego collision: more than the 2 s of future
# waypoints a frame is labelled with plus ~3 s of approach, so no frame shows driving into it.
COLLISION_DROP_S = 5.0
SLOW_LANE_CHANGE_MPS = 1.0  # slower than this the expert ego changes lanes only for its route
LANE_CHANGE_S = 2.0  # the expert's plan changes lanes as SUMO does for it (sumo.py)

_log = logging.getLogger(__name__)
_open_world: World | None = None  # libsumo runs one simulation per process


@dataclass(frozen=True)
class EgoCommand:
    """Where an external controller puts the ego at the end of the next step (world frame).

    Attributes:
        pose: box centre (x_m, y_m), metres, and yaw_rad, counter-clockwise from east.
        speed_mps: speed along the yaw, m/s; SUMO's other drivers react to it.
    """

    pose: Pose
    speed_mps: float


@dataclass(frozen=True)
class EgoTruth:
    """Ground truth about the ego after a step, for scoring a drive (world frame, metres).

    Attributes:
        time_s: simulation time, s.
        lane_id: the lane SUMO maps the ego to ("" off the road network; ":..." in a junction).
        road_id: its edge ("" off the network).
        route_index: index into `route` of the ego's edge (the last one on the route while it
            is inside a junction or off the route).
        route: the ego's planned route (edge ids).
        remaining_route_m: distance from the ego's front to the end of the route along it;
            None while the ego is off the network or off the route.
        light: state of the next traffic light on the route ("red", "yellow", "green",
            "none") at any distance; light_distance_m: its stop line, None without one.
        tls_id, tls_link_index: that light and its link governing the ego's lane ("", -1).
        entered_on_red: this step the ego entered a junction through a link that was red.
        stop_distance_m: the next stop-controlled entry's line, None without one.
        collisions: SUMO's collisions involving the ego this step ((collider, victim, kind));
            SUMO may miss some of a placed ego's (sumo#6327): check boxes as well.
    """

    time_s: float
    lane_id: str
    road_id: str
    route_index: int
    route: tuple[str, ...]
    remaining_route_m: float | None
    light: str
    light_distance_m: float | None
    tls_id: str
    tls_link_index: int
    entered_on_red: bool
    stop_distance_m: float | None
    collisions: tuple[tuple[str, str, str], ...]


@dataclass
class _Stats:
    steps: int = 0
    sim_s: float = 0.0
    wall_s: float = 0.0
    collisions: int = 0
    other_collisions: int = 0
    teleports: int = 0
    hard_brakes: int = 0
    reroutes: int = 0
    distance_m: float = 0.0
    speed_sum: float = 0.0
    gaps_s: list = field(default_factory=list)
    reasons: dict = field(default_factory=dict)


class World:
    """A SUMO episode with the expert ego (context manager; see module docstring).

    Attributes:
        config: the WorldConfig.
        profile: behaviour.PROFILES[config.behaviour].
        ended: None while running, else why it ended: "route_end", "teleported", "blocked",
            "collision".
        end_detail: a sentence saying what ended it ("" while running).
        dropped_frames: states `record` dropped before an ego collision (0 otherwise).
    """

    def __init__(self, config: WorldConfig):
        global _open_world
        if _open_world is not None:
            raise RuntimeError("libsumo runs one simulation per process: close the other World")
        if config.weather not in WEATHERS:
            raise UserError(f"unknown weather {config.weather!r}; expected one of {WEATHERS}")
        if config.behaviour not in PROFILES:
            raise UserError(
                f"unknown behaviour {config.behaviour!r}; expected one of {tuple(PROFILES)}"
            )
        if config.ego_driver not in EGO_DRIVERS:
            raise UserError(
                f"unknown ego driver {config.ego_driver!r}; expected one of {EGO_DRIVERS}"
            )
        if config.target_point not in route.TARGET_FORMS:
            raise UserError(
                f"unknown target point form {config.target_point!r}; "
                f"expected one of {route.TARGET_FORMS}"
            )
        from datagen.world.towns import check_network

        check_network(config.net_path)  # a clear UserError before SUMO sees a bad file
        self.config = config
        self.profile: Profile = PROFILES[config.behaviour]
        self.ended: str | None = None
        self.end_detail: str = ""
        self.dropped_frames = 0
        self._rng = np.random.default_rng(config.seed)
        self._stats = _Stats()
        self._sumo: Sumo | None = None
        self._kerb: dict[str, bool] = {}
        self._colliding: set[tuple[str, str]] = set()
        self._route_end_m: float | None = None
        self._reason = "none"
        self._target = 0.0
        self._standing_s = 0.0
        self._sticky: route.Sticky | None = None  # the junction a turn command was given for
        self._plan: tuple[route.PlanPoint, ...] = ()  # the sparse route plan (target_point)
        self._plan_k = 0  # index of the current target in it
        self._plan_i = 0  # externally driven: index in self._route of the ego's edge
        self._ego_collisions: tuple[tuple[str, str, str], ...] = ()
        self._on_plan = True  # SUMO's route of the ego is the planned one (from the offset)
        self._last_lane = ""  # the last lane outside a junction the expert's plan saw
        try:
            _open_world = self
            self._sumo = Sumo(config.net_path, self.profile, config.step_s, config.seed)
            self._net = self._sumo.net
            self._rules = RuleBook(self._net, config.step_s, self._is_kerb)
            roads = self._sumo.roads(config.net_path)
            self._traffic = Traffic(self._sumo, roads, self._rng, config.net_path)
            self._populate()
            self._insert_ego()
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ setup

    def _populate(self) -> None:
        """Choose the ego's route, fill the bubble around its start, run the warm-up."""
        if self.config.ego_route:
            self._ego_route = list(self.config.ego_route)
        else:
            self._ego_route = self._traffic.pick_ego_route()
        start = self._traffic.edge_mid(self._ego_route[0])
        self._traffic.populate(
            self.profile, start, self.config.n_vehicles, self.config.n_pedestrians
        )
        for _ in range(int(round(self.config.warmup_s / self.config.step_s))):
            self._sumo.step()

    def _insert_ego(self) -> None:
        fixed = bool(self.config.ego_route)
        for attempt in range(1 if fixed else 5):
            if attempt:
                self._ego_route = self._traffic.pick_ego_route()
            if self._sumo.insert_ego(tuple(self._ego_route), attempt, at_start=fixed):
                break
        else:
            raise RuntimeError("could not insert the ego vehicle")
        self._sumo.subscribe_ego(AGENT_RADIUS_M)
        self._sumo.step()
        self._set_route(self._sumo.ego_route())
        if self.config.ego_driver == "external":
            self._sumo.take_over_ego()
        self._snap = self._sumo.snapshot()
        self._sense()

    # ------------------------------------------------------------------ per step

    def _is_kerb(self, lane_id: str) -> bool:
        k = self._kerb.get(lane_id)
        if k is None:
            plain = lane_id != "" and not lane_id.startswith(":")
            k = perception.is_kerb(lane_id, self._net.allowed(lane_id) if plain else None)
            self._kerb[lane_id] = k
        return k

    def _sense(self) -> None:
        """Path ahead and signals from the latest snapshot."""
        ego = self._snap.ego
        self._path = route.path_ahead(
            self._net, ego.lane_id, ego.lane_pos_m, self._snap.links, ego.front_xy_m, ego.yaw_rad
        )
        self._signals = route.signals(
            self._snap.next_signals, self._snap.links, self._path.link_dist
        )

    def _expert_input(self) -> expert.ExpertInput:
        ego = self._snap.ego
        limit, limits_ahead = route.speed_limits(self._net, ego.lane_id, self._path)
        curv = route.curvature_ahead(self._path, expert.MIN_CURVATURE_1PM)
        sig = self._signals
        # the end of the route binds only when it will not be extended (any more)
        remaining = self._remaining_route()
        route_end = (
            remaining
            if remaining < (PATH_LOOKAHEAD_M if not self.config.reroute else 100.0)
            else None
        )
        self._route_end_m = route_end
        leader = self._sumo.leader(self._snap, PATH_LOOKAHEAD_M)
        obstacles = perception.obstacles(
            self._snap.agents, self._is_kerb, ego.lane_id.startswith(":"), self._path, leader
        )
        obstacles += perception.crossing_obstacles(
            self._snap.agents,
            self._net,
            self._is_kerb,
            self._path,
            ego.speed_mps,
            ego.lane_id.startswith(":"),
        )
        junction = route.junction_ahead(ego.lane_id, self._path, self._snap.links)
        waits_inside, foe_eta = False, None
        if junction is not None and route.waits_inside(self._net, self._snap.links[0]):
            waits_inside = True
            foe_eta = perception.foe_eta_s(
                self._snap.agents,
                self._net,
                route.junction_of(self._snap.links[0].via_lane_id),
                ego.road_id,
                self._net.stop_controlled,
            )
        stop_foe = None
        stop_d = sig.stop_distance_m
        if stop_d is not None and sig.stop_junction and stop_d < STOP_FOE_CHECK_M:
            stop_foe = perception.foe_eta_s(
                self._snap.agents,
                self._net,
                sig.stop_junction,
                ego.road_id,
                foes=stop_foes(self._net, self._snap.links),
            )
        green_left = None
        b = self.profile.ego_comfort_decel_mps2  # from where it can still stop comfortably
        near = junction is not None and junction[0] < GREEN_CHECK_M + ego.speed_mps**2 / (2 * b)
        if near and sig.light == "green" and abs(sig.light_distance_m - junction[0]) < 3.0:
            green_left = self._sumo.switch_in_s(self._snap.next_signals[0].tls_id)
        return expert.ExpertInput(
            speed_mps=ego.speed_mps,
            speed_limit_mps=float(limit),
            limits_ahead=limits_ahead,
            curvature_ahead=curv,
            obstacles=tuple(obstacles),
            light=sig.light,
            light_distance_m=sig.light_distance_m,
            stop_distance_m=sig.stop_distance_m,
            stop_done=sig.stop_distance_m is not None and self._rules.stop_done_lane == ego.lane_id,
            route_end_m=route_end,
            junction_entry_m=junction[0] if junction else None,
            junction_exit_m=junction[1] if junction else None,
            waits_inside=waits_inside,
            foe_eta_s=foe_eta,
            green_left_s=green_left,
            stop_foe_eta_s=stop_foe,
        )

    def _set_route(self, edges: list[str] | tuple[str, ...]) -> None:
        """Cache the ego's route and the length of each of its suffixes."""
        self._route = tuple(edges)
        self._route_suffix = route.route_suffix_m(self._net, self._route)
        if self.config.target_point == "sparse":  # an extension keeps the plan's prefix
            self._plan = route.sparse_plan(self._net, self._route)

    def _remaining_route(self) -> float:
        """Distance from the ego's front to the end of its route, m."""
        ego = self._snap.ego
        return route.remaining_route_m(
            self._net,
            self._route_suffix,
            ego.lane_id,
            ego.lane_pos_m,
            self._route_index(),
        )

    def _route_index(self) -> int:
        """Index in self._route of the ego's edge. The expert's SUMO route is self._route (a
        reroute keeps the passed edges); a placed ego's SUMO route may not be."""
        return self._snap.ego.route_index if self.config.ego_driver == "expert" else self._plan_i

    def _maybe_reroute(self) -> None:
        ego = self._snap.ego
        if ego.lane_id.startswith(":") or self._remaining_route() > 250.0:
            return
        edges = list(self._route)
        new = self._traffic.extension(edges[-1])
        if new:
            idx = self._route_index()
            self._sumo.set_ego_route(edges[idx:] + list(new[1:]))
            self._set_route(edges + list(new[1:]))  # the route index stays valid
            self._stats.reroutes += 1

    def _step(self) -> None:
        sumo = self._sumo
        st = self._stats
        p = self.profile
        dt = self.config.step_s
        before = self._snap
        v0 = before.ego.speed_mps
        inp = self._expert_input()
        dec = expert.decide(inp, p, EGO_DECEL_SLACK * p.ego_comfort_decel_mps2)
        self._target, reason = dec.target_speed_mps, dec.reason
        # no lane change but the route's while (nearly) standing (sumo.set_ego_lane_changes)
        sumo.set_ego_lane_changes(strategic_only=v0 < SLOW_LANE_CHANGE_MPS)
        if dec.brake_mps2 > 0.0:  # an emergency: brake harder than the vType's decel
            v_cmd = max(dec.target_speed_mps, v0 - dec.brake_mps2 * dt)
            sumo.set_ego_speed(v_cmd, regard_decel=False)
        else:
            sumo.set_ego_speed(dec.target_speed_mps)
        lane0 = before.ego.lane_id
        first_state = before.links[0].state if before.links else ""
        sumo.step()
        st.steps += 1
        st.sim_s += dt
        # --- what happened in the step
        events = sumo.events()
        for c in self._new_collisions(events):
            if self.config.end_on_collision:
                self._end("collision", f"{c.collider} hit {c.victim} ({c.kind}) on {c.lane_id}")
        st.teleports += len(events.teleported)
        if EGO_ID in events.teleported:
            self._end("teleported", "SUMO teleported the jammed ego")
            return
        if EGO_ID in events.arrived:
            self._end("route_end", "the ego reached the end of its route")
            return
        # the new snapshot; path and signals are still the previous step's until _sense()
        self._snap = snap = sumo.snapshot()
        v1 = snap.ego.speed_mps
        lane1 = snap.ego.lane_id
        if self._route_end_m is not None and self._route_end_m < 5.0 and v1 < expert.STOPPED_MPS:
            self._end("route_end", "the ego stopped at the end of its route")
        self._rules.note_red_light(lane0, lane1, first_state)
        self._rules.note_stop(lane0, snap, self._signals)
        stop_d = self._signals.stop_distance_m
        # did SUMO hold the ego below the expert's command?
        v_exp = min(self._target, v0 + p.ego_accel_mps2 * dt)
        v_exp = max(v_exp, v0 - EGO_DECEL_SLACK * p.ego_comfort_decel_mps2 * dt)
        if v1 < v_exp - 0.1 and reason not in ("red_light", "stop_sign", "route_end"):
            reason = perception.attribute_hold(
                stop_d, self._path, snap.agents, lane1.startswith(":"), self._path.link_dist
            )
        if (v0 - v1) / dt > EGO_DECEL_SLACK * p.ego_comfort_decel_mps2 + 0.3:
            st.hard_brakes += 1  # harder than any command: SUMO's safety braking
        self._reason = reason
        st.reasons[reason] = st.reasons.get(reason, 0) + 1
        st.distance_m += v1 * dt
        st.speed_sum += v1
        if dec.reason == "vehicle" and v1 > 2.0:  # steady following: the time gap kept
            cars = [o for o in inp.obstacles if o.kind == "vehicle"]
            bind = min(cars, key=lambda o: expert.follow_speed(o.distance_m, o.speed_mps, p))
            if bind.track_id.startswith("lead:") and abs(bind.speed_mps - v1) < 1.0:
                st.gaps_s.append(bind.distance_m / v1)
        self._sense()
        # standing still too long (not at a red light) ends the episode
        if v1 < expert.STOPPED_MPS and self._signals.light != "red":
            self._standing_s += dt
            if self._standing_s >= BLOCKED_S:
                self._end("blocked", f"ego stood {BLOCKED_S:.0f} s on {lane1}")
        else:
            self._standing_s = 0.0
        if st.steps % 10 == 0:
            if self.config.reroute:
                self._maybe_reroute()
            self._traffic.manage(snap.ego.front_xy_m, st.steps % 50 == 0)

    def _new_collisions(self, events: StepEvents) -> list[Collision]:
        """Count the step's collisions (each pair once: SUMO reports an overlap every step it
        lasts) and return the ego's new ones."""
        st = self._stats
        mine = []
        for c in events.collisions:
            pair = (c.collider, c.victim)
            if pair in self._colliding:
                continue
            self._colliding.add(pair)
            if EGO_ID in pair:
                st.collisions += 1
                mine.append(c)
            else:
                st.other_collisions += 1
        self._ego_collisions = tuple((c.collider, c.victim, c.kind) for c in mine)
        return mine

    def _step_external(self, command: EgoCommand) -> None:
        """One step with the ego placed by an external controller (see the module docstring)."""
        sumo = self._sumo
        st = self._stats
        dt = self.config.step_s
        before = self._snap
        lane0 = before.ego.lane_id
        first_state = before.links[0].state if before.links else ""
        sumo.place_ego(command.pose, command.speed_mps)
        sumo.step()
        st.steps += 1
        st.sim_s += dt
        events = sumo.events()
        self._new_collisions(events)  # scored by the caller; the drive goes on
        st.teleports += len(events.teleported)
        if EGO_ID in events.teleported or EGO_ID in events.arrived:
            self._end("route_end", "SUMO took the placed ego out of the simulation")
            return
        snap = sumo.snapshot()
        if self._keep_route(snap):
            snap = sumo.snapshot()  # links and signals along the restored route
        self._snap = snap
        lane1 = snap.ego.lane_id
        self._rules.note_red_light(lane0, lane1, first_state)
        if lane1:
            self._rules.note_stop(lane0, snap, self._signals)
        self._reason = "none"
        st.distance_m += snap.ego.speed_mps * dt
        st.speed_sum += snap.ego.speed_mps
        if lane1:  # off the network: path and signals stay the last ones on it
            self._sense()
        else:
            self._on_plan = False
        if st.steps % 10 == 0:
            if self.config.reroute and self._on_plan and lane1:
                self._maybe_reroute()
            self._traffic.manage(snap.ego.front_xy_m, st.steps % 50 == 0)

    def _keep_route(self, snap: Snapshot) -> bool:
        """Keep SUMO's route of a placed ego on the planned route, so that other drivers
        respect it at junctions (sumo#6140): moveToXY(keepRoute=2) replaces the route by the
        edge it maps the ego to when that edge is off the route (inside a junction: by the
        passage of the nearest internal lane). On a planned edge again, the rest of the plan is
        set back. True if the route was set."""
        road = snap.ego.road_id
        if not road or road.startswith(":"):
            return False  # off the network or inside a junction: as it was
        try:
            i = self._route.index(road, self._plan_i)
        except ValueError:
            self._on_plan = False  # off the route (e.g. the opposite lane): nothing to restore
            return False
        self._plan_i, self._on_plan = i, True
        if self._sumo.ego_route()[snap.ego.route_index :] == self._route[i:]:
            return False
        try:
            self._sumo.set_ego_route(self._route[i:])
        except self._sumo.TraCIException:
            # SUMO's own current edge may differ from the snapshot's (seen with a placed ego
            # on the opposite direction's edge): keep its route this step, try again next one
            return False
        return True

    def _end(self, why: str, detail: str) -> None:
        if self.ended is None:
            self.ended = why
            self.end_detail = detail
            log = _log.info if why == "route_end" else _log.warning
            log(
                "episode %s (seed %d) ended at %.1f s: %s (%s)",
                Path(self.config.net_path).name,
                self.config.seed,
                self._stats.sim_s,
                why,
                detail,
            )

    # ------------------------------------------------------------------ public

    def step(self, command: EgoCommand | None = None) -> None:
        """One SUMO step (config.step_s): the expert drives (command None, ego_driver
        "expert") or the ego is placed at `command` (ego_driver "external")."""
        if (command is None) != (self.config.ego_driver == "expert"):
            raise RuntimeError(
                f"ego_driver {self.config.ego_driver!r}: "
                + ("step() takes no command" if command is not None else "step() needs a command")
            )
        if self.ended is not None:
            return
        t0 = time.perf_counter()
        if command is None:
            self._step()
        else:
            self._step_external(command)
        self._stats.wall_s += time.perf_counter() - t0

    def advance(self, dt_s: float) -> None:
        """Run the simulation `dt_s` seconds (whole steps) with the expert in control."""
        if self.config.ego_driver != "expert":
            raise RuntimeError("an externally driven ego moves only by step(EgoCommand)")
        if self.ended is not None:
            return
        t0 = time.perf_counter()
        for _ in range(max(1, int(round(dt_s / self.config.step_s)))):
            self._step()
            if self.ended is not None:
                break
        self._stats.wall_s += time.perf_counter() - t0

    def expert_plan(
        self, times_s: tuple[float, ...] = WAYPOINT_TIMES_S
    ) -> tuple[np.ndarray, expert.Decision] | None:
        """The privileged expert's plan from the ego's state now, whoever drives it: where its
        box centre would be at each of `times_s` ((len(times_s), 2), world frame, m) and its
        decision now; None off the network. The plan is `expert.rollout` along the route's
        lanes from the lane point nearest the ego's front (so an ego beside its lane is led
        back to the lane's centre), in a world that keeps its velocity. With the expert
        driving, its first step is the command `step()` gives next."""
        if not self._snap.ego.lane_id:
            return None
        p = self.profile
        dists, dec = expert.rollout(
            self._expert_input(), p, times_s, EGO_DECEL_SLACK * p.ego_comfort_decel_mps2
        )
        path = self._plan_path()
        yaw = self._snap.ego.yaw_rad
        return route.centres_along(path, dists, EGO_DIMS_M[0], yaw), dec

    def _plan_path(self) -> route.Path:
        """The path the expert's plan follows, from where the ego's front is: along the route's
        lanes (inside a junction: the route's own passage, whatever internal lane SUMO maps a
        placed ego to where passages overlap), along the next lane over where the ego's lane
        does not lead along its route (what SUMO's strategic lane changing reads,
        getBestLanes), starting beside that lane's centre line as far as the ego is and
        merging into it within LANE_CHANGE_S of driving (SUMO's lane changes in the data take
        as long: sumo.py --lanechange.duration)."""
        ego = self._snap.ego
        front = np.array([ego.front_xy_m])
        ahead = self._route[self._route_index() + 1 :]
        target = None
        if ego.lane_id.startswith(":"):
            passage = self._passage(ahead)
            if passage and ego.lane_id not in passage:
                target = min(passage, key=lambda lid: self._lane_gap(lid, front)[1])
        else:
            self._last_lane = ego.lane_id
            offset = self._sumo.ego_lane_offset()
            edge, idx = ego.lane_id.rsplit("_", 1)
            k = int(idx) + (1 if offset > 0 else -1)
            if offset != 0 and 0 <= k < self._net.lane_count(edge):
                target = f"{edge}_{k}"
        path = self._path
        if target is not None:
            pos = self._lane_gap(target, front)[0]
            if target.startswith(":"):  # path_ahead walks out of the junction by itself
                exit_lane = route.exit_chain(self._net, target)[-1:]
                links = (
                    route.route_links(self._net, exit_lane[0], ahead[1:], 4) if exit_lane else ()
                )
            else:
                links = route.route_links(self._net, target, ahead, 4)
            path = route.path_ahead(self._net, target, pos, links, ego.front_xy_m, ego.yaw_rad)
        beside = float((front[0] - path.pts[0]) @ path.segments.normal)  # m left of its start
        return route.shifted(path, beside, LANE_CHANGE_S * max(ego.speed_mps, 3.0))

    def _passage(self, ahead: tuple[str, ...]) -> list[str]:
        """The internal lanes of the junction passage from the last lane the ego was on before
        it to the route's next edge ([] if none)."""
        if not ahead or not self._last_lane:
            return []
        links = route.route_links(self._net, self._last_lane, ahead, 1)
        if not links or not links[0].via_lane_id:
            return []
        return route.via_chain(self._net, links[0].via_lane_id)

    def _lane_gap(self, lane_id: str, xy: np.ndarray) -> tuple[float, float]:
        """(position along lane `lane_id` in lane-length units, distance from it, m) of the
        point (1, 2) `xy`."""
        lane = self._net.lane(lane_id)
        s, d, _ = route.project(xy, lane.pts, lane.cum_m, lane.segments)
        return float(s[0]) * lane.length_m / max(float(lane.cum_m[-1]), 1e-9), float(d[0])

    @property
    def time_s(self) -> float:
        return self._sumo.time_s()

    def state(self) -> FrameState:
        """Ground truth now (world frame, box centres): see datagen/state.py."""
        snap: Snapshot = self._snap
        ego_r = snap.ego
        el, ew, eh = EGO_DIMS_M
        ego_pose = box_centre(ego_r.front_xy_m, ego_r.yaw_rad, el)
        ego = AgentState(EGO_ID, "vehicle", ego_pose, el, ew, eh, ego_r.speed_mps)
        agents = []
        ex, ey = ego_r.front_xy_m
        for a in sorted(snap.agents, key=lambda a: a.agent_id):
            x, y = a.front_xy_m
            if math.hypot(x - ex, y - ey) > AGENT_RADIUS_M:
                continue
            length, width, height, cls = dims(a.type_id)
            pose = box_centre(a.front_xy_m, a.yaw_rad, length)
            agents.append(
                AgentState(a.agent_id, cls, pose, length, width, height, float(a.speed_mps))
            )
        command, target, self._sticky = route.command_and_target(
            self._net, ego_r.lane_id, self._path, snap.links, self._sticky
        )
        if self._plan:  # the sparse form (WorldConfig.target_point)
            i = self._route_index()
            on_edge = i < len(self._route) and ego_r.road_id == self._route[i]
            self._plan_k = route.next_plan_point(
                self._plan, self._plan_k, i, ego_r.lane_pos_m if on_edge else None, ego_r.front_xy_m
            )
            p = self._plan[self._plan_k]
            target = (p.x_m, p.y_m)
        sig = self._signals
        light, light_d = sig.light, sig.light_distance_m
        if light_d is None or light_d > SIGNAL_RANGE_M:
            light, light_d = "none", None
        stop_d = sig.stop_distance_m
        stop_d = stop_d if stop_d is not None and stop_d <= SIGNAL_RANGE_M else None
        return FrameState(
            time_s=self.time_s,
            ego=ego,
            agents=tuple(agents),
            command=command,
            target_point_xy_m=target,
            traffic_light=light,
            light_distance_m=light_d,
            stop_sign=stop_d is not None,
            stop_distance_m=stop_d,
            expert_reason=self._reason,
            signals=self._sumo.signal_states(),
        )

    def truth(self) -> EgoTruth:
        """Ground truth about the ego after the last step, for scoring (see EgoTruth)."""
        snap = self._snap
        ego = snap.ego
        on_net = ego.lane_id != ""
        sig = self._signals
        nxt = snap.next_signals[0] if snap.next_signals else None
        return EgoTruth(
            time_s=self.time_s,
            lane_id=ego.lane_id,
            road_id=ego.road_id,
            route_index=self._route_index(),
            route=self._route,
            remaining_route_m=self._remaining_route() if on_net and self._on_plan else None,
            light=sig.light if on_net else "none",
            light_distance_m=sig.light_distance_m if on_net else None,
            tls_id=nxt.tls_id if nxt else "",
            tls_link_index=nxt.link_index if nxt else -1,
            entered_on_red=self._rules.entered_on_red,
            stop_distance_m=sig.stop_distance_m if on_net else None,
            collisions=self._ego_collisions,
        )

    @property
    def stats(self) -> dict:
        """Episode statistics: collisions (of the ego; other_collisions between other road
        users, each pair once), red_light_violations (ego entered a junction on red),
        teleports (all vehicles), hard_brakes (steps braking harder than any command: SUMO's
        safety braking), mean_speed_mps, mean_time_gap_s and median_time_gap_s (bumper gap /
        speed while steadily following a lead, None if never), sim/wall seconds, steps per
        expert reason, and how the episode ended."""
        st = self._stats
        return {
            "steps": st.steps,
            "sim_s": round(st.sim_s, 3),
            "wall_s": round(st.wall_s, 3),
            "collisions": st.collisions,
            "other_collisions": st.other_collisions,
            "red_light_violations": self._rules.red_light_violations,
            "teleports": st.teleports,
            "hard_brakes": st.hard_brakes,
            "reroutes": st.reroutes,
            "distance_m": round(st.distance_m, 1),
            "mean_speed_mps": st.speed_sum / st.steps if st.steps else 0.0,
            "mean_time_gap_s": float(np.mean(st.gaps_s)) if st.gaps_s else None,
            "median_time_gap_s": float(np.median(st.gaps_s)) if st.gaps_s else None,
            "following_s": round(len(st.gaps_s) * self.config.step_s, 1),
            "n_vehicles": self._traffic.n_veh,
            "n_pedestrians": self._traffic.n_ped,
            "reasons": dict(sorted(st.reasons.items())),
            "ended": self.ended,
            "end_detail": self.end_detail,
            "dropped_frames": self.dropped_frames,
        }

    def close(self) -> None:
        """Stop SUMO (idempotent; safe after a failed start)."""
        global _open_world
        if self._sumo is not None:
            self._sumo.close()
        if _open_world is self:
            _open_world = None

    def __enter__(self) -> World:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        sumo = getattr(self, "_sumo", None)
        if sumo is not None and sumo.started:
            self.close()


def record(
    world: World,
    n_frames: int,
    period_s: float = FRAME_PERIOD_S,
    drop_before_collision_s: float = COLLISION_DROP_S,
) -> Iterator[FrameState]:
    """Yield `world.state()` now and every `period_s` (2 Hz by default) until `n_frames` states
    have been yielded or the world ends (then `world.ended` says why).

    Each state is held back until `drop_before_collision_s` more seconds have been simulated.
    When the episode ends in an ego collision, the states still held back -- the last
    `drop_before_collision_s` before it -- are dropped, so no recorded frame demonstrates the
    expert driving into the crash; any other end yields them. The states yielded are the same
    either way (the world only runs a little ahead of the consumer).
    """
    hold = max(0, int(round(drop_before_collision_s / period_s)))
    held: deque[FrameState] = deque()
    yielded = 0
    k = 0
    while yielded < n_frames:
        if k:
            world.advance(period_s)
        k += 1
        if world.ended is not None:
            break
        held.append(world.state())
        if len(held) > hold:
            yielded += 1
            yield held.popleft()
    if world.ended == "collision":
        world.dropped_frames = len(held)
        return
    while held and yielded < n_frames:
        yielded += 1
        yield held.popleft()
