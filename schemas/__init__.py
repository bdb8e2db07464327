"""The v1 shard contract shared by `datagen` (writer) and `training` (reader).

One Parquet row per recorded frame (2 Hz). Every column is declared once here, with its Arrow
type, unit and frame in the field metadata; writers derive the `pa.Schema` from `SCHEMA` and
readers call `validate(table)` / `check_version(metadata)`.

Ego frame (used by every ego-relative column): origin at the centre of the ego's bounding box
on the ground, x forward, y left, z up, metres; yaw counter-clockwise from +x, radians.
World frame: SUMO network coordinates (metres, x east, y north); world yaw counter-clockwise
from +x (east), radians, i.e. *not* SUMO's navigational angle.
"""

from __future__ import annotations

import json

import pyarrow as pa

from schemas.bev import (  # noqa: F401  (re-exported: the grid is part of the contract)
    BEV_AHEAD_M,
    BEV_PX_PER_M,
    BEV_SIDE_M,
    BEV_SIZE_PX,
    bev_pixel_centres,
    ego_to_bev_px,
)

SCHEMA_VERSION = "1.2"
"""major.minor: readers refuse a different major version; a minor bump only adds columns
(ADDED_IN), which a file of an older minor version may lack. 1.1 adds `lidar_ground_t`; 1.2
`rig_shift_m` and `rig_yaw_rad` (recovery frames)."""

# Keys of the file-level (schema) metadata. Values are UTF-8 strings; *_json values are JSON.
META_SCHEMA_VERSION = "iidsu.schema_version"
META_GENERATOR_VERSION = "iidsu.generator_version"
META_CONFIG_JSON = "iidsu.config_json"  # sensor and grid configuration
META_NETWORK_HASH = "iidsu.network_sha256"  # sha256 of the town's .net.xml bytes
META_SEED = "iidsu.seed"

# Categorical columns are readable strings in the shards (Parquet dictionary-encodes them on
# disk, so they cost no more than int8 codes) so a pandas user filters `df.weather == "foggy"`.
WEATHERS = ("sunny", "cloudy", "rainy", "foggy")
BEHAVIOURS = ("normal", "aggressive", "cautious")
COMMANDS = ("left", "right", "straight", "follow")
TRAFFIC_LIGHTS = ("none", "red", "yellow", "green")
EXPERT_REASONS = (
    "none",  # cruising at the profile's speed for the road
    "speed_limit",  # holding the (profile-scaled) speed limit of the lane
    "curve",  # slowing for a sharp curve or turn ahead
    "vehicle",  # keeping the time gap to a lead or cutting-in vehicle
    "pedestrian",  # yielding to a pedestrian on or entering the path
    "red_light",  # stopping for a red (or a yellow it can stop for comfortably)
    "stop_sign",  # stopping or waiting at a stop-controlled entry
    "junction",  # yielding to crossing traffic at a junction
    "route_end",  # stopping at the end of the route
)
BOX_CLASSES = ("vehicle", "pedestrian", "bicycle")
FRAME_RATE_HZ = 2.0  # recorded frames (Sec. IV-A); the policy plans at the same rate in `drive`
FRAME_PERIOD_S = 1.0 / FRAME_RATE_HZ  # 0.5 s between consecutive frames
BOX_TIMESTEPS = (0, 1, 2)  # frames: t, t+0.5 s, t+1.0 s
WAYPOINT_TIMES_S = tuple(k * FRAME_PERIOD_S for k in (1, 2, 3, 4))  # one per frame: 0.5 .. 2.0 s

IMAGE_SIZE_PX = 256  # stored camera crop, square
IMAGE_FULL_W_PX, IMAGE_FULL_H_PX, IMAGE_FOV_DEG = 400, 300, 100.0
LIDAR_BEV_CHANNELS = 4
BEV_CLASSES = ("other", "drivable", "lane_marking")


def _field(
    name: str,
    type_: pa.DataType,
    desc: str,
    unit: str = "",
    frame: str = "",
    nullable: bool = False,
) -> pa.Field:
    meta = {"description": desc, "unit": unit, "frame": frame}
    return pa.field(name, type_, nullable=nullable, metadata={k: v for k, v in meta.items() if v})


BOX_TYPE = pa.struct(
    [
        _field("track_id", pa.string(), "SUMO id of the vehicle or person"),
        _field("cls", pa.string(), f"one of {', '.join(BOX_CLASSES)}"),
        _field("t", pa.int8(), "timestep: 0 = t, 1 = t+0.5 s, 2 = t+1.0 s"),
        _field("x", pa.float32(), "box centre x", "m", "ego at t"),
        _field("y", pa.float32(), "box centre y", "m", "ego at t"),
        _field("yaw", pa.float32(), "heading, counter-clockwise from ego +x", "rad", "ego at t"),
        _field("length", pa.float32(), "extent along the heading", "m"),
        _field("width", pa.float32(), "extent across the heading", "m"),
        _field("speed", pa.float32(), "speed along the heading", "m/s"),
        _field("lidar_points", pa.int32(), "LiDAR returns on the agent at t; 0 for t > 0", "count"),
    ]
)

