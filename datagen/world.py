"""The driving world: libsumo stepped in-process, background traffic and pedestrians around an
expert-driven ego car. This is the only module that talks to libsumo.

    with World(WorldConfig(net_path=town_net_path("grid_small"), seed=1, weather="sunny",
                           behaviour="normal")) as world:
        for frame in record(world, n_frames=100):   # FrameState at 2 Hz
            ...

How the ego is driven. Each 0.1 s step `World` reads the ego's surroundings from libsumo
(subscriptions, a context subscription of everything within AGENT_RADIUS_M, the ego's next links
and signals), builds an `expert.ExpertInput` and sets the expert's target speed with
`vehicle.setSpeed`. The ego keeps SUMO's default speed mode 31, so SUMO remains the safety net
under the expert: it still caps the commanded speed by its safe speed behind the leader (bit 0),
by the vType's acceleration and deceleration (bits 1, 2), by right of way at junctions, pedestrians
on crossings included (bit 3), and brakes hard rather than pass a red light (bit 4). The ego
vType's decel, the cap on commanded braking, is EGO_DECEL_SLACK x the comfortable deceleration
the expert plans with; only SUMO's safety checks brake harder (up to emergencyDecel), i.e. only
to avoid a collision (counted in `stats["hard_brakes"]`). When SUMO holds the ego below the
expert's target, the step's reason names what it yields to (`junction`, `stop_sign`,
`pedestrian`, `vehicle`). Lane choice and lane changes stay with SUMO's lane-change model.

Traffic lives in a bubble around the ego: background vehicles (random routes, the profile's vType
parameters) and pedestrians (walks between random sidewalk edges, across crossings) are spawned
at 60-300 m (vehicles) and 40-200 m (people) from the ego and removed beyond 400/260 m, so the
cost per step does not grow with the town. The ego drives a random route that is extended with a
new random destination before it ends (`WorldConfig.reroute`).

Poses are converted once here: SUMO's position is the front bumper and its angle navigational
(degrees, 0 = north, clockwise); FrameState poses are box centres with yaw counter-clockwise from
east in radians.
"""

from __future__ import annotations

import logging
import math
import re
import shutil
import tempfile
import time
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from datagen import expert
from datagen.behaviour import PROFILES, Profile, vtype_attributes
from datagen.errors import UserError
from datagen.state import AgentState, FrameState, Pose
from schemas import WEATHERS

AGENT_RADIUS_M = 100.0  # agents within this distance of the ego are in FrameState.agents
SIGNAL_RANGE_M = 30.0  # FrameState.traffic_light / stop_sign look this far along the route
PATH_LOOKAHEAD_M = 100.0  # the expert plans over this much of its route
COMMAND_RANGE_M = 40.0  # a turn command is given from this distance before the junction
TARGET_AHEAD_M = 30.0  # target point on plain road: this far ahead along the route
EXIT_INTO_M = 5.0  # target point at a junction: this far into its exit lane
BLOCKED_S = 80.0  # ego standing this long (not at a red light) ends the episode ("blocked")
TELEPORT_S = 90.0  # SUMO's time-to-teleport for jammed background vehicles
WARMUP_S = 10.0  # traffic runs this long before the ego is inserted

# Vehicle bubble around the ego (m): spawn ring and removal radius.
VEH_SPAWN_M = (60.0, 300.0)
VEH_REMOVE_M = 400.0
PED_SPAWN_M = (40.0, 200.0)
PED_REMOVE_M = 260.0

EGO_ID = "ego"
# The ego vType's decel (the cap on commanded braking) is this much above the comfortable
# deceleration the expert plans with: room to track the planned profile at a 0.1 s step without
# overshooting stop points (measured: at exactly b a red-light stop ends ~0.7 m further).
EGO_DECEL_SLACK = 1.2
# Background vehicle types: (id, vClass, length, width, height, share, box class).
VEHICLE_TYPES = (
    ("car", "passenger", 4.5, 1.8, 1.5, 0.58, "vehicle"),
    ("suv", "passenger", 4.9, 1.95, 1.8, 0.17, "vehicle"),
    ("van", "delivery", 5.6, 2.0, 2.4, 0.10, "vehicle"),
    ("truck", "truck", 8.5, 2.5, 3.4, 0.05, "vehicle"),
    ("bus", "bus", 12.0, 2.55, 3.2, 0.04, "vehicle"),
    ("bicycle", "bicycle", 1.7, 0.65, 1.7, 0.06, "bicycle"),
)
EGO_DIMS_M = (4.7, 1.85, 1.5)  # length, width, height (a mid-size sedan)
PED_DIMS_M = (0.4, 0.5, 1.75)

_LIGHT = {"r": "red", "u": "red", "y": "yellow", "Y": "yellow", "G": "green", "g": "green"}
_COMMAND = {"s": "straight", "l": "left", "L": "left", "t": "left", "r": "right", "R": "right"}

_log = logging.getLogger(__name__)
_open_world: World | None = None  # libsumo runs one simulation per process


@dataclass(frozen=True)
class WorldConfig:
    """One episode's world.

    Attributes:
        net_path: SUMO network (.net.xml or .net.xml.gz).
        seed: seeds SUMO and every random choice here (same seed, same trajectories).
        weather: schemas.WEATHERS (affects only the profile and pedestrian numbers here).
        behaviour: schemas.BEHAVIOURS, the profile (behaviour.PROFILES).
        step_s: SUMO step, s (the expert acts every step).
        n_vehicles: background vehicles around the ego; None = profile density x lane-km in
            the bubble around the ego's start.
        n_pedestrians: pedestrians around the ego; None = profile density x sidewalk-km.
        reroute: extend the ego's route before it ends (else the episode ends at its end).
        warmup_s: traffic runs this long before the ego enters.
        ego_route: the ego's route as edge ids (tests, replays); None = a random route.
    """

    net_path: Path
    seed: int
    weather: str
    behaviour: str
    step_s: float = 0.1
    n_vehicles: int | None = None
    n_pedestrians: int | None = None
    reroute: bool = True
    warmup_s: float = WARMUP_S
    ego_route: tuple[str, ...] | None = None


