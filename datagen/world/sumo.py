"""The only module that calls libsumo: start the simulation, read typed snapshots, apply commands.

`Sumo` owns one libsumo simulation (libsumo runs one per process). Each step the world reads a
`Snapshot` (the ego's own state, everyone within the context radius, its next links and signals)
and sends commands back (the ego's speed or pose, spawns, removals, a new ego route). `Network`
answers static questions about lanes (shapes, links, who may use them) and caches the answers.

Conversions happen here, once: SUMO's position is the front bumper of a vehicle and its angle
navigational (degrees, 0 = north, clockwise); readings carry the front position as SUMO gives it
and `yaw_rad`, counter-clockwise from east (+x) in radians; `box_centre` turns a reading into a
box-centre `Pose`.

Size: ~640 lines on purpose: every libsumo call lives here (the one module with side effects on
the simulation, ARCHITECTURE.md), so the rest of datagen/world/ stays pure.
"""

from __future__ import annotations

import math
import shutil
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from datagen.errors import UserError
from datagen.state import Pose
from datagen.world.behaviour import EGO_DECEL_SLACK, Profile, vtype_attributes
from datagen.world.fleet import (
    EGO_DIMS_M,
    EGO_ID,
    PED_DIMS_M,
    PED_TYPE,
    VEHICLE_TYPES,
)
from datagen.world.route import Lane, Link

TELEPORT_S = 90.0  # SUMO's time-to-teleport for jammed background vehicles
EGO_TYPE = "ego_type"


def yaw_from_sumo(angle_deg: float) -> float:
    """SUMO's navigational angle (degrees, 0 = north, clockwise) -> yaw CCW from east, rad."""
    return (math.radians(90.0 - angle_deg) + math.pi) % (2 * math.pi) - math.pi


def sumo_angle(yaw_rad: float) -> float:
    """Yaw CCW from east (rad) -> SUMO's navigational angle (degrees, 0 = north, clockwise)."""
    return (90.0 - math.degrees(yaw_rad)) % 360.0


def centre_xy(
    front_xy_m: tuple[float, float], yaw_rad: float, length_m: float
) -> tuple[float, float]:
    """SUMO front-bumper position + yaw (CCW from east) -> box centre (x_m, y_m)."""
    half = 0.5 * length_m
    return front_xy_m[0] - half * math.cos(yaw_rad), front_xy_m[1] - half * math.sin(yaw_rad)


def box_centre(front_xy_m: tuple[float, float], yaw_rad: float, length_m: float) -> Pose:
    """SUMO front-bumper position + yaw (CCW from east) -> box-centre Pose."""
    return Pose(*centre_xy(front_xy_m, yaw_rad, length_m), yaw_rad)


# Readings are NamedTuples, not frozen dataclasses: ~50 are built every 0.1 s step and a
# NamedTuple is immutable and typed at a fraction of a frozen dataclass's construction cost.
class AgentReading(NamedTuple):
    """One other vehicle or person as SUMO reports it (world frame).

    Attributes:
        agent_id: SUMO id ("v<n>" vehicles, "p<n>" people).
        type_id: SUMO vType id (fleet.dims gives its box).
        front_xy_m: SUMO position, m: a vehicle's front bumper (a person's front too).
        yaw_rad: heading, counter-clockwise from east, rad.
        speed_mps: speed, m/s.
        lane_id: lane (internal lanes start with ":"; "" off the network).
        next_edge: a person's next edge on its walk (a crossing ":<junction>_c<k>" when it is
            about to cross), "" for vehicles.
    """

    agent_id: str
    type_id: str
    front_xy_m: tuple[float, float]
    yaw_rad: float
    speed_mps: float
    lane_id: str
    next_edge: str = ""


