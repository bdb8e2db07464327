"""`datagen inspect`: draw one stored frame the way the paper's Fig. 5 does.

    datagen inspect data/ --frame 10 --out frame.png
    datagen inspect data/grid_small/grid_small-7-0.parquet --frame 3 --out f.png

Left: the camera crop above the current LiDAR BEV (grey: at-ground returns of t, t-1, t-2;
orange: above-ground returns at t). Middle: the BEV map (grey drivable area, white lane markings,
black other; the paper's colours), the ego (red), agents at t (yellow, filled) and at t+0.5 s,
t+1.0 s (outlines, fading), the expert's waypoints (blue) and the target point (magenta; an arrow
at the border if it lies off the grid). Right: traffic light, stop sign, weather, behaviour,
command, speed and the expert's reason.

`--frame N` counts rows across the shards in path order (files starting with `_` are skipped);
with `--episode ID` it is that episode's `frame` number instead.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from datagen.errors import UserError

HELP = "draw one frame: camera, LiDAR BEV, BEV map with boxes and waypoints, labels (Fig. 5)"

SCALE = 2  # BEV map drawn at 2x
BEV_COLOURS_RGB = np.array([(0, 0, 0), (123, 123, 123), (228, 228, 228)], np.uint8)  # paper Fig. 5
EGO_RGB = (255, 0, 0)
AGENT_RGB = (223, 218, 8)
PERSON_RGB = (0, 220, 220)
WAYPOINT_RGB = (0, 0, 255)
TARGET_RGB = (255, 0, 255)
LIGHT_RGB = {
    "red": (255, 40, 40),
    "yellow": (255, 200, 0),
    "green": (40, 220, 90),
    "none": (150, 150, 150),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", metavar="SHARD_OR_DIR", help="a shard (.parquet) or a dataset directory")
    p.add_argument("--frame", type=int, default=0, help="row to draw (default 0)")
    p.add_argument("--episode", default=None, help="pick this episode; --frame is its frame number")
    p.add_argument("--out", default="frame.png", help="PNG to write (default frame.png)")


def shard_files(path: Path) -> list[Path]:
    """The shards under a path (itself if a file), in path order, skipping `_*` names."""
    if path.is_file():
        return [path]
    if not path.is_dir():
        raise UserError(f"{path}: no such file or directory")
    files = sorted(
        p
        for p in path.rglob("*.parquet")
        if not any(part.startswith("_") for part in p.relative_to(path).parts)
    )
    if not files:
        raise UserError(f"{path}: no .parquet shards")
    return files


def read_row(path: Path, frame: int, episode: str | None = None) -> dict:
    """One row of the dataset at `path` as a dict of Python values."""
    import pyarrow.parquet as pq

    import schemas

    if frame < 0:
        raise UserError(f"--frame must be >= 0, got {frame}")
    seen = 0
    for f in shard_files(path):
        try:
            pf = pq.ParquetFile(f)
        except Exception as e:  # noqa: BLE001  (a broken file is a user-facing error)
            raise UserError(f"{f}: not a readable Parquet file ({e})") from e
        schemas.check_version(pf.schema_arrow.metadata, str(f))
        if episode is not None:
            t = pf.read(columns=["episode_id", "frame"])
            ids, frames = t.column("episode_id").to_numpy(), t.column("frame").to_numpy()
            hit = np.flatnonzero((ids == episode) & (frames == frame))
            if len(hit):
                return pf.read().slice(int(hit[0]), 1).to_pylist()[0]
            continue
        n = pf.metadata.num_rows
        if frame < seen + n:
            return pf.read().slice(frame - seen, 1).to_pylist()[0]
        seen += n
    if episode is not None:
        raise UserError(f"{path}: no frame {frame} of episode {episode!r}")
    raise UserError(f"{path}: frame {frame} out of range ({seen} rows)")


def _ego_to_px(xy: np.ndarray) -> np.ndarray:
    """(N, 2) ego-frame points -> (N, 2) float (x=col, y=row) in the 2x BEV drawing."""
    from schemas import ego_to_bev_px

    row, col = ego_to_bev_px(xy[:, 0], xy[:, 1])
    return np.stack([col, row], 1) * SCALE


def _box_px(x: float, y: float, yaw: float, length: float, width: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    corners = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * [length / 2, width / 2]
    xy = np.stack(
        [x + c * corners[:, 0] - s * corners[:, 1], y + s * corners[:, 0] + c * corners[:, 1]], 1
    )
    return _ego_to_px(xy)


def _poly(img: np.ndarray, pts: np.ndarray, rgb, filled: bool, thickness: int = 1) -> None:
    p = [np.round(pts * 16).astype(np.int32)]
    if filled:
        cv2.fillPoly(img, p, rgb, cv2.LINE_AA, 4)
    else:
        cv2.polylines(img, p, True, rgb, thickness, cv2.LINE_AA, 4)


def draw(row: dict) -> np.ndarray:
    """(512, 1024 + 300, 3) uint8 RGB picture of one row."""
    from schemas import BEV_SIZE_PX, codecs

    image = codecs.decode_image(row["image"])
    lidar = codecs.decode_lidar_bev(row["lidar_bev"]).astype(np.float32)
    classes = codecs.decode_bev_semantic(row["bev_semantic"])

    # LiDAR: at-ground (sum of three sweeps) grey, above-ground at t orange.
    ground = np.clip(lidar[..., 0] * 50, 0, 200)
    above = np.clip(lidar[..., 1] * 120, 0, 255)
    lid = np.stack([np.maximum(ground, above), np.maximum(ground, above * 0.55), ground], -1)
    left = np.concatenate([cv2.resize(image, (256, 256)), lid.astype(np.uint8)], 0)

    size = BEV_SIZE_PX * SCALE
    bev = cv2.resize(
        BEV_COLOURS_RGB[np.clip(classes, 0, 2)], (size, size), interpolation=cv2.INTER_NEAREST
    )
    boxes = sorted(row["boxes"] or [], key=lambda b: -b["t"])
    for b in boxes:
        rgb = PERSON_RGB if b["cls"] == "pedestrian" else AGENT_RGB
        pts = _box_px(b["x"], b["y"], b["yaw"], max(b["length"], 0.5), max(b["width"], 0.5))
        if b["t"] == 0:
            _poly(bev, pts, rgb, True)
        else:
            fade = 0.75 if b["t"] == 1 else 0.5
            _poly(bev, pts, tuple(int(c * fade) for c in rgb), False, 2)
    _poly(bev, _box_px(0.0, 0.0, 0.0, 4.7, 1.85), EGO_RGB, True)
    wps = np.asarray(row["waypoints"], np.float64).reshape(-1, 2)
    for p in _ego_to_px(wps):
        cv2.circle(bev, (int(round(p[0])), int(round(p[1]))), 4, WAYPOINT_RGB, -1, cv2.LINE_AA)
    tp = _ego_to_px(np.asarray(row["target_point"], np.float64).reshape(1, 2))[0]
    if 0 <= tp[0] < size and 0 <= tp[1] < size:
        c = (int(round(tp[0])), int(round(tp[1])))
        cv2.drawMarker(bev, c, TARGET_RGB, cv2.MARKER_TILTED_CROSS, 16, 3, cv2.LINE_AA)
    else:  # an arrow from the ego towards it, ending at the border
        start = np.array([size / 2, size - 4.0])
        d = tp - start
        d = d / max(np.linalg.norm(d), 1e-9)
        end = start + d * (size * 0.45)
        cv2.arrowedLine(
            bev,
            tuple(int(v) for v in start),
            tuple(int(v) for v in end),
            TARGET_RGB,
            2,
            cv2.LINE_AA,
            0,
            0.06,
        )

    panel = np.full((size, 300, 3), 24, np.uint8)
    light = row["traffic_light"]
    dist = lambda v: "" if v is None else f" ({v:.1f} m)"  # noqa: E731
    lines = [
        (f"{row['episode_id']}  frame {row['frame']}", (220, 220, 220)),
        (f"t = {row['time_s']:.1f} s", (220, 220, 220)),
        ("", None),
        (
            f"traffic light: {light}{dist(row['light_distance_m'])}",
            LIGHT_RGB.get(light, (220, 220, 220)),
        ),
        (
            f"stop sign: {'yes' + dist(row['stop_distance_m']) if row['stop_sign'] else 'no'}",
            (255, 80, 80) if row["stop_sign"] else (220, 220, 220),
        ),
        (f"weather: {row['weather']}", (220, 220, 220)),
        (f"behaviour: {row['behaviour']}", (220, 220, 220)),
        ("", None),
        (f"command: {row['command']}", (220, 220, 220)),
        (f"speed: {row['ego_speed']:.1f} m/s", (220, 220, 220)),
        (f"expert: {row['expert_reason']}", (220, 220, 220)),
        (f"boxes: {sum(b['t'] == 0 for b in row['boxes'] or [])} now", (220, 220, 220)),
        ("", None),
        ("red ego, yellow agents (t filled,", (160, 160, 160)),
        (" +0.5 s / +1.0 s outlined), cyan", (160, 160, 160)),
        (" people, blue waypoints, magenta", (160, 160, 160)),
        (" target point", (160, 160, 160)),
    ]
    for i, (text, rgb) in enumerate(lines):
        if text:
            cv2.putText(
                panel, text, (12, 30 + 26 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.5, rgb, 1, cv2.LINE_AA
            )
    return np.concatenate([left, bev, panel], 1)


def run(args: argparse.Namespace) -> int:
    row = read_row(Path(args.path), args.frame, args.episode)
    img = draw(row)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), cv2.cvtColor(img, cv2.COLOR_RGB2BGR)):
        raise UserError(f"{out}: cannot write the image (is the extension .png?)")
    print(f"wrote {out} ({row['episode_id']} frame {row['frame']})")
    return 0
