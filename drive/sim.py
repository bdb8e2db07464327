"""The world of one route, driven by the expert or by an external controller (drive/eval).

A thin adapter over `datagen.world.World`: the route's edges are the ego's route (never
extended), its seed, weather and behaviour are the world's. With `external=True` the ego is
placed every step where the controller put it (the world's seam for who drives the ego).
"""

from __future__ import annotations

from pathlib import Path

from datagen.state import FrameState, Pose
from drive.routes import Route


class DrivenWorld:
    """Context manager: `state()`, `place_ego(pose, speed)` (external only), `step()`."""

    def __init__(self, net_path: Path, route: Route, external: bool, **options):
        from datagen.world import World, WorldConfig

        self.external = external
        self._world = World(
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
            raise NotImplementedError("external control needs the world's driver seam")

    @property
    def ended(self) -> str | None:
        return self._world.ended

    @property
    def end_detail(self) -> str:
        return self._world.end_detail

    def state(self) -> FrameState:
        return self._world.state()

    def place_ego(self, pose: Pose, speed_mps: float) -> None:
        raise NotImplementedError

    def step(self) -> None:
        self._world.advance(0.1)

    def close(self) -> None:
        self._world.close()

    def __enter__(self) -> DrivenWorld:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