class EgoReading(NamedTuple):
    """The ego as SUMO reports it (world frame).

    Attributes:
        front_xy_m: front-bumper position, m.
        yaw_rad: heading, counter-clockwise from east, rad.
        speed_mps: speed, m/s.
        lane_id, lane_pos_m: lane and distance of the front along it (lane-length units, m).
        road_id: edge id.
        route_index: index of the current edge in the ego's SUMO route.
    """

    front_xy_m: tuple[float, float]
    yaw_rad: float
    speed_mps: float
    lane_id: str
    lane_pos_m: float
    road_id: str
    route_index: int


class NextSignal(NamedTuple):
    """The next traffic-light link on the ego's route (libsumo getNextTLS).

    Attributes:
        tls_id: traffic light id; link_index: its link governing the ego's lane;
        distance_m: from the ego's front to the stop line, m; state: SUMO's state character
        ("r", "y", "G", ...) of that link now.
    """

    tls_id: str
    link_index: int
    distance_m: float
    state: str


class Leader(NamedTuple):
    """The vehicle ahead in the ego's lane(s): id, bumper gap (SUMO's, without the ego vType's
    minGap), m, and its speed, m/s."""

    agent_id: str
    gap_m: float
    speed_mps: float


@dataclass(frozen=True)
class Snapshot:
    """What the world reads from SUMO after a step.

    Attributes:
        ego: the ego.
        agents: every other vehicle and person within the context radius, in SUMO's order.
        links: the ego's next links along its route (getNextLinks), state included.
        next_signals: the next traffic-light links on its route (getNextTLS), nearest first.
    """

    ego: EgoReading
    agents: tuple[AgentReading, ...]
    links: tuple[Link, ...]
    next_signals: tuple[NextSignal, ...]


@dataclass(frozen=True)
class Collision:
    """One collision SUMO reported in the last step (libsumo getCollisions)."""

    collider: str
    victim: str
    kind: str
    lane_id: str


@dataclass(frozen=True)
class StepEvents:
    """What happened in the last step: collisions, vehicles that started a teleport, arrivals."""

    collisions: tuple[Collision, ...]
    teleported: tuple[str, ...]
    arrived: tuple[str, ...]


@dataclass(frozen=True)
class Roads:
    """Static tables of the network's edges (world frame, metres), sorted by edge id.

    Attributes:
        drive_edges: (E,) ids of edges with a lane for cars; drive_lanes: (E,) int their number
            of car lanes; drive_xy: (E, 2) middle of lane 0; drive_len: (E,) lane-0 length.
        walk_edges, walk_xy, walk_len: the same for pedestrian-only edges (sidewalks, paths).
    """

    drive_edges: tuple[str, ...]
    drive_lanes: np.ndarray
    drive_xy: np.ndarray
    drive_len: np.ndarray
    walk_edges: tuple[str, ...]
    walk_xy: np.ndarray
    walk_len: np.ndarray


FOE_CLEARANCE_M = 2.0  # a foe passage closer than this to the ego's path conflicts with it
# (half the ego's width, 0.93 m, plus half a car's and a margin)


