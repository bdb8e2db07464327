"""The running SUMO episode around the ego, whoever drives it: what both drivers (the expert's
step in world.py, an external controller's in external.py), the expert's plan (planning.py)
and World's views share.

A `Simulation` starts SUMO (sumo.py), chooses the ego's route, fills the traffic bubble around
its start (traffic.py), runs the warm-up and inserts the ego. It then holds the latest snapshot
with the path and signals ahead read from it (route.py), the ego's planned route and where the
ego is on it, its record against the rules (rules.py), the episode's counters and how the
episode ended. A driver's step is `step_sumo()` (one SUMO step, its collisions and teleports
counted), its own reading of the new snapshot, `sense()`, and `manage()` every step.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import datagen.world.perception as perception
import datagen.world.route as route
from datagen.world.behaviour import Profile
from datagen.world.config import WorldConfig
from datagen.world.fleet import EGO_ID
from datagen.world.rules import RuleBook
from datagen.world.sumo import Collision, Snapshot, StepEvents, Sumo
from datagen.world.traffic import Traffic

AGENT_RADIUS_M = 100.0  # agents within this distance of the ego are in FrameState.agents

_log = logging.getLogger(__name__)


@dataclass
class Stats:
    """The episode's counters, summed over its steps (World.stats reports them).

    Attributes:
        steps, sim_s, wall_s: SUMO steps, simulated and wall-clock seconds.
        collisions, other_collisions: of the ego, and between other road users (each pair once).
        teleports: vehicles SUMO teleported (all of them).
        hard_brakes: steps the expert ego braked harder than any command (SUMO's safety).
        reroutes: extensions of the ego's route.
        distance_m, speed_sum: the ego's distance driven, m, and the sum of its speeds, m/s.
        gaps_s: the expert's time gaps while steadily following a lead, s.
        reasons: steps per expert reason.
    """

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


class Simulation:
    """One started episode: SUMO, the traffic around the ego, and the ego's state between steps.

    Attributes:
        config, profile: the WorldConfig and its behaviour profile.
        sumo: the libsumo session; net: its network; traffic: the bubble around the ego.
        stats: the episode's counters.
        rules: the ego's record against stop signs and red lights.
        snap: the latest sumo.Snapshot; path, signals: the route ahead and its signals read
            from it (`sense`; a driver may keep the last ones on the network).
        route: the ego's planned route (edge ids); plan: its sparse route plan
            (config.target_point "sparse", else ()).
        placed_index, on_plan: an externally placed ego's edge index in `route`, and whether
            SUMO's route of it is the planned one (from there on).
        reason: the rule binding the expert's speed in the last step ("none" for a placed ego).
        ego_collisions: SUMO's collisions involving the ego in the last step ((collider,
            victim, kind)).
        ended: None while running, else why it ended; end_detail: a sentence saying what.
    """

    def __init__(self, config: WorldConfig, profile: Profile):
        """Start SUMO and insert the ego (SUMO is closed again if that fails)."""
        self.config = config
        self.profile = profile
        self.ended: str | None = None
        self.end_detail: str = ""
        self.stats = Stats()
        self.reason = "none"
        self.plan: tuple[route.PlanPoint, ...] = ()
        self.placed_index = 0
        self.on_plan = True
        self.ego_collisions: tuple[tuple[str, str, str], ...] = ()
        self._rng = np.random.default_rng(config.seed)
        self._kerb: dict[str, bool] = {}
        self._colliding: set[tuple[str, str]] = set()
        self.sumo = Sumo(config.net_path, profile, config.step_s, config.seed)
        try:
            self.net = self.sumo.net
            self.rules = RuleBook(self.net, config.step_s, self.is_kerb)
            roads = self.sumo.roads(config.net_path)
            self.traffic = Traffic(self.sumo, roads, self._rng, config.net_path)
            self._populate()
            self._insert_ego()
        except BaseException:
            self.sumo.close()
            raise

    # ------------------------------------------------------------------ setup

    def _populate(self) -> None:
        """Choose the ego's route, fill the bubble around its start, run the warm-up."""
        if self.config.ego_route:
            self._ego_route = list(self.config.ego_route)
        else:
            self._ego_route = self.traffic.pick_ego_route()
        start = self.traffic.edge_mid(self._ego_route[0])
        self.traffic.populate(
            self.profile, start, self.config.n_vehicles, self.config.n_pedestrians
        )
        for _ in range(int(round(self.config.warmup_s / self.config.step_s))):
            self.sumo.step()

    def _insert_ego(self) -> None:
        fixed = bool(self.config.ego_route)
        for attempt in range(1 if fixed else 5):
            if attempt:
                self._ego_route = self.traffic.pick_ego_route()
            if self.sumo.insert_ego(tuple(self._ego_route), attempt, at_start=fixed):
                break
        else:
            raise RuntimeError("could not insert the ego vehicle")
        self.sumo.subscribe_ego(AGENT_RADIUS_M)
        self.sumo.step()
        self.set_route(self.sumo.ego_route())
        if self.config.ego_driver == "external":
            self.sumo.take_over_ego()
        self.snap: Snapshot = self.sumo.snapshot()
        self.sense()

    # ------------------------------------------------------------------ per step

    def is_kerb(self, lane_id: str) -> bool:
        """perception.is_kerb of a lane of this network (memoised)."""
        k = self._kerb.get(lane_id)
        if k is None:
            plain = lane_id != "" and not lane_id.startswith(":")
            k = perception.is_kerb(lane_id, self.net.allowed(lane_id) if plain else None)
            self._kerb[lane_id] = k
        return k

    def sense(self) -> None:
        """Path ahead and signals from the latest snapshot."""
        ego = self.snap.ego
        self.path: route.Path = route.path_ahead(
            self.net, ego.lane_id, ego.lane_pos_m, self.snap.links, ego.front_xy_m, ego.yaw_rad
        )
        self.signals: route.Signals = route.signals(
            self.snap.next_signals, self.snap.links, self.path.link_dist
        )

    def step_sumo(self) -> tuple[StepEvents, list[Collision]]:
        """One SUMO step, counted with its collisions and teleports: its events and the ego's
        new collisions."""
        self.sumo.step()
        st = self.stats
        st.steps += 1
        st.sim_s += self.config.step_s
        events = self.sumo.events()
        mine = self._new_collisions(events)
        st.teleports += len(events.teleported)
        return events, mine

    def _new_collisions(self, events: StepEvents) -> list[Collision]:
        """Count the step's collisions (each pair once: SUMO reports an overlap every step it
        lasts) and return the ego's new ones."""
        st = self.stats
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
        self.ego_collisions = tuple((c.collider, c.victim, c.kind) for c in mine)
        return mine

    def manage(self, reroute: bool) -> None:
        """Every 10th step: extend the ego's route if `reroute` and it nears its end, and keep
        the traffic bubble around the ego (traffic.py)."""
        st = self.stats
        if st.steps % 10 == 0:
            if reroute:
                self._maybe_reroute()
            self.traffic.manage(self.snap.ego.front_xy_m, st.steps % 50 == 0)

    # ------------------------------------------------------------------ the route

    def set_route(self, edges: list[str] | tuple[str, ...]) -> None:
        """Cache the ego's route and the length of each of its suffixes."""
        self.route = tuple(edges)
        self._route_suffix = route.route_suffix_m(self.net, self.route)
        if self.config.target_point == "sparse":  # an extension keeps the plan's prefix
            self.plan = route.sparse_plan(self.net, self.route)

    def remaining_route(self) -> float:
        """Distance from the ego's front to the end of its route, m."""
        ego = self.snap.ego
        return route.remaining_route_m(
            self.net,
            self._route_suffix,
            ego.lane_id,
            ego.lane_pos_m,
            self.route_index(),
        )

    def route_index(self) -> int:
        """Index in self.route of the ego's edge. The expert's SUMO route is self.route (a
        reroute keeps the passed edges); a placed ego's SUMO route may not be."""
        return (
            self.snap.ego.route_index if self.config.ego_driver == "expert" else self.placed_index
        )

    def _maybe_reroute(self) -> None:
        ego = self.snap.ego
        if ego.lane_id.startswith(":") or self.remaining_route() > 250.0:
            return
        edges = list(self.route)
        new = self.traffic.extension(edges[-1])
        if new:
            idx = self.route_index()
            self.sumo.set_ego_route(edges[idx:] + list(new[1:]))
            self.set_route(edges + list(new[1:]))  # the route index stays valid
            self.stats.reroutes += 1

    # ------------------------------------------------------------------ the end

    def end(self, why: str, detail: str) -> None:
        """End the episode (the first reason given stays)."""
        if self.ended is None:
            self.ended = why
            self.end_detail = detail
            log = _log.info if why == "route_end" else _log.warning
            log(
                "episode %s (seed %d) ended at %.1f s: %s (%s)",
                Path(self.config.net_path).name,
                self.config.seed,
                self.stats.sim_s,
                why,
                detail,
            )

    def close(self) -> None:
        """Stop SUMO (idempotent)."""
        self.sumo.close()
