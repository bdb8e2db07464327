"""The ego driven by an external controller (WorldConfig.ego_driver "external"; drive eval).

The controller computes the ego's next pose and speed with its own kinematic model and hands
them over every 0.1 s step as an `EgoCommand`. The step puts the ego there (sumo.place_ego:
moveToXY with keepRoute=2, anywhere, off its lane or the road too), sets its speed (speed
mode 0, so other drivers see the speed it really has), keeps its SUMO route on the planned
route so other vehicles give way to it at junctions (sumo#6140), and moves the traffic bubble
with it. Nothing ends an externally driven episode but SUMO removing the ego; SUMO's ego
collisions (incomplete for a placed vehicle, sumo#6327) and red-light entries are recorded for
World.truth() and left to the caller to score.
"""

from __future__ import annotations

from dataclasses import dataclass

from datagen.state import Pose
from datagen.world.fleet import EGO_ID
from datagen.world.simulation import Simulation
from datagen.world.sumo import Snapshot


@dataclass(frozen=True)
class EgoCommand:
    """Where an external controller puts the ego at the end of the next step (world frame).

    Attributes:
        pose: box centre (x_m, y_m), metres, and yaw_rad, counter-clockwise from east.
        speed_mps: speed along the yaw, m/s; SUMO's other drivers react to it.
    """

    pose: Pose
    speed_mps: float


class ExternalDriver:
    """Steps `sim` with the ego placed where each EgoCommand says."""

    def __init__(self, sim: Simulation):
        self._sim = sim

    def step(self, command: EgoCommand) -> None:
        """One step with the ego placed at `command` (see the module docstring)."""
        sim = self._sim
        st = sim.stats
        dt = sim.config.step_s
        before = sim.snap
        lane0 = before.ego.lane_id
        first_state = before.links[0].state if before.links else ""
        sim.sumo.place_ego(command.pose, command.speed_mps)
        events, _ = sim.step_sumo()  # the ego's collisions are scored by the caller: drive on
        if EGO_ID in events.teleported or EGO_ID in events.arrived:
            sim.end("route_end", "SUMO took the placed ego out of the simulation")
            return
        snap = sim.sumo.snapshot()
        if self._keep_route(snap):
            snap = sim.sumo.snapshot()  # links and signals along the restored route
        sim.snap = snap
        lane1 = snap.ego.lane_id
        sim.rules.note_red_light(lane0, lane1, first_state)
        if lane1:
            sim.rules.note_stop(lane0, snap, sim.signals)
        sim.reason = "none"
        st.distance_m += snap.ego.speed_mps * dt
        st.speed_sum += snap.ego.speed_mps
        if lane1:  # off the network: path and signals stay the last ones on it
            sim.sense()
        else:
            sim.on_plan = False
        sim.manage(reroute=sim.config.reroute and sim.on_plan and bool(lane1))

    def _keep_route(self, snap: Snapshot) -> bool:
        """Keep SUMO's route of a placed ego on the planned route, so that other drivers
        respect it at junctions (sumo#6140): moveToXY(keepRoute=2) replaces the route by the
        edge it maps the ego to when that edge is off the route (inside a junction: by the
        passage of the nearest internal lane). On a planned edge again, the rest of the plan is
        set back. True if the route was set."""
        sim = self._sim
        road = snap.ego.road_id
        if not road or road.startswith(":"):
            return False  # off the network or inside a junction: as it was
        try:
            i = sim.route.index(road, sim.placed_index)
        except ValueError:
            sim.on_plan = False  # off the route (e.g. the opposite lane): nothing to restore
            return False
        sim.placed_index, sim.on_plan = i, True
        if sim.sumo.ego_route()[snap.ego.route_index :] == sim.route[i:]:
            return False
        try:
            sim.sumo.set_ego_route(sim.route[i:])
        except sim.sumo.TraCIException:
            # SUMO's own current edge may differ from the snapshot's (seen with a placed ego
            # on the opposite direction's edge): keep its route this step, try again next one
            return False
        return True
