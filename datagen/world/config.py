"""The world's configuration: one episode's network, seed, conditions and who drives the ego."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

WARMUP_S = 10.0  # traffic runs this long before the ego is inserted
EGO_DRIVERS = ("expert", "external")


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
        ego_driver: who drives the ego (EGO_DRIVERS): "expert" (the rule-based expert, SUMO's
            safety model under it) or "external" (a controller places it every step:
            `World.step(EgoCommand)`, external.py).
        target_point: the form of FrameState.target_point_xy_m (route.TARGET_FORMS): "sparse",
            the next point of the sparse route plan (Sec. III-A's route goal, as TransFuser's:
            junction entries and exits and every 50 m, lane-independent), or "dense", a point
            30 m ahead along the ego's lane path (5 m into the exit lane near a junction).
        end_on_collision: an ego collision ends the expert's episode ("collision"; the data's
            rule). False: it drives on and the caller scores it (drive eval, as the
            leaderboard drives on after a collision).
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
    ego_driver: str = "expert"
    target_point: str = "sparse"
    end_on_collision: bool = True