class Network:
    """Static lane queries, cached (implements route.RoadNet)."""

    def __init__(self, ls):
        self._ls = ls
        self._lanes: dict[str, Lane] = {}
        self._links: dict[str, tuple[Link, ...]] = {}
        self._allowed: dict[str, tuple[str, ...]] = {}
        self._to_junction: dict[str, str] = {}
        self._stop_controlled: dict[str, bool] = {}
        self._foes: dict[str, frozenset[str]] = {}

    def internal_foes(self, via_lane_id: str) -> frozenset[str]:
        """The internal lanes whose passages really conflict with the passage starting at
        internal lane `via_lane_id`: SUMO's internal foes (getInternalFoes of it and of the
        internal lanes that follow it) whose shape comes within FOE_CLEARANCE_M of the
        passage's shape, or that end on the lane the passage ends on. SUMO also lists passages
        into the other lanes of the road a right turn enters, which it never crosses."""
        foes = self._foes.get(via_lane_id)
        if foes is None:
            from shapely import LineString, unary_union

            ls, lane, found, chain = self._ls, via_lane_id, set(), []
            for _ in range(4):
                found.update(ls.lane.getInternalFoes(lane))
                chain.append(lane)
                nxt = [k[0] for k in ls.lane.getLinks(lane)]
                if not nxt or not nxt[0].startswith(":"):
                    break
                lane = nxt[0]
            own_end = nxt[0] if nxt else ""
            path = unary_union([LineString(ls.lane.getShape(x)) for x in chain])
            path = path.buffer(FOE_CLEARANCE_M)
            keep = set()
            for f in found:
                ends = {k[0] for k in ls.lane.getLinks(f)}
                shape = ls.lane.getShape(f)
                if own_end in ends or (len(shape) > 1 and path.intersects(LineString(shape))):
                    keep.add(f)
            foes = self._foes[via_lane_id] = frozenset(keep)
        return foes

    def lane(self, lane_id: str) -> Lane:
        lane = self._lanes.get(lane_id)
        if lane is None:
            ls = self._ls
            pts = np.asarray(ls.lane.getShape(lane_id), dtype=np.float64)
            lane = Lane(pts, ls.lane.getLength(lane_id), ls.lane.getMaxSpeed(lane_id))
            self._lanes[lane_id] = lane
        return lane

    def links(self, lane_id: str) -> tuple[Link, ...]:
        """Outgoing links of a lane (static parts only: to, via, direction; state "")."""
        links = self._links.get(lane_id)
        if links is None:
            links = tuple(Link(k[0], k[4], "", k[6]) for k in self._ls.lane.getLinks(lane_id))
            self._links[lane_id] = links
        return links

    def allowed(self, lane_id: str) -> tuple[str, ...]:
        """vClasses allowed on a lane."""
        a = self._allowed.get(lane_id)
        if a is None:
            a = tuple(self._ls.lane.getAllowed(lane_id))
            self._allowed[lane_id] = a
        return a

    def stop_controlled(self, lane_id: str) -> bool:
        """A lane whose links into its junction have stop signs (static state "s" or "w")."""
        stop = self._stop_controlled.get(lane_id)
        if stop is None:
            stop = any(k[5] in ("s", "w") for k in self._ls.lane.getLinks(lane_id))
            self._stop_controlled[lane_id] = stop
        return stop

    def lane_count(self, edge_id: str) -> int:
        return self._ls.edge.getLaneNumber(edge_id)

    def to_junction(self, edge_id: str) -> str:
        """The junction an edge leads to."""
        j = self._to_junction.get(edge_id)
        if j is None:
            j = self._ls.edge.getToJunction(edge_id)
            self._to_junction[edge_id] = j
        return j


