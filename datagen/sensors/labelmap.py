"""The label map of a town: the polygons the BEV semantic labels are painted from (paper
Sec. III-A), kept apart from the render mesh so that `datagen/labels.py` needs no scene.

World frame (SUMO network coordinates, metres, x east, y north). Built with the static scene
(datagen/sensors/scene.py `build_static_scene`), cached with it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LabelMap:
    """BEV polygons of a town, in painting order.

    Attributes:
        xy_m: (V, 2) float32 vertices of the polygons, world frame, concatenated.
        start: (P + 1,) int64, polygon p is xy_m[start[p]:start[p+1]].
        class_id: (P,) uint8 class each polygon paints, in painting order: 1 drivable (lanes open to
            cars, junctions), then 0 (sidewalks and walking areas cut out of it), then 2 lane
            markings (lines and stop lines).
        bbox_m: (P, 4) float32 (xmin, ymin, xmax, ymax) of each polygon.
    """

    xy_m: np.ndarray
    start: np.ndarray
    class_id: np.ndarray
    bbox_m: np.ndarray

    @classmethod
    def from_rings(cls, rings: Sequence[np.ndarray], classes: Sequence[int]) -> LabelMap:
        """Polygons ((n, 2) world rings) and the class each paints, in painting order."""
        rings = [np.asarray(r, np.float64).reshape(-1, 2) for r in rings]
        starts = np.concatenate([[0], np.cumsum([len(r) for r in rings])]).astype(np.int64)
        xy = np.concatenate(rings).astype(np.float32) if rings else np.zeros((0, 2), np.float32)
        bbox = np.array([[*r.min(0), *r.max(0)] for r in rings], np.float32).reshape(-1, 4)
        return cls(xy_m=xy, start=starts, class_id=np.array(classes, np.uint8), bbox_m=bbox)