@dataclass
class _Lane:
    """Static geometry of one lane (world frame, metres)."""

    pts: np.ndarray  # (N, 2) float64 shape points
    length_m: float  # SUMO lane length (may differ slightly from the shape's)
    speed_mps: float


@dataclass
class _Stats:
    steps: int = 0
    sim_s: float = 0.0
    wall_s: float = 0.0
    collisions: int = 0
    other_collisions: int = 0
    red_light_violations: int = 0
    teleports: int = 0
    hard_brakes: int = 0
    reroutes: int = 0
    distance_m: float = 0.0
    speed_sum: float = 0.0
    gaps_s: list = field(default_factory=list)
    reasons: dict = field(default_factory=dict)


def _yaw_from_sumo(angle_deg: float) -> float:
    """SUMO's navigational angle (degrees, 0 = north, clockwise) -> yaw CCW from east, rad."""
    return (math.radians(90.0 - angle_deg) + math.pi) % (2 * math.pi) - math.pi


def _box_centre(x: float, y: float, angle_deg: float, length: float) -> Pose:
    """SUMO front-bumper position + navigational angle -> box-centre Pose (yaw CCW from east)."""
    yaw = _yaw_from_sumo(angle_deg)
    half = 0.5 * length
    return Pose(x - half * math.cos(yaw), y - half * math.sin(yaw), yaw)