class Sumo:
    """One libsumo simulation (see module docstring). Call `close()` when done.

    Size: ~310 lines, every libsumo call of the project (the module docstring's reason)."""

    def __init__(self, net_path: Path, profile: Profile, step_s: float, seed: int):
        import libsumo

        self._ls = libsumo
        self.step_s = step_s
        self.started = False
        tmp = Path(tempfile.mkdtemp(prefix="iidsu-world-"))
        try:
            add_file = tmp / "types.add.xml"
            ET.ElementTree(_types_xml(profile)).write(add_file)
            libsumo.start(_command(net_path, add_file, step_s, seed))
            self.started = True
        finally:
            shutil.rmtree(tmp, ignore_errors=True)  # read at start-up; nothing to leak later
        self.net = Network(libsumo)
        self.TraCIException = libsumo.TraCIException
        self._ego_regards_decel = True  # the ego's speed mode is 31 (SUMO's default)
        self._ego_strategic_only = False  # its lane-change mode is 1621 (SUMO's default)

    # ------------------------------------------------------------------ network

    def roads(self, net_path: Path) -> Roads:
        """The network's drivable and walkable edges (UserError if no lane allows cars)."""
        ls = self._ls
        drive, walk, car_lanes = [], [], {}
        for e in ls.edge.getIDList():
            if e.startswith(":"):
                continue
            n = ls.edge.getLaneNumber(e)
            allowed = [ls.lane.getAllowed(f"{e}_{k}") for k in range(n)]
            if any("passenger" in a for a in allowed):
                drive.append(e)
                car_lanes[e] = sum("passenger" in a for a in allowed)
            if any("pedestrian" in a and "passenger" not in a for a in allowed):
                walk.append(e)
        if not drive:
            raise UserError(f"{net_path}: no lane allows passenger cars")
        drive_edges = sorted(drive)
        walk_edges = sorted(walk)

        def mid_len(e: str) -> tuple[float, float, float]:
            shape = ls.lane.getShape(f"{e}_0")
            pts = np.asarray(shape)
            i = len(pts) // 2
            m = pts[i] if len(pts) % 2 else 0.5 * (pts[i - 1] + pts[i])
            return float(m[0]), float(m[1]), ls.lane.getLength(f"{e}_0")

        d = np.array([mid_len(e) for e in drive_edges]).reshape(-1, 3)
        w = np.array([mid_len(e) for e in walk_edges]).reshape(-1, 3)
        return Roads(
            drive_edges=tuple(drive_edges),
            drive_lanes=np.array([car_lanes[e] for e in drive_edges]),
            drive_xy=d[:, :2],
            drive_len=d[:, 2],
            walk_edges=tuple(walk_edges),
            walk_xy=w[:, :2],
            walk_len=w[:, 2],
        )

    def find_route(self, a: str, b: str, vtype: str) -> tuple[str, ...]:
        """Edges of the fastest route from a to b for vtype; () if there is none."""
        try:
            return tuple(self._ls.simulation.findRoute(a, b, vtype).edges)
        except self._ls.TraCIException:  # e.g. the vClass may not use edge a
            return ()

    def find_walk(self, a: str, b: str) -> tuple:
        """Stages of a pedestrian's walk from edge a to edge b; () if there is none."""
        try:
            return tuple(self._ls.simulation.findIntermodalRoute(a, b, pType=PED_TYPE))
        except self._ls.TraCIException:
            return ()

    # ------------------------------------------------------------------ population

    def add_vehicle(self, vid: str, route: tuple[str, ...], type_id: str) -> None:
        """A background vehicle departing now at a random free place of its first edge."""
        ls = self._ls
        ls.route.add(f"r_{vid}", route)
        ls.vehicle.add(
            vid,
            f"r_{vid}",
            typeID=type_id,
            depart="now",
            departLane="best",
            departPos="random_free",
            departSpeed="max",
        )

    def add_person(self, pid: str, edge: str, pos_m: float, stages: tuple) -> None:
        ls = self._ls
        ls.person.add(pid, edge, pos_m, typeID=PED_TYPE)
        for st in stages:
            ls.person.appendStage(pid, st)

    def vehicle_ids(self) -> list[str]:
        """Ids of every vehicle but the ego."""
        return [v for v in self._ls.vehicle.getIDList() if v != EGO_ID]

    def person_ids(self) -> tuple[str, ...]:
        return self._ls.person.getIDList()

    def vehicle_xy(self, vid: str) -> tuple[float, float]:
        return self._ls.vehicle.getPosition(vid)

    def person_xy(self, pid: str) -> tuple[float, float]:
        return self._ls.person.getPosition(pid)

    def remove_vehicle(self, vid: str) -> None:
        self._ls.vehicle.remove(vid)

    def remove_person(self, pid: str) -> None:
        self._ls.person.remove(pid)

    def pending(self) -> int:
        """SUMO's expected number of vehicles and persons (running plus waiting to depart)."""
        return self._ls.simulation.getMinExpectedNumber()

    # ------------------------------------------------------------------ the ego

    def insert_ego(self, route: tuple[str, ...], attempt: int, at_start: bool) -> bool:
        """Add the ego on `route` (at its start or a random free place), step until it is in
        (at most 50 steps); False, and nothing left behind, if SUMO could not insert it."""
        ls = self._ls
        self._ego_regards_decel = True  # a new vehicle starts with speed mode 31
        self._ego_strategic_only = False  # ... and lane-change mode 1621
        ls.route.add(f"r_ego{attempt}", route)
        ls.vehicle.add(
            EGO_ID,
            f"r_ego{attempt}",
            typeID=EGO_TYPE,
            depart="now",
            departLane="best",
            departPos="base" if at_start else "random_free",
            departSpeed="0",
        )
        for _ in range(50):
            ls.simulationStep()
            if EGO_ID in ls.vehicle.getIDList():
                break
        if EGO_ID in ls.vehicle.getIDList():
            return True
        ls.vehicle.remove(EGO_ID)
        return False

    def subscribe_ego(self, radius_m: float) -> None:
        """Subscribe the ego's own variables and everyone within `radius_m` of it."""
        ls = v = self._ls
        ls.vehicle.subscribe(
            EGO_ID,
            [
                v.VAR_POSITION,
                v.VAR_ANGLE,
                v.VAR_SPEED,
                v.VAR_LANE_ID,
                v.VAR_LANEPOSITION,
                v.VAR_ROAD_ID,
                v.VAR_ROUTE_INDEX,
            ],
        )
        vars_ = [v.VAR_POSITION, v.VAR_ANGLE, v.VAR_SPEED, v.VAR_TYPE, v.VAR_LANE_ID]
        ls.vehicle.subscribeContext(EGO_ID, v.CMD_GET_VEHICLE_VARIABLE, radius_m, vars_)
        ls.vehicle.subscribeContext(
            EGO_ID, v.CMD_GET_PERSON_VARIABLE, radius_m, [*vars_, v.VAR_NEXT_EDGE]
        )

    def snapshot(self) -> Snapshot:
        """The ego and everyone around it after the last step (see Snapshot)."""
        ls = self._ls
        r = ls.vehicle.getSubscriptionResults(EGO_ID)
        ego = EgoReading(
            r[ls.VAR_POSITION],
            yaw_from_sumo(r[ls.VAR_ANGLE]),
            float(r[ls.VAR_SPEED]),
            r[ls.VAR_LANE_ID],
            r[ls.VAR_LANEPOSITION],
            r[ls.VAR_ROAD_ID],
            int(r[ls.VAR_ROUTE_INDEX]),
        )
        pos, ang, spd, typ, lane, nxt = (
            ls.VAR_POSITION,
            ls.VAR_ANGLE,
            ls.VAR_SPEED,
            ls.VAR_TYPE,
            ls.VAR_LANE_ID,
            ls.VAR_NEXT_EDGE,
        )
        yaw = yaw_from_sumo
        agents = tuple(
            [
                AgentReading(aid, a[typ], a[pos], yaw(a[ang]), a[spd], a[lane], a.get(nxt, ""))
                for aid, a in ls.vehicle.getContextSubscriptionResults(EGO_ID).items()
                if aid != EGO_ID
            ]
        )
        on_lane = ego.lane_id != ""
        links = (
            tuple(Link(k[0], k[4], k[5], k[6]) for k in ls.vehicle.getNextLinks(EGO_ID))
            if on_lane
            else ()
        )
        signals = tuple(NextSignal(*s) for s in ls.vehicle.getNextTLS(EGO_ID)) if on_lane else ()
        return Snapshot(ego, agents, links, signals)

    def leader(self, snap: Snapshot, lookahead_m: float) -> Leader | None:
        """The vehicle ahead of the ego within `lookahead_m` along its lanes, None if none."""
        found = self._ls.vehicle.getLeader(EGO_ID, lookahead_m)
        if not found or not found[0]:
            return None
        lid, gap = found
        speed = next((a.speed_mps for a in snap.agents if a.agent_id == lid), None)
        if speed is None:
            speed = self._ls.vehicle.getSpeed(lid)
        return Leader(lid, float(gap), float(speed))

    def ego_lane_offset(self) -> int:
        """How many lanes the ego must move to the left (negative: right) to follow its route
        (getBestLanes, what SUMO's strategic lane changing reads); 0 inside a junction or
        where SUMO does not say."""
        ls = self._ls
        lane = ls.vehicle.getLaneID(EGO_ID)
        if not lane or lane.startswith(":"):
            return 0
        for best in ls.vehicle.getBestLanes(EGO_ID):
            if best[0] == lane:
                return int(best[3])
        return 0

    def ego_route(self) -> tuple[str, ...]:
        return tuple(self._ls.vehicle.getRoute(EGO_ID))

    def set_ego_route(self, edges: list[str] | tuple[str, ...]) -> None:
        self._ls.vehicle.setRoute(EGO_ID, list(edges))

    def set_ego_speed(self, speed_mps: float, regard_decel: bool = True) -> None:
        """The speed the ego should drive at. SUMO's safety model may cap it (speed mode 31);
        with `regard_decel` False (speed mode 27, for emergency braking) it may also brake
        harder than the vType's decel to reach it."""
        if regard_decel != self._ego_regards_decel:
            self._ls.vehicle.setSpeedMode(EGO_ID, 31 if regard_decel else 27)
            self._ego_regards_decel = regard_decel
        self._ls.vehicle.setSpeed(EGO_ID, speed_mps)

    def set_ego_lane_changes(self, strategic_only: bool) -> None:
        """SUMO's default lane-change mode (1621), or only the changes the route needs (1537:
        strategic, respecting others; no cooperative, speed-gain or keep-right change). A
        continuous lane change at standstill turns the standing car's box up to ~40 degrees
        and leaves it so (SUMO's angle follows movement), its rear in the next lane: a SUMO
        car there drove into it (boulevard-long-04, "v18", drive eval of issue 38)."""
        if strategic_only != self._ego_strategic_only:
            self._ls.vehicle.setLaneChangeMode(EGO_ID, 1537 if strategic_only else 1621)
            self._ego_strategic_only = strategic_only

    def take_over_ego(self) -> None:
        """An external controller drives from now on: SUMO applies speeds as given (speed mode 0)
        and changes no lanes on its own (lane-change mode 0)."""
        self._ls.vehicle.setSpeedMode(EGO_ID, 0)
        self._ls.vehicle.setLaneChangeMode(EGO_ID, 0)

    def place_ego(self, pose: Pose, speed_mps: float, edge_hint: str = "") -> None:
        """Put the ego's box centre at `pose` for the next step, anywhere (moveToXY with
        keepRoute=2: exact position, off its lane or the road too), moving at `speed_mps`."""
        half = 0.5 * EGO_DIMS_M[0]
        x = pose.x_m + half * math.cos(pose.yaw_rad)  # SUMO places the front bumper
        y = pose.y_m + half * math.sin(pose.yaw_rad)
        self._ls.vehicle.moveToXY(EGO_ID, edge_hint, -1, x, y, sumo_angle(pose.yaw_rad), 2)
        self._ls.vehicle.setSpeed(EGO_ID, max(0.0, speed_mps))

    # ------------------------------------------------------------------ time

    def signal_states(self) -> tuple[tuple[str, str], ...]:
        """(id, state string) of every traffic light (getRedYellowGreenState: one character
        per controlled link)."""
        tl = self._ls.trafficlight
        return tuple((t, tl.getRedYellowGreenState(t)) for t in tl.getIDList())

    def switch_in_s(self, tls_id: str) -> float:
        """Seconds until traffic light `tls_id` next changes phase (getNextSwitch)."""
        ls = self._ls
        return float(ls.trafficlight.getNextSwitch(tls_id) - ls.simulation.getTime())

    def step(self) -> None:
        self._ls.simulationStep()

    def events(self) -> StepEvents:
        """Collisions, teleports and arrivals of the last step."""
        ls = self._ls
        return StepEvents(
            tuple(
                Collision(c.collider, c.victim, c.type, c.lane)
                for c in ls.simulation.getCollisions()
            ),
            tuple(ls.simulation.getStartingTeleportIDList()),
            tuple(ls.simulation.getArrivedIDList()),
        )

    def time_s(self) -> float:
        return float(self._ls.simulation.getTime())

    def close(self) -> None:
        """Stop SUMO (idempotent)."""
        if self.started:
            try:
                self._ls.close()
            except Exception:  # noqa: BLE001  (closing a broken simulation must not mask the cause)
                pass
            self.started = False


