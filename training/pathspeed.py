"""TransFuser++'s output (Jaeger et al., "Hidden Biases of End-to-End Driving Models", ICCV
2023): a path of spatial checkpoints and a target speed predicted as classes, in place of
timed waypoints, which average "stand" and "go" into a short plan where the two are alike.

- the path: PATH_POINTS points PATH_SPACING_M apart along where the ego drives next (the
  episode's future ego positions after t, in the ego frame at t; a point farther than the
  episode's recorded future reaches is masked);
- the target speed: the mean speed over the next second (the label waypoints' +1.0 s point's
  distance / 1 s), as the nearest of SPEED_CLASSES_MPS; class 0 is "stand" (the brake).

`to_waypoints` turns both back into the 4 timed waypoints the controller drives
(drive/controller.py tracks the speed the first two imply): stand if "stand" is the most
likely class, else points on the path at v * (0.5, 1.0, 1.5, 2.0 s) with v the expected speed
over the moving classes.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from schemas import WAYPOINT_TIMES_S

PATH_POINTS = 10
PATH_SPACING_M = 1.0
SPEED_CLASSES_MPS = (0.0, 1.0, 2.5, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0)


def future_path(xy_ego: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The path label from the ego's future positions `xy_ego` (K, 2) (ego frame at t, in
    time order, after t): the polyline from the origin through them sampled every
    PATH_SPACING_M -> points (PATH_POINTS, 2) float32 and mask (PATH_POINTS,) bool (False
    beyond the polyline's length)."""
    pts = np.concatenate([np.zeros((1, 2)), np.asarray(xy_ego, np.float64).reshape(-1, 2)])
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    want = PATH_SPACING_M * np.arange(1, PATH_POINTS + 1)
    mask = want <= s[-1]
    out = np.zeros((PATH_POINTS, 2))
    if mask.any():
        keep = np.concatenate([[True], seg > 1e-6])  # no zero-length segments for interp
        out[:, 0] = np.interp(want, s[keep], pts[keep, 0])
        out[:, 1] = np.interp(want, s[keep], pts[keep, 1])
    out[~mask] = 0.0
    return out.astype(np.float32), mask


def speed_class(waypoints: np.ndarray) -> np.ndarray:
    """(N,) int64: the nearest SPEED_CLASSES_MPS entry to the mean speed over the first second
    of label waypoints (N, 4, 2) (a frame below 0.5 m/s is class 0, "stand")."""
    k = WAYPOINT_TIMES_S.index(1.0)
    v = np.linalg.norm(np.asarray(waypoints)[:, k], axis=1) / WAYPOINT_TIMES_S[k]
    classes = np.asarray(SPEED_CLASSES_MPS)
    c = np.abs(v[:, None] - classes[None]).argmin(1)
    return np.where(v < 0.5, 0, np.maximum(c, 1)).astype(np.int64)


class PathSpeedHead(nn.Module):
    """Feature (B, C) -> path (B, PATH_POINTS, 2) m by a GRU fed the previous point and the
    target point (as the paper's planner, training.heads.PlanningHead), and speed-class
    logits (B, len(SPEED_CLASSES_MPS)) by a 2-layer MLP."""

    def __init__(self, in_dim: int, hidden: int = 128):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU(inplace=True))
        self.gru = nn.GRUCell(input_size=4, hidden_size=hidden)
        self.delta = nn.Linear(hidden, 2)
        self.speed = nn.Sequential(
            nn.Linear(in_dim, hidden),
            nn.ReLU(inplace=True),
            nn.Linear(hidden, len(SPEED_CLASSES_MPS)),
        )

    def forward(self, f: torch.Tensor, target_point: torch.Tensor) -> dict[str, torch.Tensor]:
        h = self.mlp(f)
        p = f.new_zeros(f.shape[0], 2)
        path = []
        for _ in range(PATH_POINTS):
            h = self.gru(torch.cat([p, target_point], dim=1), h)
            p = p + self.delta(h)
            path.append(p)
        return {"path": torch.stack(path, dim=1), "speed_logits": self.speed(f)}


def loss(out: dict[str, torch.Tensor], batch: dict[str, torch.Tensor]) -> torch.Tensor:
    """(B,) per-frame loss: L1 over the path's unmasked points (mean) + speed cross-entropy."""
    mask = batch["path_mask"].float()
    l1 = ((out["path"] - batch["path"]).abs().sum(2) * mask).sum(1) / mask.sum(1).clamp(min=1)
    ce = nn.functional.cross_entropy(out["speed_logits"], batch["speed_class"], reduction="none")
    return l1 + ce


def to_waypoints(out: dict[str, torch.Tensor]) -> torch.Tensor:
    """The 4 timed waypoints (B, 4, 2) of a path and speed classes (module docstring)."""
    path, logits = out["path"], out["speed_logits"]
    p = logits.float().softmax(1)
    classes = torch.tensor(SPEED_CLASSES_MPS, device=p.device)
    moving = p[:, 1:]
    v = (moving * classes[1:]).sum(1) / moving.sum(1).clamp(min=1e-6)
    v = torch.where(p.argmax(1) == 0, torch.zeros_like(v), v)
    times = torch.tensor(WAYPOINT_TIMES_S, device=p.device)
    want = v[:, None] * times[None]  # (B, 4) arc lengths
    pts = torch.cat([path.new_zeros(path.shape[0], 1, 2), path.float()], dim=1)  # (B, P+1, 2)
    seg = (pts[:, 1:] - pts[:, :-1]).norm(dim=2)
    s = torch.cat([seg.new_zeros(seg.shape[0], 1), seg.cumsum(1)], dim=1)  # (B, P+1)
    idx = torch.searchsorted(s.contiguous(), want.contiguous()).clamp(1, PATH_POINTS)
    s0, s1 = s.gather(1, idx - 1), s.gather(1, idx)
    frac = ((want - s0) / (s1 - s0).clamp(min=1e-6))[..., None]  # beyond the end: extrapolate
    a = pts.gather(1, (idx - 1)[..., None].expand(-1, -1, 2))
    b = pts.gather(1, idx[..., None].expand(-1, -1, 2))
    return a + frac * (b - a)
