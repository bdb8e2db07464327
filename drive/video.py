"""`drive eval --record N`: an MP4 of a route at the policy's 2 Hz, played in real time.

Each frame: the camera as the model sees it (left), the LiDAR BEV (right: ground hits grey,
above-ground hits yellow, brightest for t, dimmer for t-1, t-2; the ego at the bottom centre) with the plan's
waypoints (blue) and the route's target point (green), and a status line (time, speed, route
completion, infractions so far). A frame with a new infraction gets a red border and its name.
OpenCV's mp4v codec; written to a temporary name and renamed when complete.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from schemas import codecs, ego_to_bev_px

SIDE_PX = 256
FPS = 2.0


class Recorder:
    """Collects frames of one route into `path` (see module docstring)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = self.path.with_name(f".{self.path.stem}.{os.getpid()}.tmp.mp4")
        fourcc = cv2.VideoWriter_fourcc(*"mp4v")
        self._writer = cv2.VideoWriter(str(self._tmp), fourcc, FPS, (2 * SIDE_PX, SIDE_PX + 40))
        self._seen_events = 0

    def add(self, frame, image_jpeg: bytes | None, lidar_png: bytes | None, plan, tracker) -> None:
        cam = (
            codecs.decode_image(image_jpeg)
            if image_jpeg is not None
            else np.zeros((SIDE_PX, SIDE_PX, 3), np.uint8)
        )
        bev = np.zeros((SIDE_PX, SIDE_PX, 3), np.uint8)
        if lidar_png is not None:
            lid = codecs.decode_lidar_bev(lidar_png).astype(np.float32)
            ground = np.clip(lid[..., 0] * 20, 0, 70)
            above = np.clip(lid[..., 1] * 1.0 + lid[..., 2] * 0.5 + lid[..., 3] * 0.25, 0, 1)
            bev = np.repeat(ground[..., None], 3, axis=2)
            yellow = np.array([255.0, 210.0, 60.0])
            bev = np.where(above[..., None] > 0, above[..., None] * yellow, bev).astype(np.uint8)
        pose = frame.ego.pose
        tp = pose.ego_from_world(np.array([frame.target_point_xy_m]))
        row, col = ego_to_bev_px(tp[:, 0], tp[:, 1])
        cv2.circle(bev, (int(col[0]), int(row[0])), 4, (0, 200, 0), -1)
        if plan is not None:
            wps = pose.ego_from_world(plan.points_xy_m[1:])
            row, col = ego_to_bev_px(wps[:, 0], wps[:, 1])
            for r, c in zip(row, col):
                cv2.circle(bev, (int(c), int(r)), 3, (60, 90, 255), -1)
        ego_r, ego_c = ego_to_bev_px(np.array([0.0]), np.array([0.0]))
        cv2.rectangle(
            bev,
            (int(ego_c[0]) - 7, int(ego_r[0]) - 19),
            (int(ego_c[0]) + 7, int(ego_r[0])),
            (220, 40, 40),
            2,
        )
        canvas = np.zeros((SIDE_PX + 40, 2 * SIDE_PX, 3), np.uint8)
        canvas[:SIDE_PX, :SIDE_PX] = cam
        canvas[:SIDE_PX, SIDE_PX:] = bev
        counts = tracker.counts()
        status = (
            f"t {frame.time_s:6.1f} s  v {frame.ego.speed_mps:4.1f} m/s  "
            f"RC {tracker.route_completion_pct:5.1f}%  "
            + " ".join(f"{k.replace('collision_', 'col_')}={n}" for k, n in sorted(counts.items()))
        )
        cv2.putText(canvas, status, (6, SIDE_PX + 16), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255,) * 3, 1)
        new = tracker.events[self._seen_events :]
        self._seen_events = len(tracker.events)
        if new:
            cv2.rectangle(canvas, (0, 0), (2 * SIDE_PX - 1, SIDE_PX - 1), (255, 0, 0), 4)
            names = ", ".join(e.kind for e in new)
            cv2.putText(
                canvas, names, (6, SIDE_PX + 34), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 60, 60), 1
            )
        self._writer.write(cv2.cvtColor(canvas, cv2.COLOR_RGB2BGR))

    def close(self) -> None:
        self._writer.release()
        if self._tmp.exists():
            os.replace(self._tmp, self.path)
