"""The population around the ego: its random route, background vehicles and pedestrians in a
bubble that moves with it (world frame, metres).

Background vehicles (random routes, the profile's vType parameters) and pedestrians (walks
between random sidewalk edges, across crossings) are spawned at VEH_SPAWN_M / PED_SPAWN_M from
the ego and removed beyond VEH_REMOVE_M / PED_REMOVE_M, so the cost per step does not grow with
the town. Every random choice draws from the one `numpy.random.Generator` of the world, in a
fixed order (same seed, same traffic).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from datagen.errors import UserError
from datagen.world.behaviour import Profile
from datagen.world.fleet import VEHICLE_TYPES
from datagen.world.sumo import EGO_TYPE, Roads, Sumo

# Vehicle bubble around the ego (m): spawn ring and removal radius.
VEH_SPAWN_M = (60.0, 300.0)
VEH_REMOVE_M = 400.0
PED_SPAWN_M = (40.0, 200.0)
PED_REMOVE_M = 260.0


def edges_near(xy: np.ndarray, lens: np.ndarray, centre, r0: float, r1: float) -> np.ndarray:
    """Indices of edges longer than 5 m whose middle `xy` (E, 2) lies r0..r1 m from centre and
    no part of which (half its length around the middle) comes closer than r0: a vehicle
    spawned anywhere on a long edge starting at the ego appeared 3 m in front of it
    (boulevard-long-04, "v176", drive eval of issue 38)."""
    if len(xy) == 0:
        return np.zeros(0, dtype=int)
    dist = np.hypot(xy[:, 0] - centre[0], xy[:, 1] - centre[1])
    near = dist - 0.5 * lens if r0 > 0.0 else dist
    return np.flatnonzero((near >= r0) & (dist <= r1) & (lens > 5.0))


def lane_km_near(roads: Roads, centre, radius: float) -> tuple[float, float]:
    """(car lane-km, sidewalk-km) of edges whose middle lies within `radius` of centre."""
    idx = edges_near(roads.drive_xy, roads.drive_len, centre, 0.0, radius)
    lane_km = float((roads.drive_len[idx] * roads.drive_lanes[idx]).sum()) / 1000.0
    idx = edges_near(roads.walk_xy, roads.walk_len, centre, 0.0, radius)
    walk_km = float(roads.walk_len[idx].sum()) / 1000.0
    return lane_km, walk_km


def bubble_size(
    p: Profile, lane_km: float, walk_km: float, n_vehicles: int | None, n_pedestrians: int | None
) -> tuple[int, int]:
    """(vehicles, pedestrians) to keep around the ego: the given numbers, else the profile's
    densities x lane-km (5..150) and x sidewalk-km (0..100)."""
    nv = (
        int(np.clip(round(p.traffic_density * lane_km), 5, 150))
        if n_vehicles is None
        else n_vehicles
    )
    npd = n_pedestrians
    if npd is None:
        npd = int(np.clip(round(p.pedestrian_density * walk_km), 0, 100)) if walk_km else 0
    return nv, npd


class Traffic:
    """Spawns and removes road users around the ego through `sumo` (see module docstring)."""

    def __init__(self, sumo: Sumo, roads: Roads, rng: np.random.Generator, net_path: Path):
        self.sumo = sumo
        self.roads = roads
        self.rng = rng
        self.net_path = net_path
        self.n_veh = 0
        self.n_ped = 0
        self.n_spawned = 0

    def edge_mid(self, edge: str) -> np.ndarray:
        """(2,) middle of a drivable edge's lane 0, m."""
        return self.roads.drive_xy[self.roads.drive_edges.index(edge)]

    def pick_ego_route(self) -> list[str]:
        """A random route of >= 3 edges (else the longest found) between far-apart edges."""
        r_ = self.roads
        n = len(r_.drive_edges)
        cand = np.flatnonzero(r_.drive_len >= 30.0)
        if len(cand) == 0:
            cand = np.arange(n)
        best: list[str] = []
        for _ in range(60):
            a = int(cand[self.rng.integers(len(cand))])
            dist = np.hypot(*(r_.drive_xy - r_.drive_xy[a]).T)
            far = np.flatnonzero(dist >= min(600.0, 0.5 * dist.max()))
            b = int(far[self.rng.integers(len(far))]) if len(far) else int(self.rng.integers(n))
            if a == b:
                continue
            r = self.sumo.find_route(r_.drive_edges[a], r_.drive_edges[b], EGO_TYPE)
            if len(r) >= 3:
                return list(r)
            if len(r) > len(best):
                best = list(r)
        if best:
            return best
        raise UserError(f"{self.net_path}: found no route for a passenger car")

    def extension(self, last_edge: str) -> tuple[str, ...]:
        """A fastest route from `last_edge` to a random far-away edge (10 tries), () if none."""
        r_ = self.roads
        here = self.edge_mid(last_edge)
        dist = np.hypot(*(r_.drive_xy - here).T)
        far = np.flatnonzero(dist >= min(400.0, 0.5 * dist.max()))
        for _ in range(10):
            b = (
                int(far[self.rng.integers(len(far))])
                if len(far)
                else int(self.rng.integers(len(r_.drive_edges)))
            )
            new = self.sumo.find_route(last_edge, r_.drive_edges[b], EGO_TYPE)
            if len(new) >= 2:
                return new
        return ()

    def populate(
        self, p: Profile, start, n_vehicles: int | None, n_pedestrians: int | None
    ) -> None:
        """Size the bubble at `start` (2,) and fill it."""
        lane_km, walk_km = lane_km_near(self.roads, start, VEH_SPAWN_M[1])
        nv, npd = bubble_size(p, lane_km, walk_km, n_vehicles, n_pedestrians)
        self.n_veh = nv
        self.n_ped = npd if self.roads.walk_edges else 0
        self.spawn_vehicles(start, self.n_veh, r0=0.0, r1=VEH_SPAWN_M[1])
        self.spawn_pedestrians(start, self.n_ped, r0=0.0, r1=PED_SPAWN_M[1])

    def spawn_vehicles(self, centre, k: int, r0: float, r1: float) -> None:
        r_ = self.roads
        idx = edges_near(r_.drive_xy, r_.drive_len, centre, r0, r1)
        if len(idx) == 0 or k <= 0:
            return
        w = r_.drive_len[idx] / r_.drive_len[idx].sum()
        shares = np.array([t[5] for t in VEHICLE_TYPES])
        for _ in range(k):
            vt = VEHICLE_TYPES[int(self.rng.choice(len(VEHICLE_TYPES), p=shares / shares.sum()))]
            for _try in range(4):
                a = int(idx[self.rng.choice(len(idx), p=w)])
                b = int(self.rng.integers(len(r_.drive_edges)))
                if a == b:
                    continue
                r = self.sumo.find_route(r_.drive_edges[a], r_.drive_edges[b], vt[0])
                if len(r) < 2:
                    continue
                vid = f"v{self.n_spawned}"
                self.n_spawned += 1
                self.sumo.add_vehicle(vid, r, vt[0])
                break

    def spawn_pedestrians(self, centre, k: int, r0: float, r1: float) -> None:
        r_ = self.roads
        idx = edges_near(r_.walk_xy, r_.walk_len, centre, r0, r1)
        if len(idx) == 0 or k <= 0:
            return
        w = r_.walk_len[idx] / r_.walk_len[idx].sum()
        for _ in range(k):
            for _try in range(4):
                a = int(idx[self.rng.choice(len(idx), p=w)])
                dist = np.hypot(*(r_.walk_xy - r_.walk_xy[a]).T)
                dest = np.flatnonzero((dist > 60.0) & (dist < 400.0))
                if len(dest) == 0:
                    continue
                b = int(dest[self.rng.integers(len(dest))])
                ea, eb = r_.walk_edges[a], r_.walk_edges[b]
                stages = self.sumo.find_walk(ea, eb)
                if not stages:
                    continue
                pid = f"p{self.n_spawned}"
                self.n_spawned += 1
                pos = float(self.rng.uniform(0.0, max(0.1, r_.walk_len[a] - 0.1)))
                self.sumo.add_person(pid, ea, pos, stages)
                break

    def manage(self, ego_xy, remove: bool) -> None:
        """Remove road users far from the ego (if `remove`), top the bubble up (<= 4 each)."""
        sumo = self.sumo
        vids = sumo.vehicle_ids()
        pids = sumo.person_ids()
        if remove:
            for v in vids:
                x, y = sumo.vehicle_xy(v)
                if math.hypot(x - ego_xy[0], y - ego_xy[1]) > VEH_REMOVE_M:
                    sumo.remove_vehicle(v)
            for pid in pids:
                x, y = sumo.person_xy(pid)
                if math.hypot(x - ego_xy[0], y - ego_xy[1]) > PED_REMOVE_M:
                    sumo.remove_person(pid)
            vids = sumo.vehicle_ids()
            pids = sumo.person_ids()
        pending = sumo.pending() - len(vids) - len(pids) - 1
        need_v = self.n_veh - len(vids) - max(0, pending)
        if need_v > 0:
            self.spawn_vehicles(ego_xy, min(need_v, 4), *VEH_SPAWN_M)
        need_p = self.n_ped - len(pids)
        if need_p > 0:
            self.spawn_pedestrians(ego_xy, min(need_p, 4), *PED_SPAWN_M)