EGO = "ego at t"
FIELDS: tuple[pa.Field, ...] = (
    _field("episode_id", pa.string(), "unique per episode: <town>-<seed>-<index>"),
    _field("frame", pa.int32(), "0-based, consecutive within the episode (2 Hz)"),
    _field("time_s", pa.float64(), "simulation time", "s"),
    _field("town", pa.string(), "built-in town name, or the --net file's stem"),
    _field("weather", pa.string(), f"one of {', '.join(WEATHERS)}"),
    _field("behaviour", pa.string(), f"traffic and ego profile: {', '.join(BEHAVIOURS)}"),
    _field("ego_x", pa.float64(), "ego box centre x", "m", "world (SUMO network)"),
    _field("ego_y", pa.float64(), "ego box centre y", "m", "world (SUMO network)"),
    _field(
        "ego_yaw", pa.float32(), "ego heading, counter-clockwise from +x (east)", "rad", "world"
    ),
    _field("ego_speed", pa.float32(), "ego speed", "m/s"),
    _field(
        "rig_shift_m",
        pa.float32(),
        "recovery frames: the sensor rig's shift to the ego's left (negative: right); every "
        "'ego at t' column is in the rig's frame; 0 for frames sensed from the ego; since 1.2",
        "m",
        "ego",
    ),
    _field(
        "rig_yaw_rad",
        pa.float32(),
        "recovery frames: the rig's turn from the ego's heading, counter-clockwise; 0 for "
        "frames sensed from the ego; since schema 1.2",
        "rad",
        "ego",
    ),
    _field("command", pa.string(), f"high-level route command: {', '.join(COMMANDS)}"),
    _field("target_point", pa.list_(pa.float32(), 2), "next route goal point (x, y)", "m", EGO),
    _field(
        "waypoints",
        pa.list_(pa.float32(), 8),
        "expert's positions at +0.5, +1.0, +1.5, +2.0 s as x0,y0,x1,y1,...",
        "m",
        EGO,
    ),
    _field(
        "traffic_light",
        pa.string(),
        f"signal of the next junction on the route within 30 m: {', '.join(TRAFFIC_LIGHTS)}",
    ),
    _field(
        "light_distance_m",
        pa.float32(),
        "distance to that signal's stop line; null if none",
        "m",
        nullable=True,
    ),
    _field("stop_sign", pa.bool_(), "a stop-controlled entry on the route within 30 m"),
    _field(
        "stop_distance_m",
        pa.float32(),
        "distance to that stop line; null if none",
        "m",
        nullable=True,
    ),
    _field("expert_reason", pa.string(), f"why the expert slows: {', '.join(EXPERT_REASONS)}"),
    _field(
        "image",
        pa.binary(),
        "front camera, 256x256 RGB centre crop of a 400x300 100-degree "
        "image, JPEG (quality in the config metadata)",
        "",
        "camera",
    ),
    _field(
        "lidar_bev",
        pa.binary(),
        "256x256x4 uint8 PNG (RGBA samples = ch0..ch3): ch0 = "
        "at-ground hits summed over t, t-1, t-2; ch1..3 = above-ground hits at t, t-1, t-2; "
        "clipped at 255",
        "count",
        "BEV grid of the ego at t",
    ),
    _field(
        "lidar_ground_t",
        pa.binary(),
        "256x256 uint8 PNG: at-ground LiDAR hits of the sweep at t only (ch0 of lidar_bev "
        "without t-1, t-2; what a single-frame model sees); clipped at 255; since schema 1.1",
        "count",
        "BEV grid of the ego at t",
    ),
    _field(
        "bev_semantic",
        pa.binary(),
        "256x256 uint8 PNG of class ids: 0 other, 1 drivable, 2 lane marking",
        "",
        "BEV grid of the ego at t",
    ),
    _field(
        "boxes",
        pa.list_(pa.field("box", BOX_TYPE, nullable=False)),
        "agents inside the BEV area at t, t+0.5 s, t+1.0 s",
        "",
        EGO,
    ),
)

COLUMNS: tuple[str, ...] = tuple(f.name for f in FIELDS)
ADDED_IN: dict[str, str] = {"lidar_ground_t": "1.1", "rig_shift_m": "1.2", "rig_yaw_rad": "1.2"}
"""Columns added by a minor version: files written before it (older minor) may lack them."""


def _minor(version: str) -> int:
    parts = version.split(".")
    return int(parts[1]) if len(parts) > 1 and parts[1].isdigit() else 0


