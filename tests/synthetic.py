"""Small synthetic shards that satisfy the v1 contract, for tests that need no simulator."""

from __future__ import annotations

import numpy as np
import pyarrow as pa

import schemas
from schemas import codecs


def synthetic_table(
    n_frames: int = 4,
    episode_id: str = "synth-0-0",
    town: str = "synth",
    weather: str = "sunny",
    seed: int = 0,
    noise: bool = True,
) -> pa.Table:
    """`n_frames` consecutive frames of one episode with random but valid content; `noise=False`
    makes the images flat (a few ms a frame instead of ~70: for tests of hundreds of episodes)."""
    rng = np.random.default_rng(seed)
    rows = []
    for i in range(n_frames):
        if noise:
            image = rng.integers(0, 255, (256, 256, 3), dtype=np.uint8)
            bev = rng.integers(0, 4, (256, 256, 4), dtype=np.uint8)
            sem = rng.integers(0, 3, (256, 256), dtype=np.uint8)
        else:
            image = np.full((256, 256, 3), (seed + i) % 256, dtype=np.uint8)
            bev = np.full((256, 256, 4), (seed + i) % 4, dtype=np.uint8)
            sem = np.full((256, 256), (seed + i) % 3, dtype=np.uint8)
        boxes = [
            {
                "track_id": f"veh{j}",
                "cls": "vehicle",
                "t": t,
                "x": float(5 + 3 * j + t),
                "y": float(j - 1),
                "yaw": 0.1 * j,
                "length": 4.5,
                "width": 1.8,
                "speed": 5.0,
                "lidar_points": 40 if t == 0 else 0,
            }
            for j in range(2)
            for t in range(3)
        ]
        rows.append(
            {
                "episode_id": episode_id,
                "frame": i,
                "time_s": 10.0 + 0.5 * i,
                "town": town,
                "weather": weather,
                "behaviour": "cautious" if weather in ("rainy", "foggy") else "normal",
                "ego_x": 100.0 + i,
                "ego_y": 50.0,
                "ego_yaw": 0.0,
                "ego_speed": 2.0,
                "command": "follow",
                "target_point": [20.0, 0.0],
                "waypoints": [1.0, 0.0, 2.0, 0.0, 3.0, 0.0, 4.0, 0.0],
                "traffic_light": "red" if i % 2 else "none",
                "light_distance_m": 12.0 if i % 2 else None,
                "stop_sign": False,
                "stop_distance_m": None,
                "expert_reason": "none",
                "image": codecs.encode_image(image),
                "lidar_bev": codecs.encode_lidar_bev(bev),
                "bev_semantic": codecs.encode_bev_semantic(sem),
                "boxes": boxes,
            }
        )
    meta = schemas.file_metadata(
        generator_version="test", config={}, network_sha256="0" * 64, seed=seed
    )
    return pa.Table.from_pylist(rows, schema=schemas.schema(meta))
