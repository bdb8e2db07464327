"""The step loop: libsumo stepped in-process, background traffic and pedestrians around an
expert-driven ego car.

    with World(WorldConfig(net_path=town_net_path("grid_small"), seed=1, weather="sunny",
                           behaviour="normal")) as world:
        for frame in record(world, n_frames=100):   # FrameState at 2 Hz
            ...

How the expert drives the ego (`ExpertDriver`). Each 0.1 s step reads a sumo.Snapshot (the
ego, everything within AGENT_RADIUS_M, its next links and signals; simulation.py), builds the
route ahead (route.py) and what is on it (perception.py) into an `expert.ExpertInput`
(planning.py) and sets the expert's target speed. The ego keeps
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
behind it), and keeps junctions clear (expert.junction_rule): it does not enter one whose exit
is blocked, nor begin a turn that would give way at a waiting point inside it while a foe
vehicle is near (waiting there, the car's front can reach into the foe's lane).

What the dataset keeps of an episode that still ends in an ego collision: `record` holds every
state back COLLISION_DROP_S (5 s) and drops the held states when the collision comes, so no
frame shows the expert driving into it (World.dropped_frames, stats["dropped_frames"]).

The ego drives a random route that is extended with a new random destination before it ends
(`WorldConfig.reroute`); traffic lives in a bubble around it (traffic.py).

Who drives the ego: one seam. `WorldConfig.ego_driver="expert"` (the default, above: the
expert's step, `ExpertDriver`) or "external": a controller (the closed-loop evaluator) computes
the ego's next pose and speed with its own kinematic model and hands them over every 0.1 s step
as an `EgoCommand`; the world puts the ego there, keeps its SUMO route on the planned route and
moves the traffic bubble with it (external.py). `state()` gives the FrameState the sensors need;
`truth()` gives what infractions need beyond the agents' boxes in `state().agents`: lane, signal
of the ego's lane and its distance (any range), entering a junction on red, route progress,
SUMO's own ego collisions (incomplete for a placed vehicle, sumo#6327: check boxes too). Nothing
ends an externally driven episode but SUMO removing the ego; collisions and red lights are the
caller's to score. `expert_plan()` gives the expert's plan from the ego's state now, whoever
drives it (planning.py).

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

import math
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

import datagen.world.expert as expert
import datagen.world.perception as perception
import datagen.world.route as route
from datagen.errors import UserError
from datagen.state import AgentState, FrameState
from datagen.world.behaviour import EGO_DECEL_SLACK, PROFILES, Profile
from datagen.world.config import EGO_DRIVERS, WorldConfig
from datagen.world.external import EgoCommand, ExternalDriver
from datagen.world.fleet import EGO_DIMS_M, EGO_ID, dims
from datagen.world.planning import Planner
from datagen.world.route import SIGNAL_RANGE_M
from datagen.world.simulation import AGENT_RADIUS_M, Simulation
from datagen.world.sumo import Snapshot, box_centre
from schemas import FRAME_PERIOD_S, WAYPOINT_TIMES_S, WEATHERS

BLOCKED_S = 80.0  # ego standing this long (not at a red light) ends the episode ("blocked")
# record() drops the frames of the last 5 s before an ego collision: more than the 2 s of future
# waypoints a frame is labelled with plus ~3 s of approach, so no frame shows driving into it.
COLLISION_DROP_S = 5.0
SLOW_LANE_CHANGE_MPS = 1.0  # slower than this the expert ego changes lanes only for its route

_open_world: World | None = None  # libsumo runs one simulation per process


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


class ExpertDriver:
    """Steps `sim` with the expert driving the ego, SUMO's safety model under it (see the
    module docstring)."""

    def __init__(self, sim: Simulation, planner: Planner):
        self._sim = sim
        self._planner = planner
        self._standing_s = 0.0

    def step(self, command: None = None) -> None:
        """One step (`command`: always None, the expert takes none)."""
        sim = self._sim
        sumo = sim.sumo
        st = sim.stats
        p = sim.profile
        dt = sim.config.step_s
        before = sim.snap
        v0 = before.ego.speed_mps
        inp = self._planner.expert_input()
        dec = expert.decide(inp, p, EGO_DECEL_SLACK * p.ego_comfort_decel_mps2)
        target, reason = dec.target_speed_mps, dec.reason
        # no lane change but the route's while (nearly) standing (sumo.set_ego_lane_changes)
        sumo.set_ego_lane_changes(strategic_only=v0 < SLOW_LANE_CHANGE_MPS)
        if dec.brake_mps2 > 0.0:  # an emergency: brake harder than the vType's decel
            v_cmd = max(dec.target_speed_mps, v0 - dec.brake_mps2 * dt)
            sumo.set_ego_speed(v_cmd, regard_decel=False)
        else:
            sumo.set_ego_speed(dec.target_speed_mps)
        lane0 = before.ego.lane_id
        first_state = before.links[0].state if before.links else ""
        events, mine = sim.step_sumo()
        # --- what happened in the step
        for c in mine:
            if sim.config.end_on_collision:
                sim.end("collision", f"{c.collider} hit {c.victim} ({c.kind}) on {c.lane_id}")
        if EGO_ID in events.teleported:
            sim.end("teleported", "SUMO teleported the jammed ego")
            return
        if EGO_ID in events.arrived:
            sim.end("route_end", "the ego reached the end of its route")
            return
        # the new snapshot; path and signals are still the previous step's until sense()
        sim.snap = snap = sumo.snapshot()
        v1 = snap.ego.speed_mps
        lane1 = snap.ego.lane_id
        route_end = inp.route_end_m
        if route_end is not None and route_end < 5.0 and v1 < expert.STOPPED_MPS:
            sim.end("route_end", "the ego stopped at the end of its route")
        sim.rules.note_red_light(lane0, lane1, first_state)
        sim.rules.note_stop(lane0, snap, sim.signals)
        stop_d = sim.signals.stop_distance_m
        # did SUMO hold the ego below the expert's command?
        v_exp = min(target, v0 + p.ego_accel_mps2 * dt)
        v_exp = max(v_exp, v0 - EGO_DECEL_SLACK * p.ego_comfort_decel_mps2 * dt)
        if v1 < v_exp - 0.1 and reason not in ("red_light", "stop_sign", "route_end"):
            reason = perception.attribute_hold(
                stop_d, sim.path, snap.agents, lane1.startswith(":"), sim.path.link_dist
            )
        if (v0 - v1) / dt > EGO_DECEL_SLACK * p.ego_comfort_decel_mps2 + 0.3:
            st.hard_brakes += 1  # harder than any command: SUMO's safety braking
        sim.reason = reason
        st.reasons[reason] = st.reasons.get(reason, 0) + 1
        st.distance_m += v1 * dt
        st.speed_sum += v1
        if dec.reason == "vehicle" and v1 > 2.0:  # steady following: the time gap kept
            cars = [o for o in inp.obstacles if o.kind == "vehicle"]
            bind = min(cars, key=lambda o: expert.follow_speed(o.distance_m, o.speed_mps, p))
            if bind.track_id.startswith("lead:") and abs(bind.speed_mps - v1) < 1.0:
                st.gaps_s.append(bind.distance_m / v1)
        sim.sense()
        # standing still too long (not at a red light) ends the episode
        if v1 < expert.STOPPED_MPS and sim.signals.light != "red":
            self._standing_s += dt
            if self._standing_s >= BLOCKED_S:
                sim.end("blocked", f"ego stood {BLOCKED_S:.0f} s on {lane1}")
        else:
            self._standing_s = 0.0
        sim.manage(reroute=sim.config.reroute)


class World:
    """A SUMO episode around the ego (context manager; see the module docstring). `step()`
    hands each step to who drives the ego (ExpertDriver, or external.ExternalDriver);
    `state()`, `truth()`, `stats` and `expert_plan()` read the running simulation
    (simulation.py).

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
        self.dropped_frames = 0
        self._sticky: route.Sticky | None = None  # the junction a turn command was given for
        self._plan_k = 0  # index of the current target in the sparse route plan
        self._sim: Simulation | None = None
        try:
            _open_world = self
            self._sim = Simulation(config, self.profile)
        except BaseException:
            self.close()
            raise
        self._planner = Planner(self._sim)
        if config.ego_driver == "expert":
            self._driver = ExpertDriver(self._sim, self._planner)
        else:
            self._driver = ExternalDriver(self._sim)

    @property
    def ended(self) -> str | None:
        return self._sim.ended

    @property
    def end_detail(self) -> str:
        return self._sim.end_detail

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
        self._driver.step(command)
        self._sim.stats.wall_s += time.perf_counter() - t0

    def advance(self, dt_s: float) -> None:
        """Run the simulation `dt_s` seconds (whole steps) with the expert in control."""
        if self.config.ego_driver != "expert":
            raise RuntimeError("an externally driven ego moves only by step(EgoCommand)")
        if self.ended is not None:
            return
        t0 = time.perf_counter()
        for _ in range(max(1, int(round(dt_s / self.config.step_s)))):
            self._driver.step()
            if self.ended is not None:
                break
        self._sim.stats.wall_s += time.perf_counter() - t0

    def expert_plan(
        self, times_s: tuple[float, ...] = WAYPOINT_TIMES_S
    ) -> tuple[np.ndarray, expert.Decision] | None:
        """The privileged expert's plan from the ego's state now, whoever drives it: where its
        box centre would be at each of `times_s` ((len(times_s), 2), world frame, m) and its
        decision now; None off the network. The plan is `expert.rollout` along the route's
        lanes from the lane point nearest the ego's front (so an ego beside its lane is led
        back to the lane's centre), in a world that keeps its velocity. With the expert
        driving, its first step is the command `step()` gives next."""
        return self._planner.plan(times_s)

    @property
    def time_s(self) -> float:
        return self._sim.sumo.time_s()

    def state(self) -> FrameState:
        """Ground truth now (world frame, box centres): see datagen/state.py."""
        sim = self._sim
        snap: Snapshot = sim.snap
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
            sim.net, ego_r.lane_id, sim.path, snap.links, self._sticky
        )
        if sim.plan:  # the sparse form (WorldConfig.target_point)
            i = sim.route_index()
            on_edge = i < len(sim.route) and ego_r.road_id == sim.route[i]
            self._plan_k = route.next_plan_point(
                sim.plan, self._plan_k, i, ego_r.lane_pos_m if on_edge else None, ego_r.front_xy_m
            )
            p = sim.plan[self._plan_k]
            target = (p.x_m, p.y_m)
        sig = sim.signals
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
            expert_reason=sim.reason,
            signals=sim.sumo.signal_states(),
        )

    def truth(self) -> EgoTruth:
        """Ground truth about the ego after the last step, for scoring (see EgoTruth)."""
        sim = self._sim
        ego = sim.snap.ego
        on_net = ego.lane_id != ""
        sig = sim.signals
        nxt = sim.snap.next_signals[0] if sim.snap.next_signals else None
        return EgoTruth(
            time_s=self.time_s,
            lane_id=ego.lane_id,
            road_id=ego.road_id,
            route_index=sim.route_index(),
            route=sim.route,
            remaining_route_m=sim.remaining_route() if on_net and sim.on_plan else None,
            light=sig.light if on_net else "none",
            light_distance_m=sig.light_distance_m if on_net else None,
            tls_id=nxt.tls_id if nxt else "",
            tls_link_index=nxt.link_index if nxt else -1,
            entered_on_red=sim.rules.entered_on_red,
            stop_distance_m=sig.stop_distance_m if on_net else None,
            collisions=sim.ego_collisions,
        )

    @property
    def stats(self) -> dict:
        """Episode statistics: collisions (of the ego; other_collisions between other road
        users, each pair once), red_light_violations (ego entered a junction on red),
        teleports (all vehicles), hard_brakes (steps braking harder than any command: SUMO's
        safety braking), mean_speed_mps, mean_time_gap_s and median_time_gap_s (bumper gap /
        speed while steadily following a lead, None if never), sim/wall seconds, steps per
        expert reason, and how the episode ended."""
        st = self._sim.stats
        return {
            "steps": st.steps,
            "sim_s": round(st.sim_s, 3),
            "wall_s": round(st.wall_s, 3),
            "collisions": st.collisions,
            "other_collisions": st.other_collisions,
            "red_light_violations": self._sim.rules.red_light_violations,
            "teleports": st.teleports,
            "hard_brakes": st.hard_brakes,
            "reroutes": st.reroutes,
            "distance_m": round(st.distance_m, 1),
            "mean_speed_mps": st.speed_sum / st.steps if st.steps else 0.0,
            "mean_time_gap_s": float(np.mean(st.gaps_s)) if st.gaps_s else None,
            "median_time_gap_s": float(np.median(st.gaps_s)) if st.gaps_s else None,
            "following_s": round(len(st.gaps_s) * self.config.step_s, 1),
            "n_vehicles": self._sim.traffic.n_veh,
            "n_pedestrians": self._sim.traffic.n_ped,
            "reasons": dict(sorted(st.reasons.items())),
            "ended": self.ended,
            "end_detail": self.end_detail,
            "dropped_frames": self.dropped_frames,
        }

    def close(self) -> None:
        """Stop SUMO (idempotent; safe after a failed start)."""
        global _open_world
        if self._sim is not None:
            self._sim.close()
        if _open_world is self:
            _open_world = None

    def __enter__(self) -> World:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        sim = getattr(self, "_sim", None)
        if sim is not None and sim.sumo.started:
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