def _types_xml(p: Profile) -> ET.Element:
    """The additional file's vTypes: background types, the ego's, pedestrians'."""
    add = ET.Element("additional")
    common = vtype_attributes(p)
    for vid, vclass, length, width, height, _, _ in VEHICLE_TYPES:
        attrs = (
            dict(common)
            if vclass != "bicycle"
            else {
                **common,
                "speedFactor": "1",
                "speedDev": "0.1",
                "accel": "1.2",
                "decel": "3",
            }
        )
        ET.SubElement(
            add,
            "vType",
            id=vid,
            vClass=vclass,
            length=f"{length}",
            width=f"{width}",
            height=f"{height}",
            attrib=attrs,
        )
    el, ew, eh = EGO_DIMS_M
    ET.SubElement(
        add,
        "vType",
        id=EGO_TYPE,
        vClass="passenger",
        length=f"{el}",
        width=f"{ew}",
        height=f"{eh}",
        attrib={
            # The expert sets the speed; SUMO's own model is only the safety net, so the
            # vType asks for nothing the expert would not: no dawdling, a short own headway
            # (below every profile's time gap), decel a little above the comfortable one as
            # the limit for commanded braking, emergency braking only through the safety
            # checks, no impatience at junctions.
            "minGap": "1.0",
            "tau": "0.5",
            "sigma": "0",
            "speedFactor": "1.25",
            "speedDev": "0",
            "accel": f"{p.ego_accel_mps2:g}",
            "decel": f"{EGO_DECEL_SLACK * p.ego_comfort_decel_mps2:g}",
            "emergencyDecel": f"{p.emergency_decel_mps2:g}",
            "impatience": "0",
            "jmIgnoreFoeProb": "0",
            "jmTimegapMinor": f"{p.jm_timegap_minor_s:g}",
            "jmCrossingGap": f"{p.jm_crossing_gap_m:g}",
            "color": "1,0,0",
        },
    )
    pl, pw, ph = PED_DIMS_M
    ET.SubElement(
        add,
        "vType",
        id=PED_TYPE,
        vClass="pedestrian",
        length=f"{pl}",
        width=f"{pw}",
        height=f"{ph}",
        attrib={"speedDev": "0.1"},
    )
    return add


def _command(net_path: Path, add_file: Path, step_s: float, seed: int) -> list[str]:
    from datagen.world.towns import sumo_bin

    return [
        sumo_bin("sumo"),
        "-n",
        str(net_path),
        "-a",
        str(add_file),
        "--step-length",
        f"{step_s:g}",
        "--seed",
        str(int(seed) % (2**31)),
        "--no-step-log",
        "true",
        "--no-warnings",
        "true",
        "--xml-validation",
        "never",
        "--duration-log.disable",
        "true",
        "--collision.check-junctions",
        "true",
        "--collision.action",
        "warn",
        "--collision.mingap-factor",
        "0",  # only real contact counts as a collision
        "--time-to-teleport",
        f"{TELEPORT_S:g}",
        "--max-depart-delay",
        "5",
        "--lanechange.duration",
        "2",  # continuous lane changes (no 3 m jumps in the data)
        "--ignore-route-errors",
        "true",
        "--threads",
        "1",
    ]