CATEGORIES: dict[str, tuple[str, ...]] = {
    "weather": WEATHERS,
    "behaviour": BEHAVIOURS,
    "command": COMMANDS,
    "traffic_light": TRAFFIC_LIGHTS,
    "expert_reason": EXPERT_REASONS,
}


class SchemaError(ValueError):
    """A table or file that does not satisfy the shard contract; the message names the fault."""


def schema(metadata: dict[str, str] | None = None) -> pa.Schema:
    """The v1 `pa.Schema`, with the schema version and any extra file-level metadata."""
    meta = {META_SCHEMA_VERSION: SCHEMA_VERSION, **(metadata or {})}
    return pa.schema(FIELDS, metadata=meta)


SCHEMA = schema()


LABEL_ONLY_CONFIG_KEYS = ("recovery_share", "recovery_shift_m", "recovery_yaw_deg", "driver")
"""Keys of iidsu.config_json that shape a build's labels but not what its sensors see: shards
that differ only in them were sensed alike (training mixes them, drive accepts the model)."""


def sensor_part(config: dict) -> dict:
    """An iidsu.config_json dict without LABEL_ONLY_CONFIG_KEYS and without "raycaster" (how the
    rays were cast, datagen/sensors/raycast.py: the same hits either way): what the sensors
    see."""
    return {k: v for k, v in config.items() if k not in LABEL_ONLY_CONFIG_KEYS and k != "raycaster"}


def file_metadata(
    *, generator_version: str, config: dict, network_sha256: str, seed: int
) -> dict[str, str]:
    """The file-level metadata every shard carries (see module docstring for keys)."""
    return {
        META_SCHEMA_VERSION: SCHEMA_VERSION,
        META_GENERATOR_VERSION: generator_version,
        META_CONFIG_JSON: json.dumps(config, sort_keys=True),
        META_NETWORK_HASH: network_sha256,
        META_SEED: str(seed),
    }


def check_version(metadata: dict | None, where: str = "table") -> str:
    """Return the schema version in `metadata`, raising SchemaError for a missing one or a
    different major version. Keys and values may be bytes (as pyarrow gives them) or str."""
    meta = {(k.decode() if isinstance(k, bytes) else k): v for k, v in (metadata or {}).items()}
    version = meta.get(META_SCHEMA_VERSION)
    if version is None:
        raise SchemaError(f"{where}: no '{META_SCHEMA_VERSION}' metadata; not an iidsu shard")
    version = version.decode() if isinstance(version, bytes) else version
    if version.split(".")[0] != SCHEMA_VERSION.split(".")[0]:
        raise SchemaError(
            f"{where}: schema version {version} is not readable by this code (needs major "
            f"version {SCHEMA_VERSION.split('.')[0]}, i.e. {SCHEMA_VERSION})"
        )
    return version


def validate(table: pa.Table, where: str = "table") -> None:
    """Check `table` against the v1 contract; raise SchemaError naming the column at fault.

    Checks: schema version metadata, every column present with its exact Arrow type, no nulls
    in non-nullable columns, categorical values within their sets, and box classes/timesteps.
    Extra columns are allowed (a later minor version may add some); a column added in a later
    minor version than the file's (ADDED_IN) may be missing.
    """
    import pyarrow.compute as pc

    version = check_version(table.schema.metadata, where)
    for field in FIELDS:
        if field.name not in table.schema.names:
            added = ADDED_IN.get(field.name)
            if added is not None and _minor(version) < _minor(added):
                continue  # an older minor version's file, written before the column existed
            raise SchemaError(f"{where}: missing column '{field.name}'")
        actual = table.schema.field(field.name).type
        if not actual.equals(field.type):
            raise SchemaError(
                f"{where}: column '{field.name}' has type {actual}, expected {field.type}"
            )
        column = table.column(field.name)
        if not field.nullable and column.null_count:
            raise SchemaError(f"{where}: column '{field.name}' has {column.null_count} nulls")
    for name, allowed in CATEGORIES.items():
        bad = pc.filter(
            table.column(name), pc.invert(pc.is_in(table.column(name), pa.array(allowed)))
        )
        if len(bad):
            raise SchemaError(
                f"{where}: column '{name}' has value {bad[0].as_py()!r}, expected one of {allowed}"
            )
    boxes = pc.list_flatten(table.column("boxes"))
    if len(boxes):
        cls = pc.struct_field(boxes, "cls")
        bad = pc.filter(cls, pc.invert(pc.is_in(cls, pa.array(BOX_CLASSES))))
        if len(bad):
            raise SchemaError(
                f"{where}: column 'boxes' has cls {bad[0].as_py()!r}, expected one of {BOX_CLASSES}"
            )
        t = pc.struct_field(boxes, "t")
        if pc.any(pc.or_(pc.less(t, 0), pc.greater(t, 2))).as_py():
            raise SchemaError(f"{where}: column 'boxes' has t outside {BOX_TIMESTEPS}")
