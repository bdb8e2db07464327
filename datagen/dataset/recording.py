"""One episode as a Rerun recording (`datagen inspect DIR --episode ID --rerun out.rrd`).

    rerun out.rrd          # the viewer: pip install 'iidsu[viz]'

Two timelines: `frame` (the episode's frame number) and `time` (simulation time, s). Entities:

    world                       SUMO network frame (x east, y north, z up, m); the driven path
      world/ego                 the ego's pose at t: everything below is in the ego frame
        world/ego/box             the ego (4.7 x 1.85 x 1.5 m; the shards do not store its size)
        world/ego/lidar/ground    at-ground LiDAR returns of t, t-1, t-2, z = 0
        world/ego/lidar/above     above-ground returns of t, drawn at z = 1 m
        world/ego/boxes           agents at t, labelled with their SUMO track ids
        world/ego/waypoints       the expert's positions at +0.5 .. +2.0 s
        world/ego/target_point    the route's next goal point
    camera/image                the front camera crop (the stored JPEG)
    bev/map                     the BEV semantic map (other / drivable / lane marking)
    bev/lidar                   the four LiDAR BEV channels as a tensor of counts
    bev/boxes, bev/boxes_future agents at t, and at t+0.5 s / t+1.0 s, on the BEV grid (pixels)
    bev/waypoints, bev/target_point
    labels/...                  ego speed, red light, stop sign, distances (scalars);
                                traffic light, command, expert reason (text, logged on change)

The LiDAR points are re-derived from the BEV: one point per non-empty pixel, at its centre. The
BEV keeps no heights, so at-ground points lie at z = 0 and above-ground points at z = 1 m; box
heights are likewise drawn (1.5 m vehicles, 1.8 m people), not stored.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pyarrow as pa

import schemas
from datagen.errors import UserError
from schemas import codecs, dataset
from schemas.video import prepare_output

BOX_HEIGHT_M = {"vehicle": 1.5, "pedestrian": 1.8, "bicycle": 1.6}  # drawn only
EGO_SIZE_M = (4.7, 1.85, 1.5)  # drawn only (the same ego box as the inspect PNG)
ABOVE_GROUND_Z_M = 1.0
MAP_COLOURS = [(0, 0, 0), (123, 123, 123), (228, 228, 228)]  # paper Fig. 5, as the PNG
CLASS_COLOURS = {"vehicle": (223, 218, 8), "pedestrian": (0, 220, 220), "bicycle": (255, 140, 0)}


def check_installed() -> None:
    """Raise UserError in one line if rerun-sdk is missing."""
    try:
        import rerun  # noqa: F401
    except ImportError:
        raise UserError(
            "--rerun needs rerun-sdk: pip install 'iidsu[viz]' (or pip install rerun-sdk)"
        ) from None


def write(table: pa.Table, out: Path) -> None:
    """Log `table` (one episode's frames, sorted by frame) to the recording `out` (.rrd).

    Written to a hidden partial file and renamed when complete."""
    import rerun as rr

    if out.suffix != ".rrd":
        raise UserError(f"{out}: a Rerun recording must end in .rrd")
    partial = prepare_output(out)
    rows = table.to_pylist()
    rec = rr.RecordingStream("iidsu", recording_id=rows[0]["episode_id"])
    try:
        rec.save(partial)
        _log_static(rec, rows)
        last_text: dict[str, str] = {}
        for row in rows:
            rec.set_time("frame", sequence=int(row["frame"]))
            rec.set_time("time", duration=float(row["time_s"]))
            _log_frame(rec, row, last_text)
        rec.flush()
        rec.disconnect()
    except BaseException:
        rec.disconnect()
        partial.unlink(missing_ok=True)
        raise
    os.replace(partial, out)


def _log_static(rec, rows: list[dict]) -> None:
    import rerun as rr

    first = rows[0]
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    path = np.array([(r["ego_x"], r["ego_y"], 0.0) for r in rows])
    rec.log("world/driven_path", rr.LineStrips3D([path], colors=[(255, 0, 0)]), static=True)
    rec.log(
        "episode",
        rr.TextDocument(
            f"episode {first['episode_id']}: town {first['town']}, weather {first['weather']}, "
            f"behaviour {first['behaviour']}, {len(rows)} frames"
        ),
        static=True,
    )
    classes = [
        rr.AnnotationInfo(id=i, label=name, color=MAP_COLOURS[i])
        for i, name in enumerate(schemas.BEV_CLASSES)
    ]
    rec.log("bev", rr.AnnotationContext(classes), static=True)
    boxes = [
        rr.AnnotationInfo(id=i, label=name, color=CLASS_COLOURS[name])
        for i, name in enumerate(schemas.BOX_CLASSES)
    ]
    rec.log("world/ego/boxes", rr.AnnotationContext(boxes), static=True)
    length, width, height = EGO_SIZE_M
    rec.log(
        "world/ego/box",
        rr.Boxes3D(
            centers=[(0, 0, height / 2)],
            half_sizes=[(length / 2, width / 2, height / 2)],
            colors=[(255, 0, 0)],
            labels=["ego"],
        ),
        static=True,
    )


def _log_frame(rec, row: dict, last_text: dict[str, str]) -> None:
    """Log one frame; `last_text` holds the text labels logged so far (logged on change)."""
    import rerun as rr

    rec.log(
        "world/ego",
        rr.Transform3D(
            translation=(row["ego_x"], row["ego_y"], 0.0),
            rotation=rr.RotationAxisAngle(axis=(0, 0, 1), radians=row["ego_yaw"]),
        ),
    )
    lidar = codecs.decode_lidar_bev(row["lidar_bev"])  # (256, 256, 4) counts
    x, y = schemas.bev_pixel_centres()
    for name, channel, z, colour in (
        ("ground", 0, 0.0, (150, 150, 150)),
        ("above", 1, ABOVE_GROUND_Z_M, (255, 140, 0)),
    ):
        hit = lidar[..., channel] > 0
        points = np.stack([x[hit], y[hit], np.full(hit.sum(), z)], -1)
        rec.log(f"world/ego/lidar/{name}", rr.Points3D(points, colors=colour, radii=0.05))
    rec.log("bev/lidar", rr.Tensor(lidar, dim_names=("row", "col", "channel")))
    rec.log("bev/map", rr.SegmentationImage(codecs.decode_bev_semantic(row["bev_semantic"])))
    rec.log("camera/image", rr.EncodedImage(contents=row["image"], media_type="image/jpeg"))

    boxes = row["boxes"] or []
    now = [b for b in boxes if b["t"] == 0]
    heights = np.array([BOX_HEIGHT_M[b["cls"]] for b in now])
    rec.log(
        "world/ego/boxes",
        rr.Boxes3D(
            centers=[(b["x"], b["y"], h / 2) for b, h in zip(now, heights)],
            half_sizes=[(b["length"] / 2, b["width"] / 2, h / 2) for b, h in zip(now, heights)],
            rotation_axis_angles=[rr.RotationAxisAngle((0, 0, 1), radians=b["yaw"]) for b in now],
            labels=[b["track_id"] for b in now],
            class_ids=[schemas.BOX_CLASSES.index(b["cls"]) for b in now],
        ),
    )
    for entity, subset in (("bev/boxes", now), ("bev/boxes_future", [b for b in boxes if b["t"]])):
        rec.log(
            entity, rr.LineStrips2D(_bev_outlines(subset), labels=[b["track_id"] for b in subset])
        )

    waypoints = np.asarray(row["waypoints"], np.float64).reshape(-1, 2)
    target = np.asarray(row["target_point"], np.float64).reshape(1, 2)
    path = np.concatenate([[(0.0, 0.0)], waypoints])
    rec.log(
        "world/ego/waypoints",
        rr.LineStrips3D([np.c_[path, np.zeros(len(path))]], colors=[(0, 0, 255)]),
    )
    rec.log(
        "world/ego/target_point", rr.Points3D(np.c_[target, [0.0]], colors=(255, 0, 255), radii=0.4)
    )
    rec.log("bev/waypoints", rr.Points2D(_bev_xy(waypoints), colors=(0, 0, 255), radii=2))
    rec.log("bev/target_point", rr.Points2D(_bev_xy(target), colors=(255, 0, 255), radii=4))

    rec.log("labels/ego_speed_mps", rr.Scalars(row["ego_speed"]))
    rec.log("labels/red_light", rr.Scalars(float(row["traffic_light"] == "red")))
    rec.log("labels/stop_sign", rr.Scalars(float(row["stop_sign"])))
    for name in ("light_distance_m", "stop_distance_m"):
        if row[name] is not None:
            rec.log(f"labels/{name}", rr.Scalars(row[name]))
    for name in ("traffic_light", "command", "expert_reason"):
        if last_text.get(name) != row[name]:
            rec.log(f"labels/{name}", rr.TextLog(f"{name}: {row[name]}"))
            last_text[name] = row[name]


def _bev_xy(xy: np.ndarray) -> np.ndarray:
    """(..., 2) ego-frame points (m) -> (..., 2) BEV image points (column, row), pixels."""
    row, col = schemas.ego_to_bev_px(xy[..., 0], xy[..., 1])
    return np.stack([col, row], -1)


def _bev_outlines(boxes: list[dict]) -> list[np.ndarray]:
    if not boxes:
        return []
    corners = dataset.box_corners(
        *(np.array([b[k] for b in boxes]) for k in ("x", "y", "yaw", "length", "width"))
    )  # (N, 4, 2)
    return list(_bev_xy(np.concatenate([corners, corners[:, :1]], 1)))  # closed outlines
