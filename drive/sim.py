"""The world of one route, driven by the expert or by an external controller (drive/eval).

A thin adapter over `datagen.world.World`: the route's edges are the ego's route (never
extended), its seed, weather and behaviour are the world's. With `external=True` the ego is
placed every step where the controller put it: moveToXY with keepRoute 3 (bit 1: the exact
position, off its lane or the road too; bit 0: mapped onto its route's lanes, so its route,
and with it right of way at junctions and the signal ahead, stays known to SUMO,
eclipse-sumo/sumo#6140), its speed set so that followers react to it, SUMO's own speed and
lane-change control off.

TEMPORARY: until the world's own seam for who drives the ego lands (the world split), external
control is a subclass reaching into World's step internals; only this module changes then.
"""

from __future__ import annotations

import math
from pathlib import Path

from datagen.state import FrameState, Pose
from drive.routes import Route

KEEP_ROUTE = 3  # moveToXY: exact position (2) + mapped onto the route's edges (1)


def _external_world_class():
    from datagen.world import EGO_DIMS_M, EGO_ID, World

    class ExternalWorld(World):
        """World whose ego is placed by the caller each step (no expert)."""

        _pending: tuple[Pose, float] | None = None

        def take_over(self) -> None:
            ls = self._ls
            ls.vehicle.setSpeedMode(EGO_ID, 0)
            ls.vehicle.setLaneChangeMode(EGO_ID, 0)

        def place(self, pose: Pose, speed_mps: float) -> None:
            self._pending = (pose, speed_mps)

        def _step(self) -> None:
            ls = self._ls
            st = self._stats
            if self._pending is not None:
                pose, v = self._pending
                half = 0.5 * EGO_DIMS_M[0]  # SUMO places the front bumper
                x = pose.x_m + half * math.cos(pose.yaw_rad)
                y = pose.y_m + half * math.sin(pose.yaw_rad)
                angle = (90.0 - math.degrees(pose.yaw_rad)) % 360.0
                ls.vehicle.moveToXY(EGO_ID, "", -1, x, y, angle, KEEP_ROUTE)
                ls.vehicle.setSpeed(EGO_ID, max(0.0, v))
            ls.simulationStep()
            st.steps += 1
            st.sim_s += self.config.step_s
            st.teleports += len(ls.simulation.getStartingTeleportIDList())
            if EGO_ID in ls.simulation.getArrivedIDList():
                self._end("route_end", "the ego left the end of its route")
                return
            self._read()
            lane = self._ego_cache.get(ls.VAR_LANE_ID, "")
            if lane:  # off every lane SUMO keeps the last signals and path ahead
                try:
                    self._sense()
                except ls.TraCIException:
                    pass
            self._reason = "none"
            if st.steps % 10 == 0:
                self._manage_bubble(st.steps % 50 == 0)

    return ExternalWorld


class DrivenWorld:
    """Context manager: `state()`, `place_ego(pose, speed)` (external only), `step()`."""

    def __init__(self, net_path: Path, route: Route, external: bool, **options):
        from datagen.world import World, WorldConfig

        self.external = external
        cls = _external_world_class() if external else World
        self._world = cls(
            WorldConfig(
                net_path=Path(net_path),
                seed=route.seed,
                weather=route.weather,
                behaviour=route.behaviour,
                reroute=False,
                ego_route=tuple(route.edges),
                **options,
            )
        )
        if external:
            self._world.take_over()

    @property
    def ended(self) -> str | None:
        return self._world.ended

    @property
    def end_detail(self) -> str:
        return self._world.end_detail

    def state(self) -> FrameState:
        return self._world.state()

    def place_ego(self, pose: Pose, speed_mps: float) -> None:
        self._world.place(pose, speed_mps)

    def step(self) -> None:
        self._world.advance(0.1)

    def close(self) -> None:
        self._world.close()

    def __enter__(self) -> DrivenWorld:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
