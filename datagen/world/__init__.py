"""The driving world: SUMO stepped in-process, traffic around an expert-driven ego.

Modules (data flows down):
    towns.py        the built-in towns (SUMO networks from recipes, cached) and network checks
    config.py       WorldConfig: one episode's network, seed, conditions, who drives the ego
    behaviour.py    behaviour profiles (SUMO vType tables) and the weather -> behaviour draw
    expert.py       the expert ego's target speed from named rules: pure
    fleet.py        road-user types and box sizes
    sumo.py         the only module that calls libsumo; typed snapshots and commands
    route.py        route ahead, command, target point, signals: pure geometry
    perception.py   the ego's obstacles and who holds it back: pure
    traffic.py      the population in a bubble around the ego
    rules.py        the ego's record against stop signs and red lights
    simulation.py   the running episode both drivers step: SUMO, traffic, the ego's route
    planning.py     what the expert reads (ExpertInput) and its plan, from any ego state
    external.py     the ego placed by an external controller (EgoCommand)
    world.py        the expert's step loop, the seam for who drives, World's views, record

Who drives the ego is one seam: WorldConfig.ego_driver "expert" (default) or "external", then
World.step(EgoCommand(pose, speed)) every step and World.truth() for scoring (world.py).

Everything other modules import from here is re-exported below, so `from datagen.world import
World, WorldConfig, record` stays the one entry point.
"""

from datagen.world.behaviour import EGO_DECEL_SLACK
from datagen.world.config import EGO_DRIVERS, WARMUP_S, WorldConfig
from datagen.world.external import EgoCommand
from datagen.world.fleet import (
    EGO_DIMS_M,
    EGO_ID,
    PED_DIMS_M,
    VEHICLE_TYPES,
)
from datagen.world.route import (
    COMMAND_RANGE_M,
    EXIT_INTO_M,
    PATH_LOOKAHEAD_M,
    SIGNAL_RANGE_M,
    TARGET_AHEAD_M,
)
from datagen.world.simulation import AGENT_RADIUS_M
from datagen.world.sumo import TELEPORT_S
from datagen.world.traffic import PED_REMOVE_M, PED_SPAWN_M, VEH_REMOVE_M, VEH_SPAWN_M
from datagen.world.world import BLOCKED_S, COLLISION_DROP_S, EgoTruth, World, record

__all__ = [
    "AGENT_RADIUS_M",
    "BLOCKED_S",
    "COLLISION_DROP_S",
    "COMMAND_RANGE_M",
    "EGO_DECEL_SLACK",
    "EGO_DIMS_M",
    "EGO_DRIVERS",
    "EGO_ID",
    "EXIT_INTO_M",
    "PATH_LOOKAHEAD_M",
    "PED_DIMS_M",
    "PED_REMOVE_M",
    "PED_SPAWN_M",
    "SIGNAL_RANGE_M",
    "TARGET_AHEAD_M",
    "TELEPORT_S",
    "VEHICLE_TYPES",
    "VEH_REMOVE_M",
    "VEH_SPAWN_M",
    "WARMUP_S",
    "EgoCommand",
    "EgoTruth",
    "World",
    "WorldConfig",
    "record",
]