def _project(
    xy: np.ndarray, pts: np.ndarray, s: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project (K, 2) points onto a polyline: along-path s (K,), unsigned lateral distance (K,)
    and the path heading at the projection (K,), radians."""
    a = pts[:-1]  # (M, 2)
    d = pts[1:] - a  # (M, 2)
    seg_len = np.sqrt((d * d).sum(1))  # (M,)
    l2 = np.maximum(seg_len * seg_len, 1e-9)
    rel = xy[:, None, :] - a[None]  # (K, M, 2)
    t = np.clip((rel * d[None]).sum(-1) / l2, 0.0, 1.0)  # (K, M)
    off = rel - t[..., None] * d[None]
    dist = np.sqrt((off * off).sum(-1))  # (K, M)
    idx = dist.argmin(1)
    k = np.arange(len(xy))
    along = s[idx] + t[k, idx] * seg_len[idx]
    # points beyond the ends: extend the first/last segment so "behind" gives negative s
    heading = np.arctan2(d[idx, 1], d[idx, 0])
    first = (idx == 0) & (t[k, idx] <= 0.0)
    if first.any():
        u = d[0] / max(seg_len[0], 1e-9)
        along[first] = s[0] + ((xy[first] - a[0]) @ u)
        dist[k[first], 0] = np.abs((xy[first] - a[0]) @ np.array([-u[1], u[0]]))
    return along, dist[k, idx], heading


class World:
    """A SUMO episode with the expert ego (context manager; see module docstring).

    Attributes:
        config: the WorldConfig.
        profile: behaviour.PROFILES[config.behaviour].
        ended: None while running, else why it ended: "route_end", "teleported", "blocked",
            "collision".
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
        from datagen.towns import check_network

        check_network(config.net_path)  # a clear UserError before SUMO sees a bad file
        self.config = config
        self.profile: Profile = PROFILES[config.behaviour]
        self.ended: str | None = None
        self.end_detail: str = ""
        self._rng = np.random.default_rng(config.seed)
        self._stats = _Stats()
        self._tmp = Path(tempfile.mkdtemp(prefix="iidsu-world-"))
        self._started = False
        self._lanes: dict[str, _Lane] = {}
        self._edge_choice: dict[str, bool] = {}
        self._chains: dict[str, list[str]] = {}
        self._kerb: dict[str, bool] = {}
        self._colliding: set[tuple[str, str]] = set()
        self._route_end_m: float | None = None
        self._stop_junction: str | None = None
        self._veh_dims: dict[str, tuple[float, float, float, str]] = {}
        self._n_spawned = 0
        self._reason = "none"
        self._target = 0.0
        self._stop_done_lane: str | None = None
        self._stop_wait_s = 0.0
        self._standing_s = 0.0
        self._cmd_sticky: tuple[str, str, str] | None = None  # (junction, command, exit lane)
        self._ego_cache: dict = {}
        self._context: dict = {}
        self._links: tuple = ()
        self._path: tuple[np.ndarray, np.ndarray] | None = None
        try:
            import libsumo

            self._ls = libsumo
            _open_world = self
            self._start()
            self._setup_network()
            self._populate()
            self._insert_ego()
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ setup

    def _start(self) -> None:
        from datagen.towns import sumo_bin

        p = self.profile
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
            id="ego_type",
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
            id="ped",
            vClass="pedestrian",
            length=f"{pl}",
            width=f"{pw}",
            height=f"{ph}",
            attrib={"speedDev": "0.1"},
        )
        add_file = self._tmp / "types.add.xml"
        ET.ElementTree(add).write(add_file)
        cmd = [
            sumo_bin("sumo"),
            "-n",
            str(self.config.net_path),
            "-a",
            str(add_file),
            "--step-length",
            f"{self.config.step_s:g}",
            "--seed",
            str(int(self.config.seed) % (2**31)),
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
        self._ls.start(cmd)
        self._started = True
        shutil.rmtree(self._tmp, ignore_errors=True)  # read at start-up; nothing to leak later

    def _setup_network(self) -> None:
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
            raise UserError(f"{self.config.net_path}: no lane allows passenger cars")
        self._drive_edges = sorted(drive)
        self._drive_lanes = np.array([car_lanes[e] for e in self._drive_edges])
        self._walk_edges = sorted(walk)

        def mid_len(e: str) -> tuple[float, float, float]:
            shape = ls.lane.getShape(f"{e}_0")
            pts = np.asarray(shape)
            i = len(pts) // 2
            m = pts[i] if len(pts) % 2 else 0.5 * (pts[i - 1] + pts[i])
            return float(m[0]), float(m[1]), ls.lane.getLength(f"{e}_0")

        d = np.array([mid_len(e) for e in self._drive_edges]).reshape(-1, 3)
        self._drive_xy, self._drive_len = d[:, :2], d[:, 2]
        w = np.array([mid_len(e) for e in self._walk_edges]).reshape(-1, 3)
        self._walk_xy, self._walk_len = w[:, :2], w[:, 2]

    def _edges_near(self, xy: np.ndarray, lens: np.ndarray, centre, r0: float, r1: float):
        if len(xy) == 0:
            return np.zeros(0, dtype=int)
        dist = np.hypot(xy[:, 0] - centre[0], xy[:, 1] - centre[1])
        return np.flatnonzero((dist >= r0) & (dist <= r1) & (lens > 5.0))

    def _lane_km_near(self, centre, radius: float) -> tuple[float, float]:
        """(car lane-km, sidewalk-km) of edges whose middle lies within `radius` of centre."""
        idx = self._edges_near(self._drive_xy, self._drive_len, centre, 0.0, radius)
        lane_km = float((self._drive_len[idx] * self._drive_lanes[idx]).sum()) / 1000.0
        idx = self._edges_near(self._walk_xy, self._walk_len, centre, 0.0, radius)
        walk_km = float(self._walk_len[idx].sum()) / 1000.0
        return lane_km, walk_km

    def _pick_ego_route(self) -> list[str]:
        n = len(self._drive_edges)
        cand = np.flatnonzero(self._drive_len >= 30.0)
        if len(cand) == 0:
            cand = np.arange(n)
        best: list[str] = []
        for _ in range(60):
            a = int(cand[self._rng.integers(len(cand))])
            dist = np.hypot(*(self._drive_xy - self._drive_xy[a]).T)
            far = np.flatnonzero(dist >= min(600.0, 0.5 * dist.max()))
            b = int(far[self._rng.integers(len(far))]) if len(far) else int(self._rng.integers(n))
            if a == b:
                continue
            r = self._find_route(self._drive_edges[a], self._drive_edges[b], "ego_type")
            if len(r) >= 3:
                return list(r)
            if len(r) > len(best):
                best = list(r)
        if best:
            return best
        raise UserError(f"{self.config.net_path}: found no route for a passenger car")

    def _populate(self) -> None:
        """Choose the ego's route, fill the bubble around its start, run the warm-up."""
        if self.config.ego_route:
            self._ego_route = list(self.config.ego_route)
        else:
            self._ego_route = self._pick_ego_route()
        start = self._edge_mid(self._ego_route[0])
        lane_km, walk_km = self._lane_km_near(start, VEH_SPAWN_M[1])
        p = self.profile
        nv = self.config.n_vehicles
        self._n_veh = int(np.clip(round(p.traffic_density * lane_km), 5, 150)) if nv is None else nv
        npd = self.config.n_pedestrians
        if npd is None:
            npd = int(np.clip(round(p.pedestrian_density * walk_km), 0, 100)) if walk_km else 0
        self._n_ped = npd if self._walk_edges else 0
        self._spawn_vehicles(start, self._n_veh, r0=0.0, r1=VEH_SPAWN_M[1])
        self._spawn_pedestrians(start, self._n_ped, r0=0.0, r1=PED_SPAWN_M[1])
        for _ in range(int(round(self.config.warmup_s / self.config.step_s))):
            self._ls.simulationStep()

    def _find_route(self, a: str, b: str, vtype: str) -> tuple[str, ...]:
        """Edges of the fastest route from a to b for vtype; () if there is none."""
        try:
            return tuple(self._ls.simulation.findRoute(a, b, vtype).edges)
        except self._ls.TraCIException:  # e.g. the vClass may not use edge a
            return ()

    def _edge_mid(self, edge: str) -> np.ndarray:
        i = self._drive_edges.index(edge)
        return self._drive_xy[i]

    def _spawn_vehicles(self, centre, k: int, r0: float, r1: float) -> None:
        ls = self._ls
        idx = self._edges_near(self._drive_xy, self._drive_len, centre, r0, r1)
        if len(idx) == 0 or k <= 0:
            return
        w = self._drive_len[idx] / self._drive_len[idx].sum()
        shares = np.array([t[5] for t in VEHICLE_TYPES])
        for _ in range(k):
            vt = VEHICLE_TYPES[int(self._rng.choice(len(VEHICLE_TYPES), p=shares / shares.sum()))]
            for _try in range(4):
                a = int(idx[self._rng.choice(len(idx), p=w)])
                b = int(self._rng.integers(len(self._drive_edges)))
                if a == b:
                    continue
                r = self._find_route(self._drive_edges[a], self._drive_edges[b], vt[0])
                if len(r) < 2:
                    continue
                vid = f"v{self._n_spawned}"
                self._n_spawned += 1
                ls.route.add(f"r_{vid}", r)
                ls.vehicle.add(
                    vid,
                    f"r_{vid}",
                    typeID=vt[0],
                    depart="now",
                    departLane="best",
                    departPos="random_free",
                    departSpeed="max",
                )
                break

    def _spawn_pedestrians(self, centre, k: int, r0: float, r1: float) -> None:
        ls = self._ls
        idx = self._edges_near(self._walk_xy, self._walk_len, centre, r0, r1)
        if len(idx) == 0 or k <= 0:
            return
        w = self._walk_len[idx] / self._walk_len[idx].sum()
        for _ in range(k):
            for _try in range(4):
                a = int(idx[self._rng.choice(len(idx), p=w)])
                dist = np.hypot(*(self._walk_xy - self._walk_xy[a]).T)
                dest = np.flatnonzero((dist > 60.0) & (dist < 400.0))
                if len(dest) == 0:
                    continue
                b = int(dest[self._rng.integers(len(dest))])
                ea, eb = self._walk_edges[a], self._walk_edges[b]
                try:
                    stages = ls.simulation.findIntermodalRoute(ea, eb, pType="ped")
                except ls.TraCIException:
                    stages = ()
                if not stages:
                    continue
                pid = f"p{self._n_spawned}"
                self._n_spawned += 1
                pos = float(self._rng.uniform(0.0, max(0.1, self._walk_len[a] - 0.1)))
                ls.person.add(pid, ea, pos, typeID="ped")
                for st in stages:
                    ls.person.appendStage(pid, st)
                break

    def _insert_ego(self) -> None:
        ls = self._ls
        fixed = bool(self.config.ego_route)
        for attempt in range(1 if fixed else 5):
            if attempt:
                self._ego_route = self._pick_ego_route()
            ls.route.add(f"r_ego{attempt}", self._ego_route)
            ls.vehicle.add(
                EGO_ID,
                f"r_ego{attempt}",
                typeID="ego_type",
                depart="now",
                departLane="best",
                departPos="base" if fixed else "random_free",
                departSpeed="0",
            )
            for _ in range(50):
                ls.simulationStep()
                if EGO_ID in ls.vehicle.getIDList():
                    break
            if EGO_ID in ls.vehicle.getIDList():
                break
            ls.vehicle.remove(EGO_ID)
        else:
            raise RuntimeError("could not insert the ego vehicle")
        v = ls
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
        ls.vehicle.subscribeContext(EGO_ID, v.CMD_GET_VEHICLE_VARIABLE, AGENT_RADIUS_M, vars_)
        ls.vehicle.subscribeContext(EGO_ID, v.CMD_GET_PERSON_VARIABLE, AGENT_RADIUS_M, vars_)
        ls.simulationStep()
        self._set_route(ls.vehicle.getRoute(EGO_ID))
        self._read()
        self._sense()
        self._t0_wall = time.perf_counter()

    # ------------------------------------------------------------------ per step

    def _lane(self, lane_id: str) -> _Lane:
        lane = self._lanes.get(lane_id)
        if lane is None:
            ls = self._ls
            pts = np.asarray(ls.lane.getShape(lane_id), dtype=np.float64)
            lane = _Lane(pts, ls.lane.getLength(lane_id), ls.lane.getMaxSpeed(lane_id))
            self._lanes[lane_id] = lane
        return lane

    def _read(self) -> None:
        ls = self._ls
        self._ego_cache = ls.vehicle.getSubscriptionResults(EGO_ID)
        self._context = ls.vehicle.getContextSubscriptionResults(EGO_ID)

    def _sense(self) -> None:
        """Path ahead, its links and the expert's input from the last step's results."""
        ls = self._ls
        r = self._ego_cache
        lane_id, lane_pos = r[ls.VAR_LANE_ID], r[ls.VAR_LANEPOSITION]
        self._links = ls.vehicle.getNextLinks(EGO_ID)
        lane = self._lane(lane_id)
        # path polyline from the ego's front along its current lane and next links
        pieces = [self._cut(lane, lane_pos)]
        seg_lanes = [(0.0, lane_id)]
        dist = lane.length_m - lane_pos
        if lane_id.startswith(":"):
            # inside a junction getNextLinks starts after the exit lane: walk out first
            for nxt in self._exit_chain(lane_id):
                seg_lanes.append((dist, nxt))
                pieces.append(self._lane(nxt).pts)
                dist += self._lane(nxt).length_m
        link_dist = []
        for link in self._links:
            link_dist.append(dist)
            if dist > PATH_LOOKAHEAD_M:
                break
            chain = self._via_chain(link[4]) if link[4] else []
            for via in chain:
                pieces.append(self._lane(via).pts)
                dist += self._lane(via).length_m
            seg_lanes.append((dist, link[0]))
            dist += self._lane(link[0]).length_m
            pieces.append(self._lane(link[0]).pts)
        pts = np.concatenate(pieces)
        step = np.diff(pts, axis=0)
        keep = np.concatenate([[True], np.hypot(step[:, 0], step[:, 1]) > 0.2])
        pts = pts[keep]
        if len(pts) < 2:
            yaw = _yaw_from_sumo(r[ls.VAR_ANGLE])
            x, y = r[ls.VAR_POSITION]
            pts = np.array([[x, y], [x + math.cos(yaw), y + math.sin(yaw)]])
        seg = np.diff(pts, axis=0)
        s = np.concatenate([[0.0], np.cumsum(np.hypot(seg[:, 0], seg[:, 1]))])
        self._path = (pts, s)
        self._link_dist = link_dist
        self._seg_lanes = seg_lanes
        self._light, self._light_d, self._stop_d = self._signals()

    def _via_chain(self, internal: str) -> list[str]:
        """The internal lane(s) of one junction passage starting at `internal` (an internal
        junction splits a turn into two lanes)."""
        chain = self._chains.get(internal)
        if chain is None:
            chain, lid = [internal], internal
            while len(chain) < 4:
                links = self._ls.lane.getLinks(lid)
                if not links or not links[0][4]:
                    break
                lid = links[0][4]
                chain.append(lid)
            self._chains[internal] = chain
        return chain

    def _exit_chain(self, internal: str) -> list[str]:
        """From inside a junction: the remaining internal lanes and the exit lane."""
        key = "exit" + internal
        chain = self._chains.get(key)
        if chain is None:
            chain, lid = [], internal
            while len(chain) < 4:
                links = self._ls.lane.getLinks(lid)
                if not links:
                    break
                lid = links[0][4] or links[0][0]
                chain.append(lid)
                if not lid.startswith(":"):
                    break
            self._chains[key] = chain
        return chain

    @staticmethod
    def _cut(lane: _Lane, pos_m: float) -> np.ndarray:
        """The lane's shape from `pos_m` (lane-length units) to its end."""
        pts = lane.pts
        seg = np.diff(pts, axis=0)
        cum = np.concatenate([[0.0], np.cumsum(np.hypot(seg[:, 0], seg[:, 1]))])
        target = pos_m * (cum[-1] / lane.length_m if lane.length_m > 0 else 1.0)
        i = int(np.searchsorted(cum, target, side="right"))
        if i >= len(pts):
            return pts[-1:]
        i = max(i, 1)
        f = (target - cum[i - 1]) / max(cum[i] - cum[i - 1], 1e-9)
        start = pts[i - 1] + f * (pts[i] - pts[i - 1])
        return np.vstack([start, pts[i:]])

    def _signals(self) -> tuple[str, float | None, float | None]:
        """(light, light distance, stop distance) of the next signal / stop entry on the route."""
        light, light_d = "none", None
        for _tls, _idx, d, state in self._ls.vehicle.getNextTLS(EGO_ID)[:1]:
            light, light_d = _LIGHT.get(state, "none"), float(d)
            if light == "none":
                light_d = None
        stop_d = None
        self._stop_junction = None
        for link, d in zip(self._links, self._link_dist):
            if link[5] in ("s", "w"):
                stop_d = float(d)
                if link[4]:  # internal lane ":<junction>_<index>_<lane>"
                    self._stop_junction = link[4][1:].rsplit("_", 2)[0]
                break
            if link[5] not in ("M", "m", "=", "O", "o"):  # a signal first: it governs
                break
        return light, light_d, stop_d

    def _obstacles(self) -> list[expert.Obstacle]:
        ls = self._ls
        pts, s = self._path
        ids, xy, yaw, spd, dims, kerb = [], [], [], [], [], []
        for aid, r in self._context.items():
            if aid == EGO_ID:
                continue
            d = self._dims(aid, r[ls.VAR_TYPE])
            kerb.append(d[3] == "pedestrian" and self._is_kerb(r[ls.VAR_LANE_ID]))
            pose = _box_centre(*r[ls.VAR_POSITION], r[ls.VAR_ANGLE], d[0])
            ids.append(aid)
            xy.append((pose.x_m, pose.y_m))
            yaw.append(pose.yaw_rad)
            spd.append(r[ls.VAR_SPEED])
            dims.append(d)
        out = []
        half_w = 0.5 * EGO_DIMS_M[1]
        if ids:
            xy_a = np.asarray(xy)
            yaw_a = np.asarray(yaw)
            spd_a = np.asarray(spd)
            length = np.array([d[0] for d in dims])
            width = np.array([d[1] for d in dims])
            is_ped = np.array([d[3] == "pedestrian" for d in dims])
            # People on a sidewalk or walking area count only where they will be (entering the
            # road), not where they stand: someone waiting at the kerb is not on the path, and
            # yielding to them would deadlock with SUMO, where they wait for the car.
            kerb_a = np.asarray(kerb)
            in_junction = self._ego_cache[ls.VAR_LANE_ID].startswith(":")
            near = np.hypot(*(xy_a - pts[0]).T) < s[-1] + 15.0
            if near.any():
                k = np.flatnonzero(near)
                # now, and for pedestrians also where they will be in 1 s and 2 s
                horizons = (0.0, 1.0, 2.0)
                for h in horizons:
                    if h == 0.0:
                        sel = k[~kerb_a[k]]
                    elif in_junction:
                        # Inside a junction, never brake for someone still on the kerb: SUMO
                        # granted our passage, and stopping in it invites a crossing car into
                        # our side (one of the three ego collisions in a 160-episode run).
                        sel = k[is_ped[k] & ~kerb_a[k] & (spd_a[k] > 0.2)]
                    else:
                        sel = k[is_ped[k] & (spd_a[k] > 0.2)]
                    if len(sel) == 0:
                        continue
                    p = xy_a[sel] + h * spd_a[sel, None] * np.stack(
                        [np.cos(yaw_a[sel]), np.sin(yaw_a[sel])], 1
                    )
                    along, lat, head = _project(p, pts, s)
                    rel = yaw_a[sel] - head
                    c, sn = np.abs(np.cos(rel)), np.abs(np.sin(rel))
                    across = 0.5 * length[sel] * sn + 0.5 * width[sel] * c
                    ahead = 0.5 * length[sel] * c + 0.5 * width[sel] * sn
                    margin = np.where(is_ped[sel], np.where(kerb_a[sel], 0.0, 0.8), 0.35)
                    hit = (lat - across < half_w + margin) & (along + ahead > 0.0)
                    hit &= along - ahead < s[-1]
                    for j in np.flatnonzero(hit):
                        i = sel[j]
                        gap = float(along[j] - ahead[j])
                        if is_ped[i]:
                            out.append(expert.Obstacle(gap, 0.0, "pedestrian", ids[i]))
                        else:
                            v_along = max(0.0, float(spd_a[i] * np.cos(rel[j])))
                            out.append(expert.Obstacle(gap, v_along, "vehicle", ids[i]))
        leader = ls.vehicle.getLeader(EGO_ID, PATH_LOOKAHEAD_M)
        if leader and leader[0]:
            lid, d = leader
            r = self._context.get(lid)
            v = r[ls.VAR_SPEED] if r else ls.vehicle.getSpeed(lid)
            # SUMO's gap leaves out the ego vType's minGap (1 m); "lead:" marks the lane leader
            out.append(expert.Obstacle(float(d) + 1.0, float(v), "vehicle", "lead:" + lid))
        return out

    def _is_kerb(self, lane_id: str) -> bool:
        """A walking area or a pedestrian-only lane (sidewalk, footpath)."""
        k = self._kerb.get(lane_id)
        if k is None:
            if lane_id.startswith(":"):
                k = re.search(r"_w\d+_\d+$", lane_id) is not None
            else:
                k = lane_id != "" and self._ls.lane.getAllowed(lane_id) == ("pedestrian",)
            self._kerb[lane_id] = k
        return k

    def _dims(self, aid: str, type_id: str) -> tuple[float, float, float, str]:
        d = self._veh_dims.get(type_id)
        if d is None:
            for vid, _c, length, width, height, _sh, cls in VEHICLE_TYPES:
                if vid == type_id:
                    d = (length, width, height, cls)
            if d is None and type_id == "ped":
                d = (*PED_DIMS_M, "pedestrian")
            if d is None:
                d = (*EGO_DIMS_M, "vehicle")
            self._veh_dims[type_id] = d
        return d

    def _expert_input(self) -> expert.ExpertInput:
        ls = self._ls
        r = self._ego_cache
        pts, s = self._path
        lane = self._lane(r[ls.VAR_LANE_ID])
        limit = lane.speed_mps
        limits_ahead = []
        is_internal = r[ls.VAR_LANE_ID].startswith(":")
        for d, lid in self._seg_lanes[1:]:
            if lid.startswith(":"):
                continue
            v = self._lane(lid).speed_mps
            if is_internal:  # inside a junction: the exit lane's limit is the one that counts
                limit, is_internal = v, False
            elif v < limit:
                limits_ahead.append((d, v))
        # curvature at path vertices: turning angle / local segment length
        curv = ()
        if len(pts) >= 3:
            seg = np.diff(pts, axis=0)
            head = np.arctan2(seg[:, 1], seg[:, 0])
            seg_len = np.hypot(seg[:, 0], seg[:, 1])
            dth = np.abs((np.diff(head) + np.pi) % (2 * np.pi) - np.pi)
            k = dth / np.maximum(1.5, 0.5 * (seg_len[:-1] + seg_len[1:]))
            sel = np.flatnonzero(k > expert.MIN_CURVATURE_1PM)
            curv = tuple((float(s[i + 1]), float(k[i])) for i in sel)
        light, light_d, stop_d = self._light, self._light_d, self._stop_d
        # the end of the route binds only when it will not be extended (any more)
        remaining = self._remaining_route()
        route_end = (
            remaining
            if remaining < (PATH_LOOKAHEAD_M if not self.config.reroute else 100.0)
            else None
        )
        self._route_end_m = route_end
        return expert.ExpertInput(
            speed_mps=float(r[ls.VAR_SPEED]),
            speed_limit_mps=float(limit),
            limits_ahead=tuple(limits_ahead),
            curvature_ahead=curv,
            obstacles=tuple(self._obstacles()),
            light=light,
            light_distance_m=light_d,
            stop_distance_m=stop_d,
            stop_done=stop_d is not None and self._stop_done_lane == r[ls.VAR_LANE_ID],
            route_end_m=route_end,
        )

    def _set_route(self, route: list[str] | tuple[str, ...]) -> None:
        """Cache the ego's route and the length of each of its suffixes."""
        self._route = tuple(route)
        lengths = np.array([self._lane(f"{e}_0").length_m for e in self._route])
        self._route_suffix = np.concatenate([np.cumsum(lengths[::-1])[::-1], [0.0]])

    def _remaining_route(self) -> float:
        """Distance from the ego's front to the end of its route, m."""
        ls = self._ls
        r = self._ego_cache
        idx = int(r[ls.VAR_ROUTE_INDEX])
        rest = self._lane(r[ls.VAR_LANE_ID]).length_m - r[ls.VAR_LANEPOSITION]
        return float(rest + self._route_suffix[min(idx + 1, len(self._route))])

    def _maybe_reroute(self) -> None:
        ls = self._ls
        r = self._ego_cache
        if r[ls.VAR_LANE_ID].startswith(":") or self._remaining_route() > 250.0:
            return
        route = list(self._route)
        idx = int(r[ls.VAR_ROUTE_INDEX])
        last = route[-1]
        here = self._drive_xy[self._drive_edges.index(last)]
        dist = np.hypot(*(self._drive_xy - here).T)
        far = np.flatnonzero(dist >= min(400.0, 0.5 * dist.max()))
        for _ in range(10):
            b = (
                int(far[self._rng.integers(len(far))])
                if len(far)
                else int(self._rng.integers(len(self._drive_edges)))
            )
            new = self._find_route(last, self._drive_edges[b], "ego_type")
            if len(new) >= 2:
                ls.vehicle.setRoute(EGO_ID, route[idx:] + list(new[1:]))
                self._set_route(route + list(new[1:]))  # the route index stays valid
                self._stats.reroutes += 1
                return

    def _step(self) -> None:
        ls = self._ls
        st = self._stats
        p = self.profile
        dt = self.config.step_s
        r = self._ego_cache
        v0 = float(r[ls.VAR_SPEED])
        inp = self._expert_input()
        dec = expert.decide(inp, p)
        self._target, reason = dec.target_speed_mps, dec.reason
        ls.vehicle.setSpeed(EGO_ID, dec.target_speed_mps)
        lane0 = r[ls.VAR_LANE_ID]
        first_state = self._links[0][5] if self._links else ""
        ls.simulationStep()
        st.steps += 1
        st.sim_s += dt
        # --- what happened in the step
        for c in ls.simulation.getCollisions():
            pair = (c.collider, c.victim)
            if pair in self._colliding:  # SUMO reports an overlap every step it lasts
                continue
            self._colliding.add(pair)
            if EGO_ID in pair:
                st.collisions += 1
                self._end("collision", f"{c.collider} hit {c.victim} ({c.type}) on {c.lane}")
            else:
                st.other_collisions += 1
        teleported = ls.simulation.getStartingTeleportIDList()
        st.teleports += len(teleported)
        if EGO_ID in teleported:
            self._end("teleported", "SUMO teleported the jammed ego")
            return
        if EGO_ID in ls.simulation.getArrivedIDList():
            self._end("route_end", "the ego reached the end of its route")
            return
        self._read()
        r = self._ego_cache
        v1 = float(r[ls.VAR_SPEED])
        lane1 = r[ls.VAR_LANE_ID]
        if self._route_end_m is not None and self._route_end_m < 5.0 and v1 < expert.STOPPED_MPS:
            self._end("route_end", "the ego stopped at the end of its route")
        if lane1.startswith(":") and not lane0.startswith(":") and first_state in ("r", "u"):
            st.red_light_violations += 1
        if lane1 != lane0 and lane1.startswith(":"):
            self._stop_done_lane = None
        # full stop at a stop-controlled entry: hold it STOP_WAIT_S, then the entry is done
        if (
            self._stop_d is not None
            and self._stop_d < expert.STOP_SIGN_MARGIN_M + 3.0
            and v1 < expert.STOPPED_MPS
        ):
            self._stop_wait_s += dt
            if self._stop_wait_s >= expert.STOP_WAIT_S and self._junction_clear():
                self._stop_done_lane = lane1
        else:
            self._stop_wait_s = 0.0
        # did SUMO hold the ego below the expert's command?
        v_exp = min(self._target, v0 + p.ego_accel_mps2 * dt)
        v_exp = max(v_exp, v0 - EGO_DECEL_SLACK * p.ego_comfort_decel_mps2 * dt)
        if v1 < v_exp - 0.1 and reason not in ("red_light", "stop_sign", "route_end"):
            reason = self._attribute_hold()
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
        if v1 < expert.STOPPED_MPS and self._light != "red":
            self._standing_s += dt
            if self._standing_s >= BLOCKED_S:
                self._end("blocked", f"ego stood {BLOCKED_S:.0f} s on {lane1}")
        else:
            self._standing_s = 0.0
        if st.steps % 10 == 0:
            if self.config.reroute:
                self._maybe_reroute()
            self._manage_bubble(st.steps % 50 == 0)

    def _junction_clear(self) -> bool:
        """No other vehicle is inside the stop-controlled junction ahead (on its internal
        lanes); people on its crossings are left to the pedestrian rule and SUMO."""
        if self._stop_junction is None:
            return True
        prefix = f":{self._stop_junction}_"
        ls = self._ls
        for aid, r in self._context.items():
            lane = r[ls.VAR_LANE_ID]
            if aid != EGO_ID and lane.startswith(prefix) and not self._is_kerb(lane):
                if re.search(r"_c\d+_\d+$", lane) is None:  # not a crossing
                    return False
        return True

    def _attribute_hold(self) -> str:
        """Name what SUMO's safety model yields to when it holds the ego below the command."""
        if self._stop_d is not None and self._stop_d < 10.0:
            return "stop_sign"
        pts, s = self._path
        peds = [r[self._ls.VAR_POSITION] for aid, r in self._context.items() if aid.startswith("p")]
        if peds:
            along, lat, _ = _project(np.asarray(peds, dtype=np.float64), pts, s)
            if np.any((lat < 5.0) & (along > -2.0) & (along < 50.0)):
                return "pedestrian"
        in_junction = self._ego_cache[self._ls.VAR_LANE_ID].startswith(":")
        if in_junction or (self._link_dist and self._link_dist[0] < 50.0):
            return "junction"
        return "vehicle"

    def _manage_bubble(self, remove: bool) -> None:
        ls = self._ls
        ego_xy = self._ego_cache[ls.VAR_POSITION]
        vids = [v for v in ls.vehicle.getIDList() if v != EGO_ID]
        pids = ls.person.getIDList()
        if remove:
            for v in vids:
                x, y = ls.vehicle.getPosition(v)
                if math.hypot(x - ego_xy[0], y - ego_xy[1]) > VEH_REMOVE_M:
                    ls.vehicle.remove(v)
            for pid in pids:
                x, y = ls.person.getPosition(pid)
                if math.hypot(x - ego_xy[0], y - ego_xy[1]) > PED_REMOVE_M:
                    ls.person.remove(pid)
            vids = [v for v in ls.vehicle.getIDList() if v != EGO_ID]
            pids = ls.person.getIDList()
        pending = ls.simulation.getMinExpectedNumber() - len(vids) - len(pids) - 1
        need_v = self._n_veh - len(vids) - max(0, pending)
        if need_v > 0:
            self._spawn_vehicles(ego_xy, min(need_v, 4), *VEH_SPAWN_M)
        need_p = self._n_ped - len(pids)
        if need_p > 0:
            self._spawn_pedestrians(ego_xy, min(need_p, 4), *PED_SPAWN_M)

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

    def advance(self, dt_s: float) -> None:
        """Run the simulation `dt_s` seconds (whole steps) with the expert in control."""
        if self.ended is not None:
            return
        t0 = time.perf_counter()
        for _ in range(max(1, int(round(dt_s / self.config.step_s)))):
            self._step()
            if self.ended is not None:
                break
        self._stats.wall_s += time.perf_counter() - t0

    @property
    def time_s(self) -> float:
        return float(self._ls.simulation.getTime())

    def state(self) -> FrameState:
        """Ground truth now (world frame, box centres): see datagen/state.py."""
        ls = self._ls
        r = self._ego_cache
        el, ew, eh = EGO_DIMS_M
        ego_pose = _box_centre(*r[ls.VAR_POSITION], r[ls.VAR_ANGLE], el)
        ego = AgentState(EGO_ID, "vehicle", ego_pose, el, ew, eh, float(r[ls.VAR_SPEED]))
        agents = []
        ex, ey = r[ls.VAR_POSITION]
        for aid in sorted(self._context):
            if aid == EGO_ID:
                continue
            a = self._context[aid]
            x, y = a[ls.VAR_POSITION]
            if math.hypot(x - ex, y - ey) > AGENT_RADIUS_M:
                continue
            length, width, height, cls = self._dims(aid, a[ls.VAR_TYPE])
            pose = _box_centre(x, y, a[ls.VAR_ANGLE], length)
            agents.append(AgentState(aid, cls, pose, length, width, height, float(a[ls.VAR_SPEED])))
        command, target = self._command_and_target()
        light, light_d = self._light, self._light_d
        if light_d is None or light_d > SIGNAL_RANGE_M:
            light, light_d = "none", None
        stop_d = (
            self._stop_d if self._stop_d is not None and self._stop_d <= SIGNAL_RANGE_M else None
        )
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
        )

    def _junction_has_choice(self, from_lane: str) -> bool:
        """True if the edge of `from_lane` leads to two or more drivable edges (a real
        intersection, where a turn command means something)."""
        edge = from_lane.rsplit("_", 1)[0]
        has = self._edge_choice.get(edge)
        if has is None:
            ls = self._ls
            outs = set()
            for k in range(ls.edge.getLaneNumber(edge)):
                for link in ls.lane.getLinks(f"{edge}_{k}"):
                    if link[6] != "t" and "passenger" in ls.lane.getAllowed(link[0]):
                        outs.add(link[0].rsplit("_", 1)[0])
            has = len(outs) >= 2
            self._edge_choice[edge] = has
        return has

    def _command_and_target(self) -> tuple[str, tuple[float, float]]:
        ls = self._ls
        lane_id = self._ego_cache[ls.VAR_LANE_ID]
        pts, s = self._path
        if lane_id.startswith(":"):
            if self._cmd_sticky is not None:
                _j, cmd, exit_lane = self._cmd_sticky
                return cmd, self._exit_point(exit_lane)
        else:
            self._cmd_sticky = None
            from_lane = lane_id
            for link, d in zip(self._links, self._link_dist):
                if d > COMMAND_RANGE_M:
                    break
                if not link[4]:  # no internal lane: not a junction we drive through
                    from_lane = link[0]
                    continue
                if self._junction_has_choice(from_lane):
                    cmd = _COMMAND.get(link[6], "straight")
                    junction = link[4][1:].rsplit("_", 2)[0]
                    self._cmd_sticky = (junction, cmd, link[0])
                    return cmd, self._exit_point(link[0])
                from_lane = link[0]
        i = int(np.searchsorted(s, TARGET_AHEAD_M))
        if i >= len(s):
            tp = pts[-1]
        else:
            f = (TARGET_AHEAD_M - s[i - 1]) / max(s[i] - s[i - 1], 1e-9)
            tp = pts[i - 1] + f * (pts[i] - pts[i - 1])
        return "follow", (float(tp[0]), float(tp[1]))

    def _exit_point(self, lane_id: str) -> tuple[float, float]:
        lane = self._lane(lane_id)
        pts = self._cut(lane, min(EXIT_INTO_M, 0.5 * lane.length_m))
        return float(pts[0, 0]), float(pts[0, 1])

    @property
    def stats(self) -> dict:
        """Episode statistics: collisions (of the ego; other_collisions between other road
        users, each pair once), red_light_violations (ego entered a junction on red),
        teleports (all vehicles), hard_brakes (steps braking harder than any command: SUMO's
        safety braking), mean_speed_mps, mean_time_gap_s and median_time_gap_s (bumper gap /
        speed while steadily following a lead, None if never), sim/wall seconds, steps per expert reason, and how
        the episode ended."""
        st = self._stats
        return {
            "steps": st.steps,
            "sim_s": round(st.sim_s, 3),
            "wall_s": round(st.wall_s, 3),
            "collisions": st.collisions,
            "other_collisions": st.other_collisions,
            "red_light_violations": st.red_light_violations,
            "teleports": st.teleports,
            "hard_brakes": st.hard_brakes,
            "reroutes": st.reroutes,
            "distance_m": round(st.distance_m, 1),
            "mean_speed_mps": st.speed_sum / st.steps if st.steps else 0.0,
            "mean_time_gap_s": float(np.mean(st.gaps_s)) if st.gaps_s else None,
            "median_time_gap_s": float(np.median(st.gaps_s)) if st.gaps_s else None,
            "following_s": round(len(st.gaps_s) * self.config.step_s, 1),
            "n_vehicles": self._n_veh,
            "n_pedestrians": self._n_ped,
            "reasons": dict(sorted(st.reasons.items())),
            "ended": self.ended,
            "end_detail": self.end_detail,
        }

    def close(self) -> None:
        """Stop SUMO (idempotent; safe after a failed start)."""
        global _open_world
        if self._started:
            try:
                self._ls.close()
            except Exception:  # noqa: BLE001  (closing a broken simulation must not mask the cause)
                pass
            self._started = False
        if _open_world is self:
            _open_world = None
        shutil.rmtree(self._tmp, ignore_errors=True)

    def __enter__(self) -> World:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        if getattr(self, "_started", False):
            self.close()


def record(world: World, n_frames: int, period_s: float = 0.5) -> Iterator[FrameState]:
    """Yield `world.state()` now and every `period_s` (2 Hz by default) until `n_frames` states
    have been yielded or the world ends (then `world.ended` says why)."""
    for k in range(n_frames):
        if k:
            world.advance(period_s)
        if world.ended is not None:
            return
        yield world.state()
