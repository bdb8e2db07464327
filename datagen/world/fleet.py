"""Who is on the road: the background vehicle types, the ego's and pedestrians' box sizes.

Box extents are the SUMO vType's length, width and height, metres; `dims` maps a SUMO type id to
(length_m, width_m, height_m, box class) with box classes from schemas.BOX_CLASSES.
"""

from __future__ import annotations

EGO_ID = "ego"
# Background vehicle types: (id, vClass, length, width, height, share, box class).
VEHICLE_TYPES = (
    ("car", "passenger", 4.5, 1.8, 1.5, 0.58, "vehicle"),
    ("suv", "passenger", 4.9, 1.95, 1.8, 0.17, "vehicle"),
    ("van", "delivery", 5.6, 2.0, 2.4, 0.10, "vehicle"),
    ("truck", "truck", 8.5, 2.5, 3.4, 0.05, "vehicle"),
    ("bus", "bus", 12.0, 2.55, 3.2, 0.04, "vehicle"),
    ("bicycle", "bicycle", 1.7, 0.65, 1.7, 0.06, "bicycle"),
)
EGO_DIMS_M = (4.7, 1.85, 1.5)  # length, width, height (a mid-size sedan)
PED_DIMS_M = (0.4, 0.5, 1.75)
PED_TYPE = "ped"

_DIMS: dict[str, tuple[float, float, float, str]] = {
    vid: (length, width, height, cls) for vid, _c, length, width, height, _sh, cls in VEHICLE_TYPES
}
_DIMS[PED_TYPE] = (*PED_DIMS_M, "pedestrian")


def dims(type_id: str) -> tuple[float, float, float, str]:
    """(length_m, width_m, height_m, box class) of a SUMO type id; unknown types (the ego's,
    a network's own) get the ego's size and class "vehicle"."""
    return _DIMS.get(type_id, (*EGO_DIMS_M, "vehicle"))
