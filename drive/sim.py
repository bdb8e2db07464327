"""The world of one route, driven by the expert or by an external controller (drive/eval).

A thin adapter over the world's seam for who drives the ego (`datagen.world`,
WorldConfig.ego_driver): the route's edges are the ego's route (never extended), its seed,
weather and behaviour are the world's. Externally driven, the ego is placed every step where the
controller put it (`World.step(EgoCommand)`: moveToXY anywhere, off its lane or the road too,
its speed known to SUMO, its SUMO route kept on the plan so others give way at junctions).
"""

from __future__ import annotations

from pathlib import Path

from datagen.state import FrameState, Pose
from drive.routes import Route


class DrivenWorld:
    """Context manager: `state()`, `truth()`, `place_ego(pose, speed)` (external only),
    `step()`."""

    def __init__(self, net_path: Path, route: Route, external: bool, **options):
        from datagen.world import World, WorldConfig

        self.external = external
        self._command = None
        self._world = World(
            WorldConfig(
                net_path=Path(net_path),
                seed=route.seed,
                weather=route.weather,
                behaviour=route.behaviour,
                reroute=False,
                ego_route=tuple(route.edges),
                ego_driver="external" if external else "expert",
                **options,
            )
        )

    @property
    def ended(self) -> str | None:
        return self._world.ended

    @property
    def end_detail(self) -> str:
        return self._world.end_detail

    def state(self) -> FrameState:
        return self._world.state()

    def truth(self):
        """datagen.world.EgoTruth after the last step."""
        return self._world.truth()

    def place_ego(self, pose: Pose, speed_mps: float) -> None:
        """Where the ego is at the end of the next step (world frame, box centre)."""
        from datagen.world import EgoCommand

        self._command = EgoCommand(pose, speed_mps)

    def step(self) -> None:
        if self.external:
            if self._command is None:  # before the first plan: stand still
                ego = self._world.state().ego
                self.place_ego(ego.pose, 0.0)
            self._world.step(self._command)
        else:
            self._world.step()

    def close(self) -> None:
        self._world.close()

    def __enter__(self) -> DrivenWorld:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
