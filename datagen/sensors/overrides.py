"""`datagen build --sensor FIELD=VALUE`: SensorConfig overrides, each value checked here.

    parse_sensors(["jpeg_quality=80", "camera.crop_px=128", 'lidar={"channels": 32}'])

A value out of range (SENSOR_RANGES), of the wrong type, or a field that does not exist is a
one-line UserError before anything is built: a worker would otherwise crash on it mid-build,
or an encoder clamp it silently while the manifest records what was asked.
"""

from __future__ import annotations

import dataclasses
import json
import math

from datagen.errors import UserError

# --sensor values that shape the data wrong or crash a worker if out of range (a float must
# also be finite): FIELD -> (test, what it must be). A field not listed takes any value.
_positive = (lambda v: v > 0, "positive")
_non_negative = (lambda v: v >= 0, "0 or more")
SENSOR_RANGES = {
    "jpeg_quality": (lambda v: 1 <= v <= 100, "in 1..100"),
    "pose_noise_m": _non_negative,
    "pose_noise_rad": _non_negative,
    **{f"camera.{k}": _positive for k in ("width_px", "height_px", "crop_px", "range_m")},
    "camera.fov_deg": (lambda v: 0 < v < 180, "in (0, 180) degrees"),
    **{f"lidar.{k}": _positive for k in ("channels", "azimuth_steps", "range_m")},
    "lidar.upper_fov_deg": (lambda v: -90 <= v <= 90, "in -90..90 degrees"),
    "lidar.lower_fov_deg": (lambda v: -90 <= v <= 90, "in -90..90 degrees"),
    "lidar.ground_threshold_m": _non_negative,
}


def parse_sensors(overrides: list[str]):
    """SensorConfig with `FIELD=VALUE` overrides (dotted FIELD for nested configs, or a JSON
    object for a whole nested config: `camera={"crop_px": 128}`), each value checked against
    SENSOR_RANGES here, before anything is built."""
    from datagen.sensors.config import SensorConfig  # numba and Embree: imported when used

    sensors = SensorConfig()
    for item in overrides:
        name, sep, value = item.partition("=")
        if not sep:
            raise UserError(f"--sensor {item!r}: expected FIELD=VALUE")
        sensors = _replace_path(sensors, name.split("."), value, item)
    lidar = sensors.lidar
    if lidar.upper_fov_deg <= lidar.lower_fov_deg:
        raise UserError("--sensor: lidar.upper_fov_deg must be above lidar.lower_fov_deg")
    return sensors


def _replace_path(obj, path: list[str], value, item: str, where: str = ""):
    """`obj` with field path[0] (nested: path[1:]) set from `value` (text, or a JSON value
    inside a JSON object); UserError naming `item` for anything it cannot take."""
    fields = {f.name: f for f in dataclasses.fields(obj)} if dataclasses.is_dataclass(obj) else {}
    if path[0] not in fields:
        raise UserError(f"--sensor {item}: no field {path[0]!r} (fields: {', '.join(fields)})")
    current, name = getattr(obj, path[0]), where + path[0]
    if len(path) > 1:
        new = _replace_path(current, path[1:], value, item, name + ".")
        return dataclasses.replace(obj, **{path[0]: new})
    if dataclasses.is_dataclass(current):  # a JSON object of its fields
        try:
            doc = json.loads(value) if isinstance(value, str) else value
        except ValueError:
            doc = None
        if not isinstance(doc, dict):
            raise UserError(f"--sensor {item}: {name} takes a JSON object of its fields")
        for k, v in doc.items():
            current = _replace_path(current, [k], v, item, name + ".")
        return dataclasses.replace(obj, **{path[0]: current})
    try:
        if isinstance(current, bool):
            text = str(value).lower()
            new = {"true": True, "false": False, "1": True, "0": False}[text]
        elif isinstance(current, int | float):
            if isinstance(value, bool):
                raise ValueError
            new = type(current)(value)
            if not isinstance(value, str) and new != value:  # 1.5 from JSON for an int field
                raise ValueError
        elif isinstance(current, str) or current is None:
            new = str(value)
        else:
            new = type(current)(json.loads(value) if isinstance(value, str) else value)
    except (KeyError, ValueError, TypeError):
        raise UserError(f"--sensor {item}: cannot read {value!r} for {name}") from None
    if isinstance(new, float) and not math.isfinite(new):
        raise UserError(f"--sensor {item}: {name} must be a finite number, got {value}")
    test, need = SENSOR_RANGES.get(name, (None, ""))
    if test is not None and not test(new):
        raise UserError(f"--sensor {item}: {name} must be {need}, got {value}")
    try:
        return dataclasses.replace(obj, **{path[0]: new})
    except ValueError as e:  # the config's own check (__post_init__)
        raise UserError(f"--sensor {item}: {e}") from None
