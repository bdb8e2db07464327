"""`train show`: a frame's (or an episode's) inputs, predictions and truth (after Fig. 5).

    train show --ckpt runs/demo/last.pt --shards data/ --frame 10 --out runs/demo/show.png
    train show --ckpt runs/demo/last.pt --shards data/ --episode ID --video show.mp4 --speed 4

`--video` draws every frame of the episode (the first in frame order without `--episode`) into
an H.264 `.mp4` (or VP9 `.webm`; schemas/video.py) at the recording rate (2 Hz) times `--speed`.

Eight 256x256 panels, every BEV panel on the shards' grid (32 m ahead, 16 m each side, the
ego's box at the bottom centre):

    camera            | LiDAR BEV at t      | predicted: map, agents at t, | truth: map, agents at t,
                      |                     |   waypoints                  |   expert waypoints
    predicted density | predicted density   | truth: agents at t+0.5 s     | traffic rule and weather:
      t+0.5 s         |   t+1.0 s           |   and t+1.0 s                |   predicted and true

Colours as in the paper's Fig. 5: drivable area grey, lane markings white, background black,
ego red, other agents yellow, waypoints blue (expert waypoints green on the truth panel).
Frames are numbered as `pd.read_parquet(DIR)` orders them (training/data.py); with
`--episode`, `--frame` is that episode's frame number.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from schemas import BEV_SIZE_PX, FRAME_RATE_HZ, WEATHERS, ego_to_bev_px, outputs
from schemas.dataset import box_corners
from schemas.video import CODECS, VideoError, VideoWriter, prepare_output
from training import data
from training.checkpoint import check_sensors, load_checkpoint, model_from_checkpoint
from training.errors import UserError
from training.model import INPUTS
from training.targets import centres_to_objects, decode_centres, split_density

PANEL = BEV_SIZE_PX  # panel side, px: the BEV grid at its own resolution, 8 px/m
MAP_COLOURS = np.array([(0, 0, 0), (123, 123, 123), (228, 228, 228)], np.uint8)  # RGB
EGO, AGENT, WAYPOINT, EXPERT = (255, 0, 0), (223, 218, 8), (0, 0, 255), (0, 200, 0)
EGO_BOX = (1.0, 0.0, 0.0, 1.8, 4.5, 0.0)  # drawn only; the shards do not store the ego's size
VIDEO_BATCH = 16  # frames per forward pass while drawing a video


def _px(x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
    """Ego-frame points (m) -> OpenCV (column, row) pixel points on a panel, (N, 2) int32."""
    row, col = ego_to_bev_px(x_m, y_m)
    return np.stack([col, row], -1).round().astype(np.int32).reshape(-1, 2)


def _draw_box(img: np.ndarray, obj, colour, filled: bool = True) -> None:
    """obj: (score, x m, y m, width m, length m, yaw rad), ego frame, as targets.py decodes."""
    _, x, y, width, length, yaw = obj
    corners = box_corners(x, y, yaw, length, width)  # (4, 2) m, ego frame
    pts = _px(corners[:, 0], corners[:, 1])
    if filled:
        cv2.fillPoly(img, [pts], colour)
    else:
        cv2.polylines(img, [pts], True, colour, 1)


def _map_panel(classes: np.ndarray | None) -> np.ndarray:
    """(R, R) class ids -> coloured (256, 256, 3) panel; black if None."""
    if classes is None:
        return np.zeros((PANEL, PANEL, 3), np.uint8)
    img = MAP_COLOURS[classes]
    return cv2.resize(img, (PANEL, PANEL), interpolation=cv2.INTER_NEAREST)


def _scene(classes, objects, waypoints, colour_wp) -> np.ndarray:
    """Map, filled agent boxes, ego and waypoints on one panel."""
    img = _map_panel(classes)
    for obj in objects:
        _draw_box(img, obj, AGENT)
    _draw_box(img, EGO_BOX, EGO)
    for p in _px(waypoints[:, 0], waypoints[:, 1]):
        cv2.circle(img, tuple(int(v) for v in p), 3, colour_wp, -1)
    return img


def _density_panel(heat: np.ndarray | None, objects) -> np.ndarray:
    """Heatmap probabilities (R, R) in yellow, decoded boxes outlined."""
    img = np.zeros((PANEL, PANEL, 3), np.uint8)
    if heat is None:
        return img
    h = cv2.resize(heat.astype(np.float32), (PANEL, PANEL), interpolation=cv2.INTER_LINEAR)
    img = (h[..., None] * np.array(AGENT, np.float32)).clip(0, 255).astype(np.uint8)
    for obj in objects:
        _draw_box(img, obj, (255, 255, 255), filled=False)
    _draw_box(img, EGO_BOX, EGO)
    return img


def _lidar_panel(lidar: np.ndarray) -> np.ndarray:
    """LiDAR BEV at t: at-ground hits (ch0) grey, above-ground hits of t (ch1) yellow."""
    ground = (np.minimum(lidar[0], 5) * 40).astype(np.uint8)
    img = np.repeat(ground[..., None], 3, axis=2)
    img[lidar[1] > 0] = AGENT
    return img


def _text_panel(lines: list[str]) -> np.ndarray:
    img = np.full((PANEL, PANEL, 3), 32, np.uint8)
    for i, line in enumerate(lines):
        cv2.putText(img, line, (6, 22 + 19 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (240,) * 3, 1)
    return img


def _titled(img: np.ndarray, title: str) -> np.ndarray:
    bar = np.full((18, img.shape[1], 3), 255, np.uint8)
    cv2.putText(bar, title, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1)
    return np.concatenate([bar, img], axis=0)


def render(sample: dict, out: dict[str, torch.Tensor], output_px: int) -> np.ndarray:
    """The figure for one frame: `sample` from training/data.py, `out` the model's outputs for
    a batch of that one frame. Returns (2 * 274, 4 * 256, 3) uint8 RGB."""
    truths = [
        centres_to_objects(
            sample["centre_index"][t], sample["centre_reg"][t], sample["centre_mask"][t], output_px
        )
        for t in range(3)
    ]
    heat = objects = None
    if "detection" in out:
        heat_logits, reg = split_density(out["detection"].float())
        heat = heat_logits.sigmoid()[0]  # (3, R, R)
        objects = [decode_centres(heat[t][None], reg[0, t][None])[0] for t in range(3)]
        heat = heat.numpy()
    no_objects = np.zeros((0, 6), np.float32)
    bev = out["bev"][0].argmax(0).numpy() if "bev" in out else None
    waypoints = out["planning"][0].float().numpy()
    predicted = _scene(bev, objects[0] if objects else no_objects, waypoints, WAYPOINT)
    truth = _scene(sample["bev"], truths[0], sample["waypoints"], EXPERT)
    future = _map_panel(None)
    for t, colour in ((1, (160, 150, 0)), (2, AGENT)):
        for obj in truths[t]:
            _draw_box(future, obj, colour, filled=False)
    _draw_box(future, EGO_BOX, EGO)

    red, stop = (bool(v) for v in sample["traffic"])
    lines = [f"{sample['episode_id']}", f"frame {sample['frame']}, {sample['speed']:.1f} m/s", ""]
    if "traffic" in out:
        p_red, p_stop = out["traffic"][0].float().sigmoid().tolist()
        lines += [f"red light  p={p_red:.2f}  true: {'yes' if red else 'no'}"]
        lines += [f"stop sign  p={p_stop:.2f}  true: {'yes' if stop else 'no'}"]
    else:
        lines += ["(no traffic rule head)"]
    true_weather = WEATHERS[int(sample["weather"])]
    if "weather" in out:
        p = out["weather"][0].float().softmax(0)
        k = int(p.argmax())
        lines += [f"weather {WEATHERS[k]} ({p[k]:.2f})", f"  true: {true_weather}"]
    else:
        lines += ["(no weather head)", f"  true weather: {true_weather}"]
    err = np.linalg.norm(waypoints - sample["waypoints"], axis=1)
    lines += ["", f"waypoint error m: {' '.join(f'{e:.2f}' for e in err)}"]

    panels = [
        _titled(cv2.resize(sample["image"].transpose(1, 2, 0), (PANEL, PANEL)), "camera"),
        _titled(_lidar_panel(sample["lidar"]), "LiDAR BEV at t"),
        _titled(predicted, "predicted: map, agents t, waypoints"),
        _titled(truth, "truth: map, agents t, expert"),
        _titled(
            _density_panel(heat[1] if heat is not None else None, objects and objects[1]),
            "predicted t+0.5 s",
        ),
        _titled(
            _density_panel(heat[2] if heat is not None else None, objects and objects[2]),
            "predicted t+1.0 s",
        ),
        _titled(future, "truth t+0.5 s (dark), t+1.0 s"),
        _titled(_text_panel(lines), "traffic rule, weather"),
    ]
    rows = [np.concatenate(panels[i : i + 4], axis=1) for i in (0, 4)]
    return np.concatenate(rows, axis=0)


def _episode_frames(index, episode: str | None):
    """The frames of `episode` (default: the first in frame order) in `index`, by frame."""
    if episode is None:
        episode = index.episode_id.iloc[0]
        print(f"no --episode given: using the first one, {episode}", file=sys.stderr)
    frames = index[index.episode_id == episode].sort_values("frame")
    if frames.empty:
        some = ", ".join(index.episode_id.unique()[:4])
        raise UserError(f"--episode {episode!r}: not in the shards (they hold {some}, ...)")
    return frames


def _forward(model, samples: list[dict]) -> dict[str, torch.Tensor]:
    inputs = [torch.as_tensor(np.stack([np.asarray(s[k]) for s in samples])) for k in INPUTS]
    return model(*inputs)


@torch.no_grad()
def run(args) -> int:
    if getattr(args, "video", None):  # every output checked before the drawing
        outputs.check_file(args.video, "--video", suffixes=tuple(CODECS))
    elif args.out:
        outputs.check_file(args.out, "--out", suffixes=(".png",))
    state = load_checkpoint(args.ckpt)
    model = model_from_checkpoint(state, "cpu")
    index = data.scan(args.shards)
    check_sensors(state, data.sensor_config(index), args.shards, args.ckpt)
    if getattr(args, "video", None):
        try:
            return write_video(model, _episode_frames(index, args.episode), args.video, args.speed)
        except VideoError as e:
            raise UserError(str(e)) from None
    if getattr(args, "episode", None) is not None:
        frames = _episode_frames(index, args.episode)
        hit = frames.index[frames.frame == args.frame]
        if not len(hit):
            raise UserError(f"--frame {args.frame}: episode {args.episode!r} has no such frame")
        args.frame = int(index.index.get_loc(hit[0]))
    if not 0 <= args.frame < len(index):
        raise UserError(f"--frame {args.frame}: the shards hold frames 0..{len(index) - 1}")
    sample = data.read_frames(
        index.iloc[[args.frame]], model.cfg.output_px, model.cfg.single_frame_lidar
    )[0]
    figure = render(sample, _forward(model, [sample]), model.cfg.output_px)
    path = Path(args.out) if args.out else Path(args.ckpt).parent / f"show-{args.frame}.png"
    try:
        partial = prepare_output(path)
    except VideoError as e:
        raise UserError(str(e)) from None
    if not cv2.imwrite(str(partial), cv2.cvtColor(figure, cv2.COLOR_RGB2BGR)):
        partial.unlink(missing_ok=True)
        raise UserError(f"{path}: could not write the PNG (is the suffix .png?)")
    partial.replace(path)
    print(f"wrote {path} (frame {args.frame}: {sample['episode_id']} frame {sample['frame']})")
    return 0


def write_video(model, frames, out: str | Path, speed: float = 1.0) -> int:
    """The model's predictions over `frames` (one episode's rows of the frame index, in order)
    drawn by `render` into the video `out` at the recording rate times `speed`."""
    start = time.perf_counter()
    fps = FRAME_RATE_HZ * speed
    with VideoWriter(out, fps) as video:
        for i in range(0, len(frames), VIDEO_BATCH):
            samples = data.read_frames(
                frames.iloc[i : i + VIDEO_BATCH], model.cfg.output_px, model.cfg.single_frame_lidar
            )
            out_batch = _forward(model, samples)
            for k, sample in enumerate(samples):
                one = {name: value[k : k + 1] for name, value in out_batch.items()}
                video.write(render(sample, one, model.cfg.output_px))
    size_mb = Path(out).stat().st_size / 1e6
    print(
        f"wrote {out} ({video.frames} frames of {frames.episode_id.iloc[0]} at {fps:g} fps, "
        f"{video.codec}, {size_mb:.1f} MB) in {time.perf_counter() - start:.1f} s"
    )
    return 0
