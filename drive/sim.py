"""The world of one route, driven by the expert or by an external controller (drive/eval).

A thin adapter over the world's seam for who drives the ego (`datagen.world`,
WorldConfig.ego_driver): the route's edges are the ego's route (never extended), its seed,
weather and behaviour are the world's. Externally driven, the ego is placed every step where the
controller put it (`World.step(EgoCommand)`: moveToXY anywhere, off its lane or the road too,
its speed known to SUMO, its SUMO route kept on the plan so others give way at junctions).
`SensorStream` encodes what a model policy sees at each 2 Hz instant.
"""

from __future__ import annotations

from collections import deque
from pathlib import Path

import numpy as np

from datagen.state import FrameState, Pose
from drive.routes import Route

EXPERT_GO_MPS = 1.0  # the expert "would go" when its target speed is above this ...
FREE_REASONS = ("none", "speed_limit", "curve")  # ... for no reason to wait (a clear road, a
# green or no light): a red light's or a queue's approach speed is above it a few metres short


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

    def expert_would_go(self) -> bool:
        """Whether the privileged expert, in the ego's place now, would drive on with nothing to
        wait for (its target speed above EXPERT_GO_MPS, for none of the rules that stop it:
        FREE_REASONS): a policy standing then is stuck, not waiting."""
        plan = self._world.expert_plan()
        if plan is None:
            return False
        decision = plan[1]
        return decision.target_speed_mps > EXPERT_GO_MPS and decision.reason in FREE_REASONS

    def expert_waypoints(self, frame: FrameState) -> np.ndarray | None:
        """(4, 2) the privileged expert's plan from the ego's state now (World.expert_plan),
        ego frame at `frame` (its state now), m; None off the network."""
        plan = self._world.expert_plan()
        return None if plan is None else frame.ego.pose.ego_from_world(plan[0])

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


class SensorStream:
    """The sensors of one drive at consecutive 2 Hz instants, encoded as the shards hold them
    (datagen.episode.Sensors; the LiDAR BEV history t, t-1, t-2, its oldest sweep standing in
    for missing ones until it is full), so a model sees what it was trained on.

    A build sweeps its first HISTORY instants but renders no camera and counts no BEV for them
    (they make no row), so its camera stream (rain streaks) and pose-noise stream start at the
    first full history. Here those instants are encoded with copies of both streams, so from
    the first full history on the same states give a build's bytes in every weather
    (tests/test_drive_parity.py)."""

    def __init__(self, sensors, jpeg_quality: int):
        from datagen.sensors.config import HISTORY

        self.sensors = sensors
        self.jpeg_quality = jpeg_quality
        self._sweeps: deque = deque(maxlen=HISTORY + 1)
        self.last_sweep = None  # datagen.sensors.lidar.Sweep of the last instant encoded or swept

    @property
    def full(self) -> bool:
        """The last instant encoded had a full LiDAR history (a build would make a row of it)."""
        return len(self._sweeps) == self._sweeps.maxlen

    def sweep(self, frame: FrameState):
        """Only the LiDAR sweep of `frame` (no camera, no encoding; for the creep's safety box
        where no model needs the sensors)."""
        self.last_sweep = self.sensors.sweep(self.sensors.scene(frame), frame)
        return self.last_sweep

    def encode(self, frame: FrameState) -> tuple[bytes, bytes, bytes]:
        """(camera JPEG, LiDAR BEV PNG, current ground-hits PNG) of `frame`; call once per
        instant, in order."""
        import copy

        from datagen.episode import encode_sensors

        sense = self.sensors
        scene = sense.scene(frame)
        self.last_sweep = sense.sweep(scene, frame)
        self._sweeps.appendleft(self.last_sweep)  # [t, t-1, t-2]
        missing = self._sweeps.maxlen - len(self._sweeps)
        hist = list(self._sweeps) + [self._sweeps[-1]] * missing
        if not missing:
            e = encode_sensors(sense, scene, frame, hist)
        else:  # an instant a build makes no row of: leave its camera and pose streams as is
            streams = sense.camera_rng, sense.pose_rng
            sense.camera_rng, sense.pose_rng = (copy.deepcopy(g) for g in streams)
            try:
                e = encode_sensors(sense, scene, frame, hist)
            finally:
                sense.camera_rng, sense.pose_rng = streams
        return e["image"], e["lidar_bev"], e["lidar_ground_t"]
