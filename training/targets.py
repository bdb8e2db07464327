"""Dense training targets rendered from the shards' `boxes`, and their inverse for predictions.

The dense heads predict on an R x R grid covering the BEV area of the shards (schemas.bev:
32 m ahead, 16 m to each side; row 0 is 32 m ahead, column 0 is 16 m to the left), so one
output pixel is 32 / R m. For each timestep t (t, t+0.5 s, t+1.0 s), following CenterNet
(Zhou et al. 2019):

- heatmap (R, R) float32: a Gaussian peak of 1 at each agent's centre pixel, sigma from
  CenterNet's `gaussian_radius` of the box's footprint in pixels; overlapping peaks take the max.
- centres, at most MAX_OBJECTS per timestep (CenterNet's sparse encoding, so a sample costs
  kilobytes instead of a dense 6 x R x R regression map): centre_index (K,) int64, the flat
  index row * R + col of the centre pixel; centre_reg (K, 6) float32: dx, dy, the centre's
  offset from the centre of its pixel along ego x and y in output pixels (in [-0.5, 0.5]),
  log w, log l (box width and length, log metres), sin yaw, cos yaw; centre_mask (K,) float32,
  1 for a real entry and 0 for padding.

All agent classes share one heatmap (the paper's density map has one channel per timestep).
Agents beyond MAX_OBJECTS in a timestep are dropped, nearest to the ego kept.

Only agents the LiDAR sees are targets (`visible_boxes`), as in TransFuser++ (Jaeger et al.
2023, carla_garage `num_lidar_hits_for_detection`): an agent counts, at every timestep, when its
box at t has at least MIN_LIDAR_POINTS returns. The same targets feed the loss and `train
eval`'s AP, so the model is neither trained nor scored on agents hidden behind others.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from schemas import BEV_AHEAD_M, BEV_PX_PER_M, BEV_SIDE_M, BEV_SIZE_PX, BOX_TIMESTEPS
from training.heads import DENSITY_CHANNELS

N_T = len(BOX_TIMESTEPS)
N_REG = DENSITY_CHANNELS - 1  # dx, dy, log w, log l, sin, cos
MAX_OBJECTS = 128  # per timestep (CenterNet's max_objs)
GRID_M = BEV_SIZE_PX / BEV_PX_PER_M  # 32 m: the side of the (square) BEV area
MIN_LIDAR_POINTS = 8
"""LiDAR returns at t an agent needs to be a detection target: TransFuser++'s first release
keeps boxes with more than `num_lidar_hits_for_detection = 7` hits."""


def visible_boxes(boxes: dict[str, np.ndarray], min_lidar_points: int) -> dict[str, np.ndarray]:
    """The boxes of one frame whose agent has >= `min_lidar_points` LiDAR returns at t.

    `boxes` holds equal-length arrays with at least track_id, t and lidar_points (the shards'
    box fields); future boxes (t > 0, whose lidar_points is 0 by the schema) follow their
    agent's box at t, and an agent without a box at t is dropped.
    """
    if min_lidar_points <= 0 or not len(boxes["t"]):
        return boxes
    ids = boxes["track_id"]
    seen = set(ids[(boxes["t"] == 0) & (boxes["lidar_points"] >= min_lidar_points)].tolist())
    keep = np.fromiter((i in seen for i in ids.tolist()), bool, len(ids))  # ~10x np.isin's speed
    return {k: v[keep] for k, v in boxes.items()}


def px_per_m(output_px: int) -> float:
    """Output pixels per metre for an R x R map of the BEV area."""
    return output_px / GRID_M


def gaussian_radius(height_px: float, width_px: float, min_overlap: float = 0.7) -> float:
    """CenterNet's radius: how far a corner may move so a box still overlaps its truth by
    `min_overlap` IoU (the smallest root of three quadratic cases, as in CornerNet's code)."""
    h, w = height_px, width_px
    b1, c1 = h + w, w * h * (1 - min_overlap) / (1 + min_overlap)
    r1 = (b1 + math.sqrt(b1**2 - 4 * c1)) / 2
    b2, c2 = 2 * (h + w), (1 - min_overlap) * w * h
    r2 = (b2 + math.sqrt(b2**2 - 16 * c2)) / 2
    a3 = 4 * min_overlap
    b3, c3 = -2 * min_overlap * (h + w), (min_overlap - 1) * w * h
    r3 = (b3 + math.sqrt(b3**2 - 4 * a3 * c3)) / 2
    return min(r1, r2, r3)


def _draw_gaussian(heatmap: np.ndarray, row: int, col: int, radius: int) -> None:
    """Max a (2r+1)^2 Gaussian with sigma = (2r+1)/6 into `heatmap` at (row, col), in place."""
    sigma = (2 * radius + 1) / 6
    d = np.arange(-radius, radius + 1)
    g = np.exp(-(d[:, None] ** 2 + d[None, :] ** 2) / (2 * sigma**2))
    R = heatmap.shape[0]
    r0, r1 = max(0, row - radius), min(R, row + radius + 1)
    c0, c1 = max(0, col - radius), min(R, col + radius + 1)
    patch = g[r0 - row + radius : r1 - row + radius, c0 - col + radius : c1 - col + radius]
    np.maximum(heatmap[r0:r1, c0:c1], patch, out=heatmap[r0:r1, c0:c1])


def render_density(boxes: dict[str, np.ndarray], output_px: int) -> dict[str, np.ndarray]:
    """Heatmap and centre targets for one frame.

    Args:
        boxes: one frame's boxes as arrays of equal length N: t (int), x, y (m, ego at t),
            yaw (rad, ego at t), length, width (m).
        output_px: R.
    Returns:
        heatmap (3, R, R) float32; centre_index (3, K) int64; centre_reg (3, K, 6) float32;
        centre_mask (3, K) float32; K = MAX_OBJECTS.
    """
    R, ppm = output_px, px_per_m(output_px)
    heatmap = np.zeros((N_T, R, R), np.float32)
    index = np.zeros((N_T, MAX_OBJECTS), np.int64)
    reg = np.zeros((N_T, MAX_OBJECTS, N_REG), np.float32)
    mask = np.zeros((N_T, MAX_OBJECTS), np.float32)
    row_f = (BEV_AHEAD_M - boxes["x"]) * ppm  # continuous pixel coordinates
    col_f = (BEV_SIDE_M - boxes["y"]) * ppm
    count = [0] * N_T
    for k in np.argsort(np.hypot(boxes["x"], boxes["y"]), kind="stable"):
        row, col, t = int(math.floor(row_f[k])), int(math.floor(col_f[k])), int(boxes["t"][k])
        if not (0 <= row < R and 0 <= col < R) or count[t] == MAX_OBJECTS:
            continue  # centre outside the grid, or too many agents
        length, width, yaw = float(boxes["length"][k]), float(boxes["width"][k]), boxes["yaw"][k]
        radius = max(0, int(gaussian_radius(length * ppm, width * ppm)))
        _draw_gaussian(heatmap[t], row, col, radius)
        j = count[t]
        index[t, j] = row * R + col
        reg[t, j] = (
            row + 0.5 - row_f[k],  # dx: +x is up the grid (smaller row)
            col + 0.5 - col_f[k],  # dy: +y is left (smaller column)
            math.log(max(width, 1e-2)),
            math.log(max(length, 1e-2)),
            math.sin(yaw),
            math.cos(yaw),
        )
        mask[t, j] = 1.0
        count[t] += 1
    return {"heatmap": heatmap, "centre_index": index, "centre_reg": reg, "centre_mask": mask}


def gather_centres(regression: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Regression maps (B, T, 6, R, R) read at centre indices (B, T, K) -> (B, T, K, 6)."""
    B, T, C, R, _ = regression.shape
    flat = regression.reshape(B, T, C, R * R)
    picked = flat.gather(3, index[:, :, None, :].expand(B, T, C, index.shape[2]))
    return picked.transpose(2, 3)


def centres_to_objects(
    index: np.ndarray, reg: np.ndarray, mask: np.ndarray, output_px: int
) -> np.ndarray:
    """One timestep's centre targets (K,), (K, 6), (K,) -> (N, 6) objects as `decode_centres`
    gives them, with score 1: the ground truth in the same form as predictions."""
    keep = mask > 0
    i = index[keep]
    row, col, r = i // output_px, i % output_px, reg[keep]
    ppm = px_per_m(output_px)
    objs = np.stack(
        [
            np.ones(len(i)),
            BEV_AHEAD_M - (row + 0.5 - r[:, 0]) / ppm,
            BEV_SIDE_M - (col + 0.5 - r[:, 1]) / ppm,
            np.exp(r[:, 2]),
            np.exp(r[:, 3]),
            np.arctan2(r[:, 4], r[:, 5]),
        ],
        axis=1,
    )
    return objs.astype(np.float32).reshape(-1, 6)


def split_density(out: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The detection head's (B, 21, R, R) -> heatmap logits (B, 3, R, R), regression
    (B, 3, 6, R, R)."""
    B, _, R, _ = out.shape
    out = out.view(B, N_T, DENSITY_CHANNELS, R, R)
    return out[:, :, 0], out[:, :, 1:]


def decode_centres(
    heat: torch.Tensor,
    regression: torch.Tensor,
    threshold: float = 0.3,
    max_objects: int = 100,
) -> list[np.ndarray]:
    """Objects from one timestep's maps: local maxima of the heatmap (3x3 max pooling, as in
    CenterNet), at most `max_objects` above `threshold`, placed with their regression.

    Args:
        heat: (B, R, R) heatmap probabilities (or a 0/1 mask, for ground truth).
        regression: (B, 6, R, R), the head's regression channels for that timestep.
    Returns:
        per frame, an (N, 6) float32 array of (score, x m, y m, width m, length m, yaw rad),
        ego frame, highest score first.
    """
    B, R, _ = heat.shape
    ppm = px_per_m(R)
    peak = heat == torch.nn.functional.max_pool2d(heat[:, None], 3, 1, 1)[:, 0]
    scores = torch.where(peak, heat, torch.zeros_like(heat)).flatten(1)
    top, idx = scores.topk(min(max_objects, R * R), dim=1)
    result = []
    for b in range(B):
        keep = top[b] >= threshold
        s, i = top[b][keep], idx[b][keep]
        row, col = (i // R).float(), (i % R).float()
        reg = regression[b].flatten(1)[:, i].float()  # (6, N)
        x = BEV_AHEAD_M - (row + 0.5 - reg[0]) / ppm
        y = BEV_SIDE_M - (col + 0.5 - reg[1]) / ppm
        yaw = torch.atan2(reg[4], reg[5])
        objs = torch.stack([s.float(), x, y, reg[2].exp(), reg[3].exp(), yaw], dim=1)
        result.append(objs.cpu().numpy().astype(np.float32))
    return result
