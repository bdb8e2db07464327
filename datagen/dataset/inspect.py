"""`datagen inspect`: draw stored frames the way the paper's Fig. 5 does; a frame, a video, Rerun.

    datagen inspect data/ --frame 10 --out frame.png
    datagen inspect data/shards/grid_small/grid_small-7-0000.parquet --frame 3 --out f.png
    datagen inspect data/ --episode grid_small-7-0000 --video episode.mp4 --speed 4
    datagen inspect data/ --episode grid_small-7-0000 --rerun episode.rrd   # then: rerun episode.rrd

Left: the camera crop above the current LiDAR BEV (grey: at-ground returns of t, t-1, t-2;
orange: above-ground returns at t). Middle: the BEV map (grey drivable area, white lane markings,
black other; the paper's colours), the ego (red), agents at t (yellow, filled) and at t+0.5 s,
t+1.0 s (outlines, fading), the expert's waypoints (blue) and the target point (magenta; an arrow
at the border if it lies off the grid). Right: traffic light, stop sign, weather, behaviour,
command, speed and the expert's reason.

`--frame N` counts rows across the shards in read order (`schemas.dataset.shard_files`); with
`--episode ID` it is that episode's `frame` number instead. `--video` draws every frame of the
episode (the first one in read order without `--episode`) into an H.264 `.mp4` (or VP9 `.webm`)
at the recording rate (2 Hz) times `--speed`; `--rerun` logs it to a Rerun recording
(datagen/dataset/recording.py).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

import schemas
from datagen.errors import UserError
from schemas import dataset, outputs
from schemas.video import CODECS, VideoError, VideoWriter, prepare_output

HELP = "draw a frame (PNG), an episode (video) or log it to Rerun: camera, LiDAR, BEV, labels"

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
    p.add_argument("--frame", type=int, default=0, help="row to draw")
    p.add_argument("--episode", default=None, help="pick this episode; --frame is its frame number")
    p.add_argument("--out", default=None, help="PNG to write (default: frame.png)")
    p.add_argument(
        "--video", metavar="MP4", default=None, help="draw every frame of the episode to a video"
    )
    p.add_argument(
        "--speed", type=float, default=1.0, help="video speed-up over the recording's 2 Hz"
    )
    p.add_argument(
        "--rerun", metavar="RRD", default=None, help="log the episode to a Rerun .rrd recording"
    )


def _ego_to_px(xy: np.ndarray) -> np.ndarray:
    """(..., 2) ego-frame points -> (..., 2) float (x=col, y=row) in the 2x BEV drawing."""
    row, col = schemas.ego_to_bev_px(xy[..., 0], xy[..., 1])
    return np.stack([col, row], -1) * SCALE


def _box_px(x: float, y: float, yaw: float, length: float, width: float) -> np.ndarray:
    return _ego_to_px(dataset.box_corners(x, y, yaw, length, width))


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
    try:
        return _run(args)
    except (dataset.DatasetError, schemas.SchemaError, VideoError) as e:
        raise UserError(str(e)) from None


def _run(args: argparse.Namespace) -> int:
    path = Path(args.path)
    # every output checked before any drawing (schemas/outputs.py)
    if args.video is not None:
        outputs.check_file(args.video, None, suffixes=tuple(CODECS))
    if args.rerun is not None:
        outputs.check_file(args.rerun, None, suffixes=(".rrd",))
    if args.video is None and args.rerun is None:
        out = outputs.check_file(args.out or "frame.png", None, suffixes=(".png",))
        return write_png(path, args.frame, args.episode, out)
    if args.out is not None:
        outputs.check_file(args.out, None, suffixes=(".png",))
    if not args.speed > 0:
        raise UserError(f"--speed must be > 0, got {args.speed}")
    episode = args.episode
    if episode is None:
        episode = dataset.episode_ids(path)[0]
        print(f"no --episode given: using the first one, {episode}", file=sys.stderr)
    if args.rerun is not None:
        from datagen.dataset import recording

        recording.check_installed()
    table = dataset.read_episode(path, episode)
    if args.out is not None:
        write_png(path, args.frame, episode, Path(args.out))
    if args.video is not None:
        write_video(table.to_pylist(), Path(args.video), args.speed)
    if args.rerun is not None:
        start = time.perf_counter()
        recording.write(table, Path(args.rerun))
        print(f"wrote {args.rerun} ({table.num_rows} frames, {time.perf_counter() - start:.1f} s)")
    return 0


def write_png(path: Path, frame: int, episode: str | None, out: Path) -> int:
    row = dataset.read_row(path, frame, episode)
    img = draw(row)
    partial = prepare_output(out)
    try:
        ok = cv2.imwrite(str(partial), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    except cv2.error:
        ok = False
    if not ok:
        partial.unlink(missing_ok=True)
        raise UserError(
            f"{out}: cannot write the image (is the extension .png and the folder writable?)"
        )
    partial.replace(out)
    print(f"wrote {out} ({row['episode_id']} frame {row['frame']})")
    return 0


def write_video(rows: list[dict], out: Path, speed: float = 1.0) -> None:
    """Every row (one episode's frames, in order) drawn by `draw` into the video `out`, played
    at the recording rate times `speed`; prints what it wrote and how long it took."""
    start = time.perf_counter()
    fps = schemas.FRAME_RATE_HZ * speed
    with VideoWriter(out, fps) as video:
        for row in rows:
            video.write(draw(row))
    seconds = time.perf_counter() - start
    print(
        f"wrote {out} ({video.frames} frames at {fps:g} fps, {video.codec}, "
        f"{out.stat().st_size / 1e6:.1f} MB) in {seconds:.1f} s"
    )
